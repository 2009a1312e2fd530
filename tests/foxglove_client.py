"""The client's side of the Foxglove WebSocket protocol, as the live-view tests read a view: the
channels it advertises, a subscription to some of them, and the message frames that come back.

Written from the protocol's description (foxglove-sdk's ``ws-protocol``): after ``serverInfo``
the server advertises its channels in JSON text frames; a client subscribes with its own ids; a
message arrives as a binary frame of opcode 1, the subscription id (u32), the log time (u64,
nanoseconds) and the payload, little-endian.
"""

from __future__ import annotations

import json
import struct
from collections.abc import Iterable, Iterator
from typing import Any

__all__ = ["SUBPROTOCOL", "WAIT", "Channel", "advertised", "frames", "messages", "subscribe"]

SUBPROTOCOL = "foxglove.sdk.v1"
"""foxglove-sdk 0.30's name for the protocol (foxglove.websocket.v1)."""

WAIT = 10.0
"""Seconds one frame may take to come: a live view's threads on a loaded host (the live-view
tests' own patience, twice tests.conftest's)."""

Channel = dict[str, Any]
"""An advertised channel as the server describes it (``id``, ``topic``, ``schemaName``...)."""

_MESSAGE_DATA = 1
_HEADER = struct.Struct("<BIQ")


def advertised(ws: Any, count: int) -> dict[str, Channel]:
    """The server's channels by topic, once ``count`` are advertised (after its serverInfo)."""
    info = json.loads(ws.recv(timeout=WAIT))
    assert info["op"] == "serverInfo"
    channels: dict[str, Channel] = {}
    while len(channels) < count:
        for channel in json.loads(ws.recv(timeout=WAIT)).get("channels", []):
            channels[channel["topic"]] = channel
    return channels


def subscribe(ws: Any, channels: Iterable[Channel]) -> dict[int, Channel]:
    """Subscribe to ``channels``, each with its channel id as the subscription id; returns the
    channels by that id."""
    subs = {channel["id"]: channel for channel in channels}
    ws.send(
        json.dumps({"op": "subscribe", "subscriptions": [{"id": i, "channelId": i} for i in subs]})
    )
    return subs


def frames(ws: Any, subs: dict[int, Channel]) -> Iterator[tuple[Channel, int, bytes]]:
    """(channel, log time in ns, payload) of every message frame, for as long as asked; a
    TimeoutError when the server sends nothing for :data:`WAIT` seconds."""
    while True:
        frame = ws.recv(timeout=WAIT)
        if isinstance(frame, bytes) and frame[0] == _MESSAGE_DATA:
            _, sub, log_time = _HEADER.unpack_from(frame)
            yield subs[sub], log_time, frame[_HEADER.size :]


def messages(ws: Any, subs: dict[int, Channel], typestore: Any) -> Iterator[tuple[str, Any, int]]:
    """(topic, message decoded by ``typestore``, log time in ns) of every message frame."""
    for channel, log_time, payload in frames(ws, subs):
        yield channel["topic"], typestore.deserialize_cdr(payload, channel["schemaName"]), log_time

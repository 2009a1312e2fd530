"""The live view, checked from the other end: a real WebSocket client (``websockets``) speaking
the Foxglove protocol sees the channels advertised and receives messages that decode."""

from __future__ import annotations

import json
import struct
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.typesys import Stores, get_typestore
from websockets.sync.client import connect

from biris_hw import ros2
from biris_hw.liveview import LiveView
from biris_hw.replay import ReplayServer
from tests.test_record_support import cloud_xyz, synthetic_scans, write_raw

STANDARD = get_typestore(Stores.ROS2_HUMBLE)
SUBPROTOCOL = "foxglove.sdk.v1"  # foxglove-sdk 0.30's name for foxglove.websocket.v1
WAIT = 10.0


def _advertised(ws: Any) -> dict[str, dict[str, Any]]:
    info = json.loads(ws.recv(timeout=WAIT))
    assert info["op"] == "serverInfo"
    channels: dict[str, dict[str, Any]] = {}
    while len(channels) < len(ros2.TOPICS):
        message = json.loads(ws.recv(timeout=WAIT))
        for channel in message.get("channels", []):
            channels[channel["topic"]] = channel
    return channels


def test_live_view_advertises_and_delivers_decodable_messages(tmp_path: Path) -> None:
    scans = synthetic_scans(4, n_acq=80, samples=32)  # more acquisitions than one batch takes
    path = write_raw(tmp_path / "run.mcap", scans)
    replay = ReplayServer(path, speed=None, autostart=False)
    view = LiveView(replay, port=0, status_period_s=0.05, sweep_period_s=0.0)
    with replay, view, connect(f"ws://127.0.0.1:{view.port}", subprotocols=[SUBPROTOCOL]) as ws:
        channels = _advertised(ws)
        assert set(channels) == set(ros2.TOPICS)
        for topic, channel in channels.items():
            assert channel["encoding"] == "cdr"
            assert channel["schemaName"] == ros2.TOPICS[topic]
            assert channel["schemaEncoding"] == "ros2msg"
            text = STANDARD.generate_msgdef(channel["schemaName"], ros_version=2)[0]
            assert channel["schema"] == text
        subs = dict(enumerate(channels.values()))
        ws.send(
            json.dumps(
                {
                    "op": "subscribe",
                    "subscriptions": [{"id": i, "channelId": c["id"]} for i, c in subs.items()],
                }
            )
        )
        acquisitions = sum(s.n_acq for s in scans)
        want = {"/biris/points": len(scans), "/biris/profile": acquisitions, "/tf": acquisitions}
        swept = sum(int((s.range_mm > 0).sum()) for s in scans)
        got: dict[str, list[Any]] = {}
        started = False
        while (
            any(len(got.get(t, [])) < n for t, n in want.items())
            or not all(t in got for t in ("/diagnostics", "/tf_static"))
            or sum(m.width for m in got.get("/biris/sweep", [])) < swept
        ):
            if not started and view.published.get("/diagnostics"):
                replay.start()  # the subscriptions are in place
                started = True
            frame = ws.recv(timeout=WAIT)
            if not isinstance(frame, bytes) or frame[0] != 1:
                continue
            sub, _log_time = struct.unpack_from("<IQ", frame, 1)
            channel = subs[sub]
            message = STANDARD.deserialize_cdr(frame[13:], channel["schemaName"])
            got.setdefault(channel["topic"], []).append(message)
    for scan, cloud in zip(scans, got["/biris/points"], strict=False):
        np.testing.assert_allclose(cloud_xyz(cloud), scan.points(), atol=1e-5)
    # /biris/sweep: each message the acquisitions since the previous one, every point sent once
    # (not the whole sweep again each time), which put together are the scans' clouds
    sweep = got["/biris/sweep"]
    assert len(sweep) > 1 and all(m.header.frame_id == ros2.VEHICLE_FRAME for m in sweep)
    assert all(len(m.data) == m.width * m.point_step for m in sweep)
    assert sum(m.width for m in sweep) == swept
    pieces = np.concatenate([cloud_xyz(m) for m in sweep])
    np.testing.assert_allclose(pieces, np.concatenate([s.points() for s in scans]), atol=1e-5)
    assert got["/diagnostics"][0].status[0].name == "biris: server"


def test_the_layout_keeps_the_sweep_pieces_long_enough_to_show_a_sweep() -> None:
    """docs/foxglove-layout.json shows every cloud topic in its 3-D panel; /biris/sweep carries
    only the points since its previous message, so the panel must keep them (a decay time)."""
    layout = json.loads((Path(__file__).parents[1] / "docs" / "foxglove-layout.json").read_text())
    topics = layout["configById"]["3D!biris"]["topics"]
    clouds = {t for t, msgtype in ros2.TOPICS.items() if msgtype == ros2.POINT_CLOUD2}
    assert clouds <= set(topics)
    assert topics["/biris/sweep"]["decayTime"] > 0

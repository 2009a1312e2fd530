"""The vehicle's pose from a ROS 2 base on Zenoh: odometry or a transform, in CDR.

A ROS 2 base publishes its pose as ``nav_msgs/msg/Odometry`` (``/odom``) or as the ``odom ->
base_link`` transform. Through rmw_zenoh each topic is a Zenoh key
``<domain>/<topic>/<type>/<type hash>`` (``0/odom/nav_msgs::msg::dds_::Odometry_/RIHS01_...``:
subscribe to ``0/odom/**``); through zenoh-bridge-ros2dds it is the topic's name without its
leading slash (``odom``). Either way the payload is the message in CDR, which
:func:`biris_hw.io.codec.decode_pose` reads: :func:`subscribe_poses` puts every sample it
receives into a :class:`~biris_hw.io.pose.PoseBuffer`, as it arrives (no thread of ours: Zenoh's
callback adds it). docs/moving.md, "The pose input", has the wire format.

Zenoh is imported on first use (the ``net`` extra), so importing this module needs nothing.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Mapping, Sequence
from types import TracebackType
from typing import TYPE_CHECKING, Any

from biris_hw.errors import RequestError
from biris_hw.io.codec import POSE_TYPES, WireError, decode_pose
from biris_hw.io.pose.buffer import PoseBuffer

if TYPE_CHECKING:
    from biris_hw.io.net.lifetime import SessionLife

__all__ = ["PoseSubscription", "subscribe_poses"]

log = logging.getLogger(__name__)


class PoseSubscription:
    """A Zenoh subscription that feeds a :class:`PoseBuffer` (made by :func:`subscribe_poses`).

    Counts what it saw: :attr:`received` payloads, :attr:`taken` into the buffer, :attr:`other`
    (the frames were not those asked for), :attr:`malformed` (not a pose message: the error is
    kept in :attr:`last_error`); a sample the buffer refused (out of order) is counted there. A
    payload is counted in :attr:`received` once it has been handled, together with its outcome,
    so that a reader who sees ``received`` reach n also sees the buffer as those n left it (a
    payload counted on arrival could still be on its way into the buffer).
    Close it (or leave its ``with`` block) to unsubscribe; a session it opened itself is closed
    with it.
    """

    def __init__(
        self,
        buffer: PoseBuffer,
        msgtype: str | None,
        frame_id: str | None,
        child_frame_id: str | None,
    ) -> None:
        self.buffer = buffer
        self.msgtype = msgtype
        self.frame_id = frame_id
        self.child_frame_id = child_frame_id
        self._lock = threading.Lock()
        self._arrived = 0
        """Payloads that have arrived (handled or not): each one's sequence number."""
        self.received = 0
        self.taken = 0
        self.other = 0
        self.malformed = 0
        self.last_error: WireError | None = None
        self._subscriber: Any = None
        self._life: SessionLife | None = None  # set when the session is ours to close
        self._closed = False

    def on_payload(self, data: bytes) -> None:
        """Take one payload in (what the Zenoh callback calls; a test may call it too)."""
        with self._lock:
            seq = self._arrived
            self._arrived += 1
        try:
            message = decode_pose(data, self.msgtype, seq=seq)
        except WireError as exc:
            with self._lock:
                self.malformed += 1
                self.last_error = exc
                self.received += 1
            log.debug("pose payload refused: %s", exc)
            return
        if (self.frame_id is not None and message.frame_id != self.frame_id) or (
            self.child_frame_id is not None and message.child_frame_id != self.child_frame_id
        ):
            with self._lock:
                self.other += 1
                self.received += 1
            return
        taken = self.buffer.add(message.sample)
        with self._lock:
            self.taken += taken
            self.received += 1

    def _on_sample(self, sample: Any) -> None:
        self.on_payload(sample.payload.to_bytes())

    @property
    def closed(self) -> bool:
        return self._closed

    def close(self) -> None:
        """Unsubscribe (idempotent); close the session if this subscription opened it."""
        if self._closed:
            return
        self._closed = True
        subscriber, self._subscriber = self._subscriber, None
        life, self._life = self._life, None
        try:
            if subscriber is not None:
                subscriber.undeclare()
        finally:
            if life is not None:
                life.close()

    def __enter__(self) -> PoseSubscription:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


def subscribe_poses(
    key: str,
    buffer: PoseBuffer,
    *,
    session: Any = None,
    connect: Sequence[str] = (),
    zenoh_options: Mapping[str, Any] | None = None,
    msgtype: str | None = None,
    frame_id: str | None = None,
    child_frame_id: str | None = None,
) -> PoseSubscription:
    """Subscribe to the Zenoh key expression ``key`` and put every pose it carries into
    ``buffer`` (stamps on the base's clock: set the buffer's ``clock_offset_s``).

    ``session`` is an open ``zenoh.Session`` to subscribe on; without one a peer session of
    the subscription's own is opened, connecting to ``connect`` endpoints (with
    ``zenoh_options``; multicast scouting when no endpoint is given), and closed with it.
    ``msgtype`` is :data:`~biris_hw.io.codec.ODOMETRY` or
    :data:`~biris_hw.io.codec.TRANSFORM_STAMPED`; None takes either. ``frame_id`` and
    ``child_frame_id``, when given, keep only the messages between those frames (a key that
    carries several transforms).

    Raises:
        RequestError: a message type that is not a pose's, a key Zenoh refuses, a session that
            cannot be opened.
    """
    if msgtype is not None and msgtype not in POSE_TYPES:
        raise RequestError(f"msgtype must be one of {', '.join(POSE_TYPES)} or None: {msgtype!r}")
    import zenoh

    from biris_hw.io.net.lifetime import SessionLife
    from biris_hw.io.net.zconfig import make_config

    subscription = PoseSubscription(buffer, msgtype, frame_id, child_frame_id)
    life = None
    if session is None:
        config = make_config(  # a subscriber listens nowhere (as every client)
            connect=list(connect), multicast=not connect, options=zenoh_options or {}, client=True
        )
        try:
            session = zenoh.open(config)
        except Exception as exc:  # zenoh.ZError: a malformed endpoint...
            raise RequestError(f"cannot start the Zenoh session: {exc}") from exc
        life = SessionLife(session, f"the pose subscription to {key!r}")
    try:
        subscription._subscriber = session.declare_subscriber(key, subscription._on_sample)
    except Exception as exc:  # zenoh.ZError: a key expression it refuses
        if life is not None:
            life.close()
        raise RequestError(f"cannot subscribe to {key!r}: {exc}") from exc
    subscription._life = life
    return subscription

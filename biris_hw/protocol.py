"""The client/server protocol: every message a client sends to the BIRIS server's administrator.

Named after the report's client messages (OPEN_REQUEST, REQUEST_POINT, REQUEST_SCAN_DATA, ...,
READY_FOR_DATA, SET_ELEVATION, the "new message" the report asks for to servo the elevation
axis, and START_CONTINUOUS / STOP_CONTINUOUS, Appendix D's messages that switch BIRIS's
continuous acquisition on and off). It sits below both :mod:`biris_hw.client` and
:mod:`biris_hw.server`, so neither imports the other for it. All messages are immutable.

The messages that carry numbers check them when they are made, whoever makes them: a destination
is a whole number of counts (any integer type, kept as a plain ``int``; the administrator clamps
it), motor parameters are a :class:`MotorParams`, and ``poll`` is a bool. A malformed message
thus fails in the sender's thread, with a :class:`~biris_hw.errors.RequestError`, before it
reaches the administrator, and nothing changes. Converting degrees and seconds is the client's
work (:mod:`biris_hw.client`).
"""

from __future__ import annotations

import operator
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from biris_hw.angles import shown
from biris_hw.data import ConnectionKind, DeliveryPolicy, Direction
from biris_hw.errors import RequestError
from biris_hw.records import MotorParams
from biris_hw.status import check_change
from biris_hw.timebase import HwCondition, TimeBase


def _counts(message: object, name: str) -> None:
    """Normalise field ``name`` of a frozen message to a plain int of counts, or refuse it."""
    value = getattr(message, name)
    if isinstance(value, bool):
        raise RequestError(f"{name}: must be a whole number of counts, not a bool")
    try:
        number = operator.index(value)
    except TypeError:
        raise RequestError(
            f"{name}: must be a whole number of counts, not {type(value).__name__}"
        ) from None
    object.__setattr__(message, name, number)


def _check_poll(poll: object) -> None:
    """``poll`` must be a bool: a truthy number there is a bug in the sender, not a wish."""
    if poll is not True and poll is not False:
        raise RequestError(f"poll: must be True or False, not {poll!r}")


MAX_DEPTH = 1 << 16
"""Largest queue a connection may ask for (a bound on the server's memory, not a BIRIS limit)."""


def check_policy(kind: ConnectionKind, policy: object, depth: object) -> tuple[DeliveryPolicy, int]:
    """The policy and queue depth an OPEN_REQUEST asks for, checked.

    ``depth`` may be any integer type (a numpy ``int64`` from a computed size passes) and comes
    back a plain int; None means the policy's default.

    Raises:
        RequestError: an unknown policy, a policy on a NORMAL connection, or a depth that is not
            a whole number in 1..MAX_DEPTH (1 under LATEST).
    """
    try:
        chosen = DeliveryPolicy(policy)
    except ValueError:
        raise RequestError(f"no delivery policy {policy!r}") from None
    if kind is not ConnectionKind.DATA and chosen is not DeliveryPolicy.LATEST:
        raise RequestError("a delivery policy is for DATA connections")
    if depth is None:
        return chosen, chosen.default_depth
    wanted = f"depth: must be a whole number in 1..{MAX_DEPTH}"
    if isinstance(depth, bool):
        raise RequestError(f"{wanted}, not a bool")
    try:
        number = operator.index(depth)  # type: ignore[arg-type]  # any integer type
    except TypeError:
        raise RequestError(f"{wanted}, not {type(depth).__name__}") from None
    if not 1 <= number <= MAX_DEPTH:
        raise RequestError(f"{wanted}, not {shown(number)}")
    if chosen is DeliveryPolicy.LATEST and number != 1:
        raise RequestError("depth: LATEST keeps only the newest scan: its depth is 1")
    return chosen, number


@dataclass(frozen=True, slots=True)
class OpenRequest:
    kind: ConnectionKind
    owner_ident: object
    """The opening thread: the connection is released when it ends."""
    policy: DeliveryPolicy = DeliveryPolicy.LATEST
    depth: int | None = None
    """None: the policy's default."""


@dataclass(frozen=True, slots=True)
class CloseRequest:
    conn: int


@dataclass(frozen=True, slots=True)
class RequestPoint:
    conn: int


@dataclass(frozen=True, slots=True)
class RequestScanData:
    conn: int
    direction: Direction


@dataclass(frozen=True, slots=True)
class TimeoutEnable:
    conn: int


@dataclass(frozen=True, slots=True)
class TimeoutDisable:
    conn: int


@dataclass(frozen=True, slots=True)
class BirisMotorParams:
    conn: int
    params: MotorParams

    def __post_init__(self) -> None:
        if not isinstance(self.params, MotorParams):
            raise RequestError(f"params: must be a MotorParams, not {type(self.params).__name__}")


@dataclass(frozen=True, slots=True)
class SingleScanRqst:
    conn: int
    destination: int
    """Counts, before _Scan_limit (the administrator clamps)."""

    def __post_init__(self) -> None:
        _counts(self, "destination")


@dataclass(frozen=True, slots=True)
class ContScanRqst:
    conn: int
    cw_limit: int
    ccw_limit: int

    def __post_init__(self) -> None:
        _counts(self, "cw_limit")
        _counts(self, "ccw_limit")


@dataclass(frozen=True, slots=True)
class StopScanRqst:
    conn: int


@dataclass(frozen=True, slots=True)
class BirisHome:
    conn: int


@dataclass(frozen=True, slots=True)
class StartContinuous:
    """START_CONTINUOUS (Appendix D): acquire continuously into BIRIS's ring from now on --
    at once when no scan runs, else once the scan under way (or continuous scanning) ends."""

    conn: int


@dataclass(frozen=True, slots=True)
class StopContinuous:
    """STOP_CONTINUOUS (Appendix D): "cease all acquisitions immediately" and go back to one
    BI_ACQUIRE sequence per scan."""

    conn: int


@dataclass(frozen=True, slots=True)
class SetElevation:
    """The report's future elevation message: tilt to ``destination`` counts and reload the
    calibration table for it."""

    conn: int
    destination: int

    def __post_init__(self) -> None:
        _counts(self, "destination")


@dataclass(frozen=True, slots=True)
class ReadyForData:
    """READY_FOR_DATA. ``poll``: answer at once -- the oldest waiting buffer (or point), or a
    TimeoutError when none waits -- instead of parking until one comes (``timeout=0``)."""

    conn: int
    poll: bool = False

    def __post_init__(self) -> None:
        _check_poll(self.poll)


@dataclass(frozen=True, slots=True)
class WaitIdle:
    """Reply once the server is idle. ``poll``: answer at once -- None when idle, a TimeoutError
    when not -- instead of parking until it is (``timeout=0``)."""

    conn: int
    poll: bool = False

    def __post_init__(self) -> None:
        _check_poll(self.poll)


@dataclass(frozen=True, slots=True)
class ResetRequest:
    conn: int


@dataclass(frozen=True, slots=True)
class StatusRequest:
    """The server's status. With ``newer_than``, the push: parked, as READY_FOR_DATA is until
    there are data, until the status's change number (:attr:`ServerStatus.change
    <biris_hw.status.ServerStatus.change>`) is above it, so that a watcher hears of a change as
    it happens and asks nothing while nothing changes. ``poll`` (with ``newer_than``): answer at
    once, a newer status or a TimeoutError. ``conn``: the connection the request belongs to; a
    parked request ends with ConnectionClosed when that connection closes, so that its owner can
    stop a watch from another thread."""

    conn: int | None = None
    newer_than: int | None = None
    poll: bool = False

    def __post_init__(self) -> None:
        _check_poll(self.poll)
        object.__setattr__(self, "newer_than", check_change(self.newer_than))
        if self.poll and self.newer_than is None:
            raise RequestError("poll: only a status request with newer_than waits, or polls")


class Bulletin:
    """What a client may read of the administrator's state without a round trip.

    Written by the administrator alone (:meth:`advance`), after every message that may change
    what a client would be told (anything but a request that only reads): :attr:`epoch` grows
    by one each time, and :attr:`change` is then the status's change number
    (:attr:`ServerStatus.change <biris_hw.status.ServerStatus.change>`). A client that was told
    "nothing waits for you" at one epoch would be told the same while the epoch stays, and one
    that waits for a status newer than ``c`` has nothing to ask while :attr:`change` is ``c``:
    both wait here (:meth:`wait_until`) and ask the administrator once there is something to
    ask for, so an idle sensor's readers and watchers cost it nothing
    (:class:`biris_hw.client.Connection`). The numbers are ints, read whole, so a reader needs
    no lock; waiting goes through the rig's time base, so a wait here is a wait of its domain.
    """

    __slots__ = ("_cond", "_scale", "_timebase", "_waiting", "change", "epoch")

    def __init__(self, timebase: TimeBase | None = None) -> None:
        self.epoch = 0
        self.change = 0
        self._timebase = timebase
        self._cond: HwCondition | threading.Condition = (
            timebase.Condition() if timebase is not None else threading.Condition()
        )
        self._scale = timebase.timeout_hw(1.0) if timebase is not None else 1.0
        """Hardware seconds per second of a caller's timeout."""
        self._waiting = 0

    def __repr__(self) -> str:
        return f"<Bulletin epoch={self.epoch} change={self.change}>"

    def advance(self, change: int | None = None) -> None:
        """The epoch moves on (and the status's change number is ``change``, if given); whoever
        waits is woken. A lock hand-over: the administrator never waits here."""
        with self._cond:
            self.epoch += 1
            if change is not None:
                self.change = change
            if self._waiting:
                self._cond.notify_all()

    def _now(self) -> float:
        return self._timebase.now() if self._timebase is not None else time.monotonic()

    def wait_until(self, ready: Callable[[], bool], timeout: float | None) -> float | None:
        """Block until ``ready()`` (asked again each time the bulletin moves); returns what is
        left of ``timeout`` (the caller's seconds; None for no deadline).

        Raises:
            TimeoutError: ``timeout`` seconds passed first.
        """
        scale = self._scale
        deadline = None if timeout is None else self._now() + timeout * scale
        with self._cond:
            self._waiting += 1
            try:
                while not ready():
                    left = None if deadline is None else deadline - self._now()
                    if left is not None and left <= 0:
                        raise TimeoutError("nothing has changed in the server")
                    if isinstance(self._cond, HwCondition):
                        self._cond.wait(left, what="the administrator's bulletin")
                    else:
                        self._cond.wait(left)
            finally:
                self._waiting -= 1
        return None if deadline is None else max(0.0, (deadline - self._now()) / scale)

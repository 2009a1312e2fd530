"""One sensor interface: what a program needs of a BIRIS sensor, wherever the sensor is.

Three kinds of sensor answer to it: a local :class:`~biris_hw.BirisServer` on the hardware (or the
simulator), a service reached over the network (:class:`biris_hw.io.net.RemoteSensor`) and a
replayed recording (:class:`biris_hw.io.record.ReplayServer`). :class:`Sensor` and
:class:`Connection` are typing Protocols, so the three need no common base class and a type
checker holds each to the same methods (a test suite holds them to the same behaviour:
``tests/test_sensor_contract.py``). The outside world (:mod:`biris_hw.io`: the service, the
recorder, the live view) is written against these two names alone, which is what lets it serve,
record or show any of the three.

:class:`ConnectionBase` is the part of a connection that does not depend on where the sensor is
(the closed flag, an idempotent ``close``, the context manager, ``repr``); the three connection
classes derive from it. :func:`open_sensor` (loaded on first use, as ``biris_hw``'s own names
are) opens whichever kind a program is pointed at.
"""

from __future__ import annotations

import importlib
from types import TracebackType
from typing import TYPE_CHECKING, Any, Generic, Literal, Protocol, overload

from biris_hw.angles import RealLike
from biris_hw.data import ConnectionKind, DeliveryPolicy, Direction, Point, Scan
from biris_hw.errors import ConnectionClosed, RequestError
from biris_hw.records import BirisInitRecord, MotorParams
from biris_hw.status import ServerStatus

if TYPE_CHECKING:  # the defaults need PEP 696; at run time plain TypeVars do the same job
    from typing_extensions import Self, TypeVar

    from biris_hw.opening import open_sensor

    D = TypeVar("D", Scan, Point, default=Scan)
    D_co = TypeVar("D_co", Scan, Point, covariant=True, default=Scan)
else:
    from typing import TypeVar

    D = TypeVar("D", Scan, Point)
    D_co = TypeVar("D_co", Scan, Point, covariant=True)

__all__ = ["Connection", "ConnectionBase", "Sensor", "open_sensor"]


class Connection(Protocol[D_co]):
    """A connection to a sensor (NORMAL or DATA): one method per client message of the report.

    Generic in what READY_FOR_DATA hands out, as :class:`biris_hw.client.Connection` is: a
    ``Connection[Scan]`` (the default) under the LATEST and EVERY_BUFFER policies, a
    ``Connection[Point]`` under EVERY_ACQUISITION. Every kind of sensor raises the same errors
    for the same reasons: ConnectionClosed on a closed connection or sensor, RequestError (and
    nothing changed) for a bad argument or a request the sensor cannot carry out, HardwareFault
    in a fault, TimeoutError when a wait runs out.
    """

    @property
    def ident(self) -> int:
        """The sensor's number for this connection (as in ``status().connections``)."""
        ...

    @property
    def kind(self) -> ConnectionKind: ...

    @property
    def policy(self) -> DeliveryPolicy: ...

    @property
    def depth(self) -> int: ...

    @property
    def dropped(self) -> int:
        """What this DATA connection missed, as of its last READY_FOR_DATA."""
        ...

    @property
    def closed(self) -> bool: ...

    def request_point(self) -> Point | None: ...

    def request_scan_data(self, direction: Direction | int) -> Scan | None: ...

    def ready_for_data(self, timeout: RealLike | None = None) -> D_co: ...

    def single_scan(self, to_deg: RealLike) -> int: ...

    def continuous_scan(self, cw_deg: RealLike, ccw_deg: RealLike) -> tuple[int, int]: ...

    def set_elevation(self, deg: RealLike) -> int: ...

    def stop_scan(self) -> None: ...

    def start_continuous(self) -> None: ...

    def stop_continuous(self) -> None: ...

    def home(self) -> None: ...

    def set_motor_params(self, params: MotorParams) -> None: ...

    def timeout_enable(self) -> None: ...

    def timeout_disable(self) -> None: ...

    def wait_idle(self, timeout: RealLike | None = None) -> None: ...

    def reset(self) -> None: ...

    def status(
        self, *, newer_than: int | None = None, timeout: RealLike | None = None
    ) -> ServerStatus:
        """The sensor's status, as :meth:`Sensor.status`; a wait for a newer one also ends
        (ConnectionClosed) when this connection is closed, from any thread."""
        ...

    def close(self) -> None: ...

    def __enter__(self) -> Self: ...

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None: ...


class Sensor(Protocol):
    """What a program needs of a sensor, wherever it is (see the module)."""

    @property
    def playback(self) -> bool:
        """A recording: it refuses motion and configuration itself (a RequestError of its own),
        whoever asks, so a service hands such requests to it rather than refuse them."""
        ...

    @property
    def paced(self) -> bool:
        """Its data come at its own pace, whatever its readers do. False for a recording played
        as fast as its slowest queueing reader takes it (``speed=None``), which one stalled
        reader stalls for every other: a service refuses to serve such a sensor."""
        ...

    @property
    def record(self) -> BirisInitRecord | None:
        """The init record the sensor runs with (its mount, motor parameters, limits), or None
        when it is not known (a recording made without one)."""
        ...

    @overload
    def open(
        self,
        kind: ConnectionKind = ...,
        *,
        policy: Literal[DeliveryPolicy.EVERY_ACQUISITION],
        depth: int | None = ...,
    ) -> Connection[Point]: ...

    @overload
    def open(
        self,
        kind: ConnectionKind = ...,
        *,
        policy: Literal[DeliveryPolicy.LATEST, DeliveryPolicy.EVERY_BUFFER] = ...,
        depth: int | None = ...,
    ) -> Connection[Scan]: ...

    @overload
    def open(
        self,
        kind: ConnectionKind = ...,
        *,
        policy: DeliveryPolicy,
        depth: int | None = ...,
    ) -> Connection[Scan] | Connection[Point]: ...

    def status(
        self, *, newer_than: int | None = None, timeout: RealLike | None = None
    ) -> ServerStatus:
        """What the sensor is doing and has done.

        With ``newer_than`` (a status's :attr:`~biris_hw.status.ServerStatus.change`), the
        push: returns once the status has changed since (at once if it has already), so a
        watcher asks nothing while nothing changes. ``timeout`` bounds that wait (None: as long
        as it takes; 0: a poll).

        Raises:
            ConnectionClosed: the sensor is closed.
            RequestError: a ``newer_than`` or ``timeout`` that is not a number of its kind.
            TimeoutError: no newer status within ``timeout``.
        """
        ...

    def clock(self) -> float:
        """Hardware seconds now: the local hardware's clock; for a network client or a replay,
        the newest hardware time it has seen (0.0 before it has seen any). Never goes back."""
        ...

    def close(self) -> None: ...

    def __enter__(self) -> Self: ...

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None: ...


class ConnectionBase(Generic[D]):
    """What every kind of connection shares: its figures, the closed flag, an idempotent
    :meth:`close`, the context manager and ``repr``.

    A subclass tells its sensor in :meth:`_close` (called once, by the first :meth:`close`;
    the connection counts as closed afterwards whatever it raised) and calls
    :meth:`_check_open` before each request.
    """

    def __init__(
        self,
        ident: int,
        kind: ConnectionKind,
        policy: DeliveryPolicy = DeliveryPolicy.LATEST,
        depth: int = 1,
    ) -> None:
        self.ident = ident
        self.kind = kind
        self.policy = policy
        """What READY_FOR_DATA delivers and what a slow client loses (DATA connections)."""
        self.depth = depth
        """How many buffers (or points) wait for the client at most."""
        self.dropped = 0
        """Buffers (points) this DATA connection missed, as of its last READY_FOR_DATA: replaced
        or pushed out of a full queue because the client was not ready in time, or (points)
        lost by the sensor. ``status()`` has the running figure."""
        self._closed = False

    def _where(self) -> str:
        """What ``repr`` puts before the number: the sensor's name where there is one."""
        return ""

    def __repr__(self) -> str:
        state = "closed" if self._closed else "open"
        policy = f" {self.policy.name}" if self.kind is ConnectionKind.DATA else ""
        return (
            f"<{type(self).__name__} {self._where()}{self.ident} {self.kind.name}{policy} {state}>"
        )

    @property
    def closed(self) -> bool:
        return self._closed

    def _check_open(self) -> None:
        """Raise ConnectionClosed once this connection is closed."""
        if self._closed:
            raise ConnectionClosed(f"connection {self.ident} is closed")

    @staticmethod
    def _direction(direction: object) -> Direction:
        """REQUEST_SCAN_DATA's direction, checked alike on every kind of connection.

        Raises:
            RequestError: no such direction (True is 1 to Python, but it names none).
        """
        try:
            if isinstance(direction, bool):
                raise ValueError(direction)
            return Direction(direction)  # type: ignore[arg-type]  # any value: refused below
        except (ValueError, TypeError):
            raise RequestError(
                f"direction: no direction {direction!r}; use Direction.CW or CCW"
            ) from None

    def _close(self) -> None:
        """Tell the sensor (CLOSE_REQUEST); the base has no sensor to tell."""

    def close(self) -> None:
        """CLOSE_REQUEST; calling it again does nothing."""
        if self._closed:
            return
        try:
            self._close()
        finally:
            self._closed = True

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


if not TYPE_CHECKING:  # hidden from type checkers, which see the import above

    def __getattr__(name: str) -> Any:
        """``open_sensor`` is loaded on first use (PEP 562): it reaches every kind of sensor
        (the server, the network, recordings), which this bottom-layer module must not import
        when it is itself imported."""
        if name != "open_sensor":
            raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
        value = importlib.import_module("biris_hw.opening").open_sensor
        globals()[name] = value  # later look-ups skip this function
        return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))

"""``BirisServer.status()``'s answer, typed: :class:`ServerStatus` and :class:`ConnectionStatus`.

Both are frozen dataclasses, so a caller gets attributes a type checker knows
(``status.state is ServerState.IDLE``, ``status.fault == "bus"``, ``status.counters["scans"]``).
They also read as mappings, as ``status()`` did when it returned a dict, so existing callers keep
working: ``status["state"]`` is the state's name, or ``"fault:<kind>"`` in the fault state, and
every other key is the attribute of that name.

:meth:`ServerStatus.accounts` reconciles the acquisition counters: where every acquisition BIRIS
made has gone (:class:`Accounts`).
"""

from __future__ import annotations

import enum
import operator
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field, fields
from typing import Any

from biris_hw.errors import FaultKind, RequestError
from regs.wiener_crate import CrateReading

__all__ = [
    "Accounts",
    "ConnectionStatus",
    "ServerState",
    "ServerStatus",
    "StatusChanges",
    "check_change",
]


class ServerState(enum.Enum):
    """What the server is doing: the most telling of its activities."""

    INITIALISING = "initialising"
    IDLE = "idle"
    HOMING = "homing"
    TILTING = "tilting"
    SCANNING = "scanning"
    BUSY = "busy"
    """Initialised and none of the above, but something is still owed (a motor parameter load,
    Appendix D's ring starting or stopping, a BIRIS command): ``wait_idle`` waits for it, so
    ``idle`` is said only when ``wait_idle(timeout=0)`` would return."""
    FAULT = "fault"  # ServerStatus.fault says which kind


class _ReadsAsMapping(Mapping[str, Any]):
    """Mapping access to a frozen dataclass's fields (for callers of the dict it replaced)."""

    def __getitem__(self, key: str) -> Any:
        if key not in self._keys():
            raise KeyError(key)
        return getattr(self, key)

    def _keys(self) -> tuple[str, ...]:
        return tuple(f.name for f in fields(self))  # type: ignore[arg-type]

    def __iter__(self) -> Iterator[str]:
        return iter(self._keys())

    def __len__(self) -> int:
        return len(self._keys())


@dataclass(frozen=True, eq=False)
class ConnectionStatus(_ReadsAsMapping):
    """One open connection's figures."""

    kind: str
    """NORMAL or DATA."""
    policy: str
    """The DATA connection's delivery policy's name."""
    depth: int
    queued: int
    delivered: int
    dropped: int
    latency: Mapping[str, Any]
    """Delivery latency: count, mean, max, p50, p99 (seconds) and a histogram."""


@dataclass(frozen=True)
class Accounts:
    """Where every acquisition BIRIS made has gone, from one ``status()``.

    Two identities hold::

        accounted = read + idle + lost                                  (what BIRIS made)
        read = in_scans + constant_azimuth + stale + aborted + in_progress   (what became of it)

    The second holds at every ``status()``: :attr:`adds_up` says so, and anything else is a
    server bug. The first is :attr:`accounted`, and it equals the number of acquisitions BIRIS
    made once the server has looked at all of them: when no BI_ACQUIRE is under way (after
    ``wait_idle()``), and in continuous acquisition once the ring has stopped (a reset or a tilt
    stops it), because the frames a live ring makes while the head stands idle are counted when
    the next sweep opens or when the ring stops, not as they are made. The simulator's
    ``rig.supervisor.acquisitions_made`` is then exactly :attr:`accounted`.
    """

    read: int
    """Read out of BIRIS memory and handed to the administrator (``acquisitions_read``)."""
    in_scans: int
    """In completed scans: what clients were given as Scans (``acquisitions_in_scans``)."""
    constant_azimuth: int
    """Dropped: made with the head standing at a continuous-acquisition sweep's start or end."""
    stale: int
    """Dropped: of a sequence or sweep the server no longer waited for."""
    aborted: int
    """Dropped: kept by a scan that a fault or reset abandoned (``aborted_acquisitions``)."""
    idle: int
    """Never read: ring frames made while no sweep wanted them (``idle_ring_frames``)."""
    lost: int
    """Never read: overwritten before they could be read (``lost_acquisitions``)."""
    in_progress: int
    """Read and held by the scan under way (and a finished sweep's turn-around tail, until the
    next sweep takes it): settled when that scan completes or is abandoned."""

    @property
    def accounted(self) -> int:
        """Acquisitions BIRIS made that the server has accounted for (read, idle or lost)."""
        return self.read + self.idle + self.lost

    @property
    def settled(self) -> int:
        """Read acquisitions whose fate is decided: in a scan, or dropped for a reason."""
        return self.in_scans + self.constant_azimuth + self.stale + self.aborted

    @property
    def adds_up(self) -> bool:
        """Every acquisition read is in a completed scan, dropped for a counted reason, or in
        progress: none went missing between the reader and the clients."""
        return self.read == self.settled + self.in_progress


@dataclass(frozen=True, eq=False)
class ServerStatus(_ReadsAsMapping):
    """What the server is doing and has done."""

    state: ServerState
    fault: FaultKind | None
    """The fault's kind while ``state`` is FAULT, else None."""
    azimuth: int
    """Counts: where the pan axis was last sent (its move's end)."""
    elevation: int
    """Counts: where the tilt stands once its last tilt is over."""
    calibration: int | None
    """Elevation (counts) of the calibration table BIRIS holds; None when unknown."""
    continuous: bool
    """Continuous scanning is on."""
    acquisition: str
    """"continuous" (Appendix D's ring) or "single" (one BI_ACQUIRE per scan): the mode in force,
    chosen by the init record's ``continuous_acquisition`` and switched at run time by
    ``conn.start_continuous()`` / ``conn.stop_continuous()`` (:attr:`acquisition_pending`)."""
    ring: str
    """The ring's state: off, starting, live, stopping."""
    counters: Mapping[str, int]
    connections: Mapping[int, ConnectionStatus]
    interrupts: Mapping[str, int] = field(default_factory=dict)
    """Interrupts raised per logical kind (filled in by the server, outside the administrator)."""
    azimuth_live: int | None = None
    """Counts: the pan encoder, read for this status (or a reading at most 0.1 hardware s old
    while an axis moves, 1 s at rest: :mod:`biris_hw.server.encoders`); None while
    initialising or if the board cannot be read."""
    elevation_live: int | None = None
    acquisitions_in_progress: int = 0
    """Acquisitions read and held by the scan under way (and a finished sweep's turn-around
    tail), not yet in any counter: the in-progress term of :meth:`accounts`."""
    acquisition_pending: str | None = None
    """The acquisition mode asked for and not yet in force, else None: ``"continuous"`` while a
    START_CONTINUOUS waits for the scan under way (or continuous scanning) to end, as BIRIS_HOME
    does. ``acquisition`` keeps saying the mode the data are taken in until then. Only a start
    ever waits: STOP_CONTINUOUS takes effect at once (and withdraws a start that waits)."""
    tasks_down: tuple[str, ...] = ()
    """The server's tasks (:mod:`biris_hw.server.task_table` names) that failed and wait for
    the next reset, sorted; empty while every task runs. A failure is a fault too (``internal``,
    or the kind of the hardware fault the task met), so this says which part of the server the
    reset will bring back."""
    task_failures: Mapping[str, int] = field(default_factory=dict)
    """How many times each task has failed since the server started (only those that have)."""
    crate: CrateReading | None = None
    """The VME crate's last reading over CAN (power, voltages, fans, temperatures and the
    crate's own alarms: ``crate.alarms()``), when the hardware has a crate monitor
    (``BirisHardware.crate``); None without one, or before its first answer. Kept when a later
    poll fails: :attr:`crate_error` then says so, and ``crate.read_at`` how old it is."""
    crate_error: str | None = None
    """Why the last poll of the crate failed (it did not answer, a malformed frame), else None."""
    change: int = 0
    """This status's change number: it grows each time what :meth:`signature` covers changes, so
    ``sensor.status(newer_than=status.change)`` waits until there is something new to say
    (the push a service or a live view needs instead of polling). Numbered by the sensor that
    answers: a :class:`~biris_hw.BirisServer`'s administrator, or a network client or a replay
    for what it has seen; compare it only with numbers from the same sensor object."""

    def signature(self) -> tuple[Any, ...]:
        """What a watcher acts on, as one comparable value; :attr:`change` counts its changes.

        The state (fault kind included), where the axes were sent, the calibration, the scanning
        and acquisition modes, and which connections are open. Not the counters, the live
        encoder readings nor the crate's reading: those move while nothing a watcher decides on
        does (every acquisition, every step of the head), and a watcher that wants them fresh
        asks at its own pace.
        """
        return (
            self.state,
            self.fault,
            self.azimuth,
            self.elevation,
            self.calibration,
            self.continuous,
            self.acquisition,
            self.acquisition_pending,
            self.ring,
            tuple(self.connections),
        )

    def accounts(self) -> Accounts:
        """The acquisition counters reconciled (:class:`Accounts`): ``accounts().adds_up``
        always; ``accounts().accounted`` equals what BIRIS made once the server has drained
        everything (for instance after ``stop_scan()`` and ``wait_idle()``; in continuous
        acquisition, once the ring has stopped)."""
        counters = self.counters
        return Accounts(
            read=counters.get("acquisitions_read", 0),
            in_scans=counters.get("acquisitions_in_scans", 0),
            constant_azimuth=counters.get("constant_azimuth", 0),
            stale=counters.get("stale_acquisitions", 0),
            aborted=counters.get("aborted_acquisitions", 0),
            idle=counters.get("idle_ring_frames", 0),
            lost=counters.get("lost_acquisitions", 0),
            in_progress=self.acquisitions_in_progress,
        )

    @property
    def state_name(self) -> str:
        """``state``'s name as ``status["state"]`` gives it: ``fault:<kind>`` in a fault."""
        if self.state is ServerState.FAULT:
            return f"fault:{self.fault}"
        return str(self.state.value)

    def __getitem__(self, key: str) -> Any:
        if key == "state":
            return self.state_name
        return super().__getitem__(key)

    def __repr__(self) -> str:
        return (
            f"<ServerStatus {self.state_name} az={self.azimuth} el={self.elevation} "
            f"change={self.change}>"
        )


class StatusChanges:
    """Numbers the changes of a status's :meth:`~ServerStatus.signature` as they are seen.

    One per sensor: :meth:`see` is given every signature the sensor learns, in order, and
    :attr:`change` is then the number to stamp on the latest status. Not thread-safe: its owner
    calls it under its own lock (or from its one thread, as the administrator does).
    """

    def __init__(self) -> None:
        self.change = 0
        self._last: tuple[Any, ...] | None = None

    def see(self, signature: tuple[Any, ...]) -> bool:
        """Note ``signature``; True (and :attr:`change` one up) when it differs from the last."""
        if signature == self._last:
            return False
        self._last = signature
        self.change += 1
        return True


def check_change(value: object, name: str = "newer_than") -> int | None:
    """A ``newer_than`` argument checked: None, or a change number as a plain int (any integer
    type passes; a bool, a float or a string is a mistake, not a number).

    Raises:
        RequestError: anything else.
    """
    if value is None:
        return None
    wanted = f"{name}: must be a status's change number (a whole number)"
    if isinstance(value, bool):
        raise RequestError(f"{wanted}, not a bool")
    try:
        return operator.index(value)  # type: ignore[arg-type]  # any integer type
    except TypeError:
        raise RequestError(f"{wanted}, not {type(value).__name__}") from None

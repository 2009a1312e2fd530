"""``BirisServer.status()``'s answer, typed: :class:`ServerStatus` and :class:`ConnectionStatus`.

Both are frozen dataclasses, so a caller gets attributes a type checker knows
(``status.state is ServerState.IDLE``, ``status.fault == "bus"``, ``status.counters["scans"]``).
They also read as mappings, as ``status()`` did when it returned a dict, so existing callers keep
working: ``status["state"]`` is the state's name, or ``"fault:<kind>"`` in the fault state, and
every other key is the attribute of that name.
"""

from __future__ import annotations

import enum
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field, fields
from typing import Any

from biris_hw.errors import FaultKind

__all__ = ["ConnectionStatus", "ServerState", "ServerStatus"]


class ServerState(enum.Enum):
    """What the server is doing: the most telling of its activities."""

    INITIALISING = "initialising"
    IDLE = "idle"
    HOMING = "homing"
    TILTING = "tilting"
    SCANNING = "scanning"
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
    """"continuous" (Appendix D's ring) or "single" (one BI_ACQUIRE per scan)."""
    ring: str
    """The ring's state: off, starting, live, stopping."""
    counters: Mapping[str, int]
    connections: Mapping[int, ConnectionStatus]
    interrupts: Mapping[str, int] = field(default_factory=dict)
    """Interrupts raised per logical kind (filled in by the server, outside the administrator)."""
    azimuth_live: int | None = None
    """Counts: the pan encoder now; None while initialising or if the board cannot be read."""
    elevation_live: int | None = None

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
        return f"<ServerStatus {self.state_name} az={self.azimuth} el={self.elevation}>"

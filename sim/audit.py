"""The simulator's audit: every hardware rule a driver can break, recorded when it is broken.

A violation is a driver bug. Each record carries the hardware time, the rule's name and the
register values involved, so a failing test says exactly what the driver did (the rules:
README.md, "Faults and the audit").
"""

from __future__ import annotations

import enum
import threading
from collections.abc import Callable
from dataclasses import dataclass, field

__all__ = ["Audit", "Rule", "Violation"]


class Rule(str, enum.Enum):
    """The audit rules; the value is the name used in reports."""

    CMD_WHILE_BUSY = "CMD_WHILE_BUSY"
    """COMMAND written before the previous command completed."""
    MOTOR_BEYOND_LIMIT = "MOTOR_BEYOND_LIMIT"
    """A destination outside +-0x1000 counts reached the chip."""
    HEAD_BEYOND_LIMIT = "HEAD_BEYOND_LIMIT"
    """The true pan head went beyond +-0x1000 counts (plus the filter's overshoot) from true
    azimuth 0: the cable is being wound, whatever the chip's counter says (beyond the report).
    Recorded once per excursion."""
    POSITION_MODE_WHILE_MOVING = "POSITION_MODE_WHILE_MOVING"
    """A mode switch that would make the motor jump (position control while moving)."""
    MOTION_WHILE_UNINITIALISED = "MOTION_WHILE_UNINITIALISED"
    """A move before the chip's filter and sample registers were set."""
    ACQUIRE_WITHOUT_MOTOR_ACCESS = "ACQUIRE_WITHOUT_MOTOR_ACCESS"
    """BI_ACQUIRE while azimuth tagging is requested but _Biris_motor_access is clear."""
    WRITE_TO_READ_ONLY = "WRITE_TO_READ_ONLY"
    """A write to a read-only register."""
    ACQUIRE_WHILE_TILTING = "ACQUIRE_WHILE_TILTING"
    """An acquisition while the elevation axis moves (beyond the report)."""
    WRONG_CALIBRATION = "WRONG_CALIBRATION"
    """An acquisition under a calibration table for another elevation (beyond the report)."""


@dataclass(frozen=True)
class Violation:
    """One broken rule: when (hardware seconds), which rule, the registers involved.

    ``rule`` is a :class:`Rule`, or a rule of a simulated transport's own audit (the VM-USB's
    ``sim.vmusb.VmUsbRule``, a CiA 402 drive's ``sim.cia402.DriveRule``): string enums whose
    value is the name used in reports."""

    time: float
    rule: enum.Enum
    registers: dict[str, int] = field(default_factory=dict)
    detail: str = ""

    def __str__(self) -> str:
        regs = " ".join(f"{k}=0x{v & 0xFFFFFFFF:X}" for k, v in self.registers.items())
        return f"t={self.time:.6f}s {self.rule.value} {regs} {self.detail}".rstrip()


class Audit:
    """Thread-safe list of violations, stamped with the simulator clock.

    The simulator keeps one for the report's rules (``rig.audit``); a simulated transport keeps
    its own for the rules of its protocol, in the same shape."""

    def __init__(self, clock: Callable[[], float]) -> None:
        self._clock = clock
        self._lock = threading.Lock()
        self._violations: list[Violation] = []

    def record(self, rule: enum.Enum, detail: str = "", **registers: int) -> None:
        """Note that ``rule`` was broken now, with the register values that show it."""
        violation = Violation(self._clock(), rule, dict(registers), detail)
        with self._lock:
            self._violations.append(violation)

    @property
    def violations(self) -> list[Violation]:
        """A copy of everything recorded so far, oldest first."""
        with self._lock:
            return list(self._violations)

    def clear(self) -> None:
        with self._lock:
            self._violations.clear()

    def __len__(self) -> int:
        with self._lock:
            return len(self._violations)

"""The Bit 3 Model 412 coupler's local (host-side) node registers, as a bus device.

What the driver needs from the coupler is its error reporting and the level-2 vector; the memory
window itself is modelled elsewhere (a plain buffer shared with the supervisor). So this model
keeps the node registers of :mod:`regs.bit3` and their side effects:

- Power-up: LOCAL_STATUS = CARD_READY, everything else 0 (interrupt control 0, so the
  coupler's own error interrupts are *disabled* until the driver sets ERROR_INT_ENABLE, bit 5,
  of LOCAL_INT_CONTROL; LEVEL2_VECTOR 0 until the driver programs it).
- PARITY_ERROR and REMOTE_BUS_ERROR are sticky: :meth:`Bit3Coupler.parity_error` and
  :meth:`Bit3Coupler.bus_error` set them and, if error interrupts are enabled, raise level 2
  through the gate ("perr"/"berr"); only a write of LOCAL_COMMAND with CLR_ERROR (bit 7)
  clears them (every ERROR_MASK bit at once). The other LOCAL_COMMAND bits are one-shots with
  nothing behind them here, and LOCAL_COMMAND reads 0.
- LOCAL_INT_CONTROL bits 6..0 are read/write; bit 7 (INT_PENDING) reads 0: the pending state
  of a level lives in the interrupt line (the eventfd count), not in a register. Passing of
  BIRIS's interrupts (remote IRQ2) is always on; only the coupler's own error interrupts obey
  the enable.
- LOCAL_INT_STATUS shows CINT2 (bit 2) when the last level-2 interrupt came from BIRIS (a
  "data" or "cmd" interrupt through the gate), 0 otherwise; it is never cleared by a read.
- Offset 0x08 reads REMOTE_STATUS (0x10: remote bus not locked); writes there
  (REMOTE_COMMAND_1: remote reset, IACK level, ...) are accepted and have no effect.
  REMOTE_COMMAND_2, the page registers and the address modifier are plain read/write.
  REMOTE_CARD_ID reads :data:`REMOTE_CARD_ID_VALUE` (ours).
  REMOTE_IACK (word at 0x0E) answers the level-2 vector in its low byte: the report puts the
  vector for every BIRIS interrupt in a register on this board.
- Writes to the read-only registers (LOCAL_STATUS, LOCAL_INT_STATUS, REMOTE_CARD_ID,
  REMOTE_IACK) are ignored and recorded as ``WRITE_TO_READ_ONLY``. Undocumented offsets read 0
  and ignore writes.
- Remote power (:meth:`Bit3Coupler.remote_power_off`, ``rig.faults.remote_power_off()``): the
  BIRIS crate, on the far side of the cable, loses power. LOCAL_STATUS shows NO_CONNECT (bit 0,
  "remote power or cable off" in the Bit 3 family) until :meth:`Bit3Coupler.remote_power_on`;
  it is a state, not an error bit, so it raises no interrupt and CLR_ERROR leaves it. Every
  access across the cable meanwhile (BIRIS memory: the rig's window calls
  :meth:`Bit3Coupler.remote_access`) times out: the sticky TIMEOUT error bit (bit 2) is set,
  level 2 is raised if error interrupts are enabled (source "timeout") when the bit was clear
  (so a stack that reads across the coupler at every interrupt, a VM-USB's, cannot turn one
  lost crate into an interrupt storm), and the access fails
  with :class:`~biris_hw.errors.BusError` (``ETIMEDOUT``), as the adaptor ends the host's cycle
  with a bus error. The timeout costs no modelled time (a real adaptor's is microseconds).
  The node registers themselves are on the host's side and keep working.
"""

from __future__ import annotations

import errno
import threading

from biris_hw.errors import BusError
from regs.bit3 import (
    BIT3_SPACE,
    ERROR_MASK,
    REMOTE_STATUS,
    Bit3Reg,
    LocalCommand,
    LocalIntControl,
    LocalStatus,
)
from sim.audit import Audit, Rule
from sim.device import DeviceWindow
from sim.irqgate import BIRIS_SOURCES, InterruptGate

__all__ = ["CINT2", "REMOTE_CARD_ID_VALUE", "REMOTE_STATUS_IDLE", "Bit3Coupler"]

REMOTE_CARD_ID_VALUE = 0x41
"""What REMOTE_CARD_ID reads (interpretation: no Model 412 card id survives)."""

REMOTE_STATUS_IDLE = 0x10
"""REMOTE_STATUS with the remote bus not locked and nothing pending."""

CINT2 = 0x04
"""LOCAL_INT_STATUS bit for remote IRQ2, the level BIRIS interrupts on."""

_READ_ONLY = {
    int(Bit3Reg.LOCAL_STATUS): "LOCAL_STATUS",
    int(Bit3Reg.LOCAL_INT_STATUS): "LOCAL_INT_STATUS",
    int(Bit3Reg.REMOTE_CARD_ID): "REMOTE_CARD_ID",
    int(Bit3Reg.REMOTE_IACK): "REMOTE_IACK",
    int(Bit3Reg.REMOTE_IACK) + 1: "REMOTE_IACK",
}

_PLAIN_RW = (
    int(Bit3Reg.REMOTE_COMMAND_2),
    int(Bit3Reg.REMOTE_PAGE_LO),
    int(Bit3Reg.REMOTE_PAGE_HI),
    int(Bit3Reg.REMOTE_ADDR_MOD),
    int(Bit3Reg.LEVEL2_VECTOR),
)


class Bit3Coupler:
    """The coupler's local node: ``bus_read``/``bus_write`` for the driver, faults for the rig."""

    def __init__(self, gate: InterruptGate, *, audit: Audit | None = None) -> None:
        self._gate = gate
        self._audit = audit
        self._lock = threading.RLock()
        self._status = int(LocalStatus.CARD_READY)
        self._int_control = 0
        self._plain = dict.fromkeys(_PLAIN_RW, 0)
        self._error_irqs = 0
        self._remote_powered = True
        self._timeouts = 0

    # -- bus side (with side effects) ----------------------------------------------------------
    def bus_read(self, offset: int) -> int:
        with self._lock:
            return self._peek(offset)

    def bus_write(self, offset: int, value: int) -> None:
        value &= 0xFF
        with self._lock:
            if offset in _READ_ONLY:
                if self._audit is not None:
                    self._audit.record(
                        Rule.WRITE_TO_READ_ONLY,
                        f"Bit 3 {_READ_ONLY[offset]}",
                        offset=offset,
                        value=value,
                    )
                return
            if offset == Bit3Reg.LOCAL_COMMAND:
                if value & LocalCommand.CLR_ERROR:
                    self._status &= ~ERROR_MASK
                if value & LocalCommand.CLR_PR_INT:
                    self._status &= ~int(LocalStatus.PR_INT)
            elif offset == Bit3Reg.LOCAL_INT_CONTROL:
                self._int_control = value & ~int(LocalIntControl.INT_PENDING)
            elif offset in self._plain:
                self._plain[offset] = value

    def window(self) -> DeviceWindow:
        """The driver's window onto these registers (BIT3_SPACE bytes, byte accesses)."""
        return DeviceWindow(self, BIT3_SPACE, self._lock)

    # -- faults --------------------------------------------------------------------------------
    def parity_error(self) -> None:
        """A parity error on the cable: sticky PARITY_ERROR, BIT3_PERR if errors interrupt."""
        self._error(LocalStatus.PARITY_ERROR, "perr")

    def bus_error(self) -> None:
        """A coupler cycle on the BIRIS bus got BERR: sticky REMOTE_BUS_ERROR, BIT3_BERR."""
        self._error(LocalStatus.REMOTE_BUS_ERROR, "berr")

    def remote_power_off(self) -> None:
        """The BIRIS crate loses power (or the cable comes out): NO_CONNECT, and every access
        across the cable times out until :meth:`remote_power_on` (module notes)."""
        with self._lock:
            self._remote_powered = False
            self._status |= int(LocalStatus.NO_CONNECT)

    def remote_power_on(self) -> None:
        """Power is back: NO_CONNECT clears; a TIMEOUT already set stays until CLR_ERROR."""
        with self._lock:
            self._remote_powered = True
            self._status &= ~int(LocalStatus.NO_CONNECT)

    def remote_access(self, op: str, offset: int, nbytes: int) -> None:
        """Called before every access the driver makes across the cable (``op``, "read" or
        "write", of ``nbytes`` at ``offset`` in BIRIS memory): nothing while the far side has
        power; otherwise the access times out (module notes).

        Raises:
            BusError: ``ETIMEDOUT``; the access must not happen.
        """
        if self._remote_powered:  # a plain read: the hot path of every BIRIS memory access
            return
        with self._lock:  # (power back meanwhile: this access was under way as it came)
            self._timeouts += 1
            first = not self._status & LocalStatus.TIMEOUT
        if first:
            self._error(LocalStatus.TIMEOUT, "timeout")
        raise BusError(
            f"BIRIS memory {op} of {nbytes} byte(s) at 0x{offset:X} across the Bit 3 coupler "
            f"timed out: the BIRIS crate does not answer "
            f"(LOCAL_STATUS NO_CONNECT: its power is off or the cable is out)",
            errno.ETIMEDOUT,
        )

    def _error(self, bit: LocalStatus, source: str) -> None:
        with self._lock:
            self._status |= int(bit)
            enabled = bool(self._int_control & LocalIntControl.ERROR_INT_ENABLE)
            if enabled:
                self._error_irqs += 1
        if enabled:
            self._gate.raise_irq(source)

    # -- backdoor (no side effects) ------------------------------------------------------------
    @property
    def status(self) -> int:
        """LOCAL_STATUS as the driver would read it."""
        with self._lock:
            return self._status

    @property
    def remote_powered(self) -> bool:
        """The BIRIS crate has power (backdoor)."""
        with self._lock:
            return self._remote_powered

    @property
    def timeouts(self) -> int:
        """Accesses across the cable that timed out (backdoor)."""
        with self._lock:
            return self._timeouts

    @property
    def error_interrupts(self) -> int:
        """Error interrupts the coupler has raised (PERR, BERR and TIMEOUT together)."""
        with self._lock:
            return self._error_irqs

    def snapshot(self) -> bytes:
        """Every register as a read would show it, BIT3_SPACE bytes, without side effects."""
        with self._lock:
            return bytes(self._peek(offset) for offset in range(BIT3_SPACE))

    def _peek(self, offset: int) -> int:
        if offset == Bit3Reg.LOCAL_STATUS:
            return self._status
        if offset == Bit3Reg.LOCAL_INT_CONTROL:
            return self._int_control
        if offset == Bit3Reg.LOCAL_INT_STATUS:
            return CINT2 if self._gate.last_source in BIRIS_SOURCES else 0
        if offset == REMOTE_STATUS:
            return REMOTE_STATUS_IDLE
        if offset == Bit3Reg.REMOTE_CARD_ID:
            return REMOTE_CARD_ID_VALUE
        if offset == Bit3Reg.REMOTE_IACK + 1:
            return self._plain[int(Bit3Reg.LEVEL2_VECTOR)]
        return self._plain.get(offset, 0)

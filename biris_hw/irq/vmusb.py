"""``VmUsbLine``: a VME interrupt delivered by a Wiener VM-USB bridge.

The VM-USB has no interrupt endpoint: when a VME IRQ of a programmed level answers its IACK
with a programmed vector, the bridge runs an *IRQ stack* (a list of reads loaded beforehand)
and sends what it read as a data buffer. So a wake of this line comes with the registers the
interrupt routine decides from, read when the interrupt was serviced: :meth:`VmUsbLine.prefetched`.
The bridge's side (stacks, ISV entries, data taking, the reader thread) is
:class:`biris_hw.bus.vmusb.VmUsbBridge`.

``biris_hw.irq`` and ``biris_hw.bus`` are independent layers of the import contract (pyproject
``[tool.importlinter]``), so this module does not import :mod:`biris_hw.bus.vmusb`: the line
reaches the bridge through the windows it reads, and a line without reads loads the bridge
module by name when it is opened, the way ``open_line("vmusb", ...)`` loads this one.
"""

from __future__ import annotations

import errno
import importlib
import logging
from collections.abc import Sequence
from typing import Any

from biris_hw.errors import BusError
from biris_hw.irq.fdline import FdLine
from regs.vmusb import isv_entry

IRQ_STACK_IDS = range(2, 8)
"""The bridge's IRQ stacks (mirrors :data:`biris_hw.bus.vmusb.IRQ_STACK_IDS`)."""

__all__ = ["VmUsbLine"]

log = logging.getLogger(__name__)

_BRIDGE_MODULE = "biris_hw.bus.vmusb"


class VmUsbLine(FdLine):
    """VME IRQ ``level`` with ``vector``, through a VM-USB.

    ``reads`` are ``(window, offset, width_bits)`` registers the IRQ stack reads, in order, when
    the interrupt is serviced; the windows must be ``vmusb`` windows of one bridge, which the
    line then uses (``serial`` and ``backend``, if given too, must name the same). With no
    reads, ``serial`` / ``backend`` / ``timeout_s`` pick the bridge as for a window.

    ``wait()`` returns the number of events since the previous wait (coalesced, as an eventfd);
    :meth:`prefetched` the values the stack read for the newest of them. ``close()`` clears the
    ISV entry (data taking stops when no line is left) and wakes waiters with ``LineClosed``;
    while the bridge is lost (unplugged), ``wait()`` raises its ``BusError`` (a ``bus`` fault
    upstream) and the line stays open, until a reset re-links the bridge and re-arms the stack.
    """

    kind = "vmusb"

    def __init__(
        self,
        *,
        level: int,
        vector: int,
        reads: Sequence[tuple[Any, int, int]] = (),
        serial: str | None = None,
        backend: Any = None,
        timeout_s: float = 2.0,
    ) -> None:
        for name, value in (("level", level), ("vector", vector)):
            if isinstance(value, bool) or not isinstance(value, int):
                raise ValueError(f"a VME interrupt {name} is a number, not {value!r}")
        try:
            isv_entry(vector, level, IRQ_STACK_IDS.start)  # what an ISV entry can hold
        except ValueError:
            raise ValueError(
                f"VME IRQ level {level} / vector {vector} out of range (1..7, 0..255)"
            ) from None
        vmusb = importlib.import_module(_BRIDGE_MODULE)
        items = list(reads)
        bridge = self._bridge_of(vmusb, items, serial, backend)
        if bridge is not None:
            shared = vmusb.VmUsbBridge.acquire(bridge.serial, bridge.backend, timeout_s)
            if shared is not bridge:  # the windows' bridge has gone; a new one was opened
                shared.release()
                raise BusError(f"VM-USB {bridge.serial} of these windows is gone", errno.ENODEV)
        else:
            bridge = vmusb.VmUsbBridge.acquire(serial, backend, timeout_s)
        self.level = level
        self.vector = vector
        self.error: BusError | None = None
        """Why the line closed itself (the bridge went away), or None."""
        self._bridge: Any = bridge
        self._sub: Any = None
        self._prefetched: tuple[int, ...] | None = None
        super().__init__()
        try:
            stack = vmusb.VmeList()
            for window, offset, width in items:
                window.add_read(stack, offset, width)
            self._sub = bridge.arm_irq(level, vector, stack, on_close=self._bridge_closed)
        except BaseException:
            self._sub = None
            self._closed = True
            self._release()
            raise
        if self._sub.error is not None:  # the bridge failed before the line knew its stack
            self._bridge_closed(self._sub.error)

    @staticmethod
    def _bridge_of(
        vmusb: Any, items: list[tuple[Any, int, int]], serial: str | None, backend: Any
    ) -> Any:
        """The bridge of the windows in ``items`` (None without any); refuses a mixture."""
        bridges: list[Any] = []
        for window, _offset, _width in items:
            if not isinstance(window, vmusb.VmUsbWindow):
                raise ValueError(f"a vmusb line reads vmusb windows only, not {window!r}")
            if window.closed:
                raise BusError(f"{window!r} is closed")
            if not any(window.bridge is b for b in bridges):
                bridges.append(window.bridge)
        if not bridges:
            return None
        if len(bridges) > 1:
            serials = ", ".join(b.serial for b in bridges)
            raise ValueError(f"an IRQ stack runs on one VM-USB; the reads name {serials}")
        bridge = bridges[0]
        if serial is not None and serial != bridge.serial:
            raise ValueError(f"serial {serial} given, but the reads are on {bridge.serial}")
        if backend is not None and backend is not bridge.backend:
            raise ValueError("backend given, but the reads' windows use another one")
        return bridge

    def prefetched(self) -> tuple[int, ...] | None:
        """What the IRQ stack read for the newest event the last successful ``wait()`` took, in
        the order of ``reads``; None before any, or if that event came back short (a VME bus
        error inside the stack)."""
        return self._prefetched

    @property
    def serial(self) -> str:
        return str(self._bridge.serial)

    # -- FdLine hooks --------------------------------------------------------------------------
    def _line_fd(self) -> int:
        return int(self._sub.fileno())

    def _consume(self) -> int:
        count, values = self._sub.take()
        if count:
            self._prefetched = values
        return int(count)

    def _wake_pollers(self) -> None:
        if self._sub is not None:
            self._sub.wake()

    def _release_line(self) -> None:
        sub, self._sub = self._sub, None
        try:
            if sub is not None:
                sub.disarm()
        except BusError as exc:
            log.warning("VM-USB %s: disarming IRQ %d: %s", self.serial, self.level, exc)
        finally:
            self._bridge.release()

    def _bridge_closed(self, error: BusError) -> None:
        """The bridge dropped this IRQ (device gone): close, so every waiter gets LineClosed."""
        self.error = error
        if self._sub is not None:
            self.close()

    def __repr__(self) -> str:
        state = "closed" if self._closed else "armed"
        return f"<VmUsbLine {self.serial} IRQ{self.level} vector 0x{self.vector:02X} {state}>"

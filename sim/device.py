"""``DeviceWindow``: a bus window whose accesses reach a device model, side effects and all.

Register files such as the HCTL-1000's cannot be plain memory: reading R14H latches, writing R0EH
commits. The simulator therefore hands the driver a window that turns every byte access into a
call on the model's *bus* interface (``bus_read``/``bus_write``), keeping the model's backdoor
(peek/poke, no side effects) for the simulator's own use. Wider accesses to a byte-wide board are
split into byte accesses in ascending address order, as a D8 board sees them.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from typing import Protocol

from biris_hw.bus.base import BusWindow

__all__ = ["BusDevice", "DeviceWindow"]


class BusDevice(Protocol):
    """The bus side of a simulated register file: one byte per access, with side effects. A
    device may also offer ``bus_read_block(offsets) -> list[int]``, several reads as one
    transaction (:meth:`DeviceWindow.read_many` uses it)."""

    def bus_read(self, offset: int) -> int: ...

    def bus_write(self, offset: int, value: int) -> None: ...


class DeviceWindow(BusWindow):
    """A window over a :class:`BusDevice`; accesses are serialised with the model's lock."""

    kind = "device"

    def __init__(self, device: BusDevice, size: int, lock: threading.RLock | None = None) -> None:
        super().__init__(size)
        self._device: BusDevice | None = device
        self._lock = lock if lock is not None else threading.RLock()
        self._read_block: Callable[[list[int]], list[int]] | None = getattr(
            device, "bus_read_block", None
        )
        """The device's own transaction read, if it has one (looked up once: read_many is the
        settling poll's path)."""

    def _dev(self) -> BusDevice:
        if self._device is None:  # pragma: no cover - _check() refuses a closed window first
            raise RuntimeError("device window is closed")
        return self._device

    def _read(self, offset: int, n: int) -> bytes:
        dev = self._dev()
        with self._lock:
            return bytes(dev.bus_read(offset + i) & 0xFF for i in range(n))

    def read_many(self, spans: Sequence[tuple[int, int]]) -> list[bytes]:
        """The spans in order as one transaction: by the device's ``bus_read_block`` when it
        has one (it takes its own lock), else one access after another under one hold of the
        model's lock (what the default does, without taking the lock and building a generator
        per span: a settling poll's six register bytes are the simulator's commonest access)."""
        checked = list(spans)
        for offset, n in checked:
            self._check(offset, n, 1)
        device = self._dev()
        block = self._read_block
        if block is not None:
            values = block([offset + i for offset, n in checked for i in range(n)])
            out: list[bytes] = []
            at = 0
            for _, n in checked:
                out.append(bytes([value & 0xFF for value in values[at : at + n]]))
                at += n
            return out
        read = device.bus_read
        with self._lock:
            return [bytes([read(offset + i) & 0xFF for i in range(n)]) for offset, n in checked]

    def _write(self, offset: int, data: bytes) -> None:
        dev = self._dev()
        with self._lock:
            for i, byte in enumerate(data):
                dev.bus_write(offset + i, byte)

    def _close(self) -> None:
        self._device = None
        self._read_block = None

"""The ``memory`` window: a bytearray in this process, the hardware-free default."""

from __future__ import annotations

from biris_hw.bus.base import BufferWindow

__all__ = ["MemoryWindow"]


class MemoryWindow(BufferWindow):
    """A zero-filled span of process memory, or one laid over a caller's writable buffer
    (a ``bytearray``, or a ``memoryview`` such as part of a shared-memory segment).

    The simulator and the driver share one ``MemoryWindow`` when both run in one process; that
    is the in-process equivalent of BIRIS memory seen through the coupler.
    """

    kind = "memory"

    def __init__(self, size: int, buffer: bytearray | memoryview | None = None) -> None:
        if buffer is not None and len(buffer) < size:
            raise ValueError(f"buffer of {len(buffer)} bytes is smaller than size {size}")
        self._array = buffer if buffer is not None else bytearray(max(size, 1))
        super().__init__(self._array, size)

    def _release(self) -> None:
        self._array = bytearray()  # the caller's buffer, if any, stays the caller's

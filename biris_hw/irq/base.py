"""The interrupt-line contract: how a notifier waits for an interrupt (docs/registers.md)."""

from __future__ import annotations

from abc import ABC, abstractmethod
from types import TracebackType
from typing import ClassVar, TypeVar

__all__ = ["InterruptLine"]

_Self = TypeVar("_Self", bound="InterruptLine")


class InterruptLine(ABC):
    """One interrupt source that a thread can block on.

    ``wait(timeout)`` returns the number of interrupts since the previous wait (more than 1 when
    they were coalesced) or 0 on timeout; it raises :class:`~biris_hw.errors.LineClosed` once the
    line is closed, including for a thread that was already blocked in it. ``fileno()`` gives a
    descriptor that polls readable while an interrupt is pending, so callers can multiplex.
    """

    kind: ClassVar[str] = "abstract"

    @abstractmethod
    def wait(self, timeout: float | None = None) -> int:
        """Block until an interrupt (returns the count) or ``timeout`` seconds (returns 0)."""

    @abstractmethod
    def fileno(self) -> int:
        """A descriptor that is readable while an interrupt is pending."""

    @abstractmethod
    def close(self) -> None:
        """Wake every waiter (they raise ``LineClosed``) and release the line; idempotent."""

    @property
    @abstractmethod
    def closed(self) -> bool:
        """True once :meth:`close` has been called."""

    def __enter__(self: _Self) -> _Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

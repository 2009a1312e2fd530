"""Harmony's interrupt demultiplexing, generically: one physical line into logical lines.

Harmony lets several logical interrupts share one physical level and demultiplexes them in a
service routine; a notifier task blocks on its logical interrupt only. :class:`Demultiplexer` is
that routine's frame, with nothing device-specific in it: a thread that waits on the physical
line *and* on its own stop eventfd (one ``poll``, so ``close()`` is immediate and shutdown wins
over an interrupt flood), one :class:`EventFdLine` per logical interrupt, counters, and the
lifecycle. A subclass says which logical interrupts it carries and implements
:meth:`Demultiplexer._service`, which decodes ``count`` coalesced physical interrupts (by reading
the devices' status registers) and raises logical ones with :meth:`Demultiplexer._raise`.

The BIRIS server's two routines (level 2: BIRIS and the Bit 3 coupler; level 3: the Model 7600)
decode the report's protocol, so they live with the server: :mod:`biris_hw.server.isr`.

A demultiplexer does not own the physical line (the hardware bundle does). It runs in one of two
ways, for two kinds of owner:

* :meth:`Demultiplexer.run` (and :meth:`Demultiplexer.start`, which runs it in a thread of its
  own) stands alone. If the physical line is closed under it, it closes its logical lines, so
  every notifier raises ``LineClosed``. It does the same after logging any unexpected failure of
  ``_service`` or of the line, so that no notifier waits forever on a dead routine.
* :meth:`Demultiplexer.serve` is the same routine for a supervisor (the BIRIS server runs every
  task under one). It *raises* instead: :class:`~biris_hw.errors.BusError` when the physical line
  is closed under it or fails (the target is gone, which is a bus fault, not a quiet end), or
  whatever ``_service`` raised. It leaves the logical lines open, so the notifiers keep waiting
  and the supervisor can report the failure and run the routine again later.

Either way :meth:`Demultiplexer.close` stops and joins the thread, and only then closes the stop
eventfd and the logical lines.

An owner that expected an interrupt and has not seen it (an edge lost on the way: a motor
watchdog running out on a move whose profile has in fact ended) calls
:meth:`Demultiplexer.recheck`: the routine's thread then reads the devices once as if they had
interrupted (:meth:`Demultiplexer._look`), so a lost interrupt costs a delay, not the move.

A demultiplexer given a time base (``timebase=``, issue 22) belongs to that rig's domain: its
thread is the time base's (:meth:`~biris_hw.timebase.TimeBase.Thread`), its logical lines are
:class:`EventFdLine` on the same time base, every write to its stop and look descriptors is
followed by a :meth:`~biris_hw.timebase.TimeBase.kick`, and on virtual time the thread polls
through the time base, so the domain sees it waiting for an interrupt rather than running. The
physical line must then be raised with a kick of the same time base too (an :class:`EventFdLine`
made with it, which the simulator triggers): in virtual time nothing else wakes the routine.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import select
import threading
from abc import ABC, abstractmethod
from collections.abc import Callable, Collection, Hashable, Iterable, Iterator
from types import TracebackType
from typing import Any, Generic, TypeVar

from biris_hw.errors import BusError, LineClosed
from biris_hw.irq.base import InterruptLine
from biris_hw.irq.eventfd import EventFdLine
from biris_hw.timebase import HwEvent, HwThread, TimeBase

__all__ = ["Demultiplexer"]

log = logging.getLogger(__name__)

K = TypeVar("K", bound=Hashable)
_D = TypeVar("_D", bound="Demultiplexer[Any]")


def _label(logical: object) -> str:
    """An enum member's name, anything else's repr: for messages."""
    name = getattr(logical, "name", None)
    return name if isinstance(name, str) else repr(logical)


class Demultiplexer(ABC, Generic[K]):
    """A service routine's thread on a physical line, raising the logical lines it ``carries``.

    ``name`` names the thread and the log lines. ``carries`` are the logical interrupts (any
    hashable keys, typically an enum's members), each with its own line and counter.
    ``timebase``: the time base of the rig whose domain the routine belongs to (module notes);
    None for none (its thread is then a plain thread, its waits real ones).
    """

    def __init__(
        self,
        line: InterruptLine,
        carries: Iterable[K],
        name: str,
        *,
        timebase: TimeBase | None = None,
    ) -> None:
        self.name = name
        self.timebase = timebase
        """The time base given, if any."""
        self._virtual = timebase if timebase is not None and timebase.virtual else None
        self._line = line
        self._lines: dict[K, EventFdLine] = {}
        try:
            for logical in carries:
                self._lines[logical] = EventFdLine(timebase=timebase)
            self._stop_fd = os.eventfd(0, os.EFD_CLOEXEC | os.EFD_NONBLOCK)
        except BaseException:
            self._close_logical()
            raise
        try:
            self._look_fd = os.eventfd(0, os.EFD_CLOEXEC | os.EFD_NONBLOCK)
        except BaseException:
            os.close(self._stop_fd)
            self._close_logical()
            raise
        self._lifecycle = threading.Lock()
        self._stats = threading.Lock()
        self._counts: dict[K, int] = dict.fromkeys(self._lines, 0)
        self._spurious = 0
        self._thread: threading.Thread | None = None
        self._closed = False
        # set once close() has finished; a second closer waits on it, in the domain if any
        self._shut: threading.Event | HwEvent = (
            threading.Event() if timebase is None else timebase.Event()
        )
        self._serving = False  # the service thread is inside _serve (under _lifecycle)
        self._release_on_exit = False  # close() ran in that thread: it releases the stop fd

    # -- what notifiers and status reports use ---------------------------------------------------
    @property
    def carries(self) -> tuple[K, ...]:
        """The logical interrupts this routine raises, in the order given."""
        return tuple(self._lines)

    def line(self, logical: K) -> InterruptLine:
        """The line a notifier blocks on for ``logical``; ValueError if this routine lacks it."""
        try:
            return self._lines[logical]
        except KeyError:
            raise ValueError(f"{self.name} does not carry {_label(logical)}") from None

    @property
    def counts(self) -> dict[K, int]:
        """Interrupts raised so far per logical kind (a copy)."""
        with self._stats:
            return dict(self._counts)

    @property
    def spurious(self) -> int:
        """Physical interrupts that turned out to have no source."""
        with self._stats:
            return self._spurious

    @property
    def running(self) -> bool:
        """True while the service thread is alive."""
        thread = self._thread
        return thread is not None and thread.is_alive()

    @property
    def closed(self) -> bool:
        return self._closed

    def recheck(self) -> None:
        """Ask the routine to look at the devices as if they had interrupted (:meth:`_look`),
        from any thread, without waiting: for an owner that expected an interrupt and has not
        seen it (a lost edge). Nothing once closed."""
        with self._lifecycle:
            if not self._closed:
                os.eventfd_write(self._look_fd, 1)
                self._kick(self._look_fd)

    # -- lifecycle -------------------------------------------------------------------------------
    def start(self) -> None:
        """Start servicing the physical line in a thread named :attr:`name`; RuntimeError if
        started before or closed."""
        with self._lifecycle:
            self._check_startable()
            if self.timebase is not None:
                self._thread = self.timebase.Thread(self.run, name=self.name, daemon=True)
            else:
                self._thread = threading.Thread(target=self.run, name=self.name, daemon=True)
            self._thread.start()

    def run(self) -> None:
        """The service thread's body, standing alone: serve the physical line until closed.

        For an owner that makes the thread itself; :meth:`start` runs it too. Returns at once if
        the demultiplexer was closed before the thread got here; RuntimeError if another thread
        already serves it. When the physical line is closed under it, or anything fails, the
        logical lines are closed (see the module notes).
        """
        if not self._enter():
            return
        try:
            with self._serving_scope():
                self._serve()
        except LineClosed:
            log.info("%s: physical line closed; closing its logical lines", self.name)
            self._close_logical()
        except Exception:
            log.exception("%s failed; closing its logical lines", self.name)
            self._close_logical()

    def serve(self) -> None:
        """The service thread's body, under a supervisor: serve until :meth:`close`, or raise.

        Raises :class:`BusError` when the physical line is closed under the routine or fails
        (both mean the target is gone), and whatever ``_service`` raised. The logical lines stay
        open, so the notifiers go on waiting on them. The same thread may call it again after a
        failure (a supervisor restarting the routine); RuntimeError if another thread serves it.
        Returns at once once the demultiplexer is closed.
        """
        if not self._enter():
            return
        try:
            with self._serving_scope():
                self._serve()
        except LineClosed as exc:
            if self._closed:
                return
            raise BusError(
                f"{self.name}: its physical interrupt line was closed under it ({exc}); "
                "the target is gone",
                errno.ENODEV,
            ) from exc

    @contextlib.contextmanager
    def _serving_scope(self) -> Iterator[None]:
        """Mark the thread as inside the routine; on the way out, release the stop descriptor
        if :meth:`close` was called from inside (it could not: the routine still polled it)."""
        with self._lifecycle:
            self._serving = True
        try:
            yield
        finally:
            with self._lifecycle:
                self._serving = False
                release, self._release_on_exit = self._release_on_exit, False
            if release:
                os.close(self._stop_fd)
                os.close(self._look_fd)

    def _enter(self) -> bool:
        """Claim the routine for the calling thread; False if it is closed already."""
        with self._lifecycle:
            if self._closed:
                return False
            me = threading.current_thread()
            if self._thread is not me:
                self._check_startable()
                self._thread = me
        return True

    def _check_startable(self) -> None:
        if self._closed:
            raise RuntimeError(f"{self.name} is closed")
        if self._thread is not None:
            raise RuntimeError(f"{self.name} is already running")

    def close(self) -> None:
        """Stop and join the thread, then close the logical lines (waking their notifiers).

        Leaves the physical line open: it belongs to the hardware bundle. Idempotent; a second
        caller returns once the first has finished.
        """
        with self._lifecycle:
            first = not self._closed
            self._closed = True
            thread = self._thread
            if first:
                os.eventfd_write(self._stop_fd, 1)
                self._kick(self._stop_fd)
        me = threading.current_thread()
        if not first:
            if thread is not me:
                if isinstance(self._shut, threading.Event):
                    self._shut.wait()
                else:
                    self._shut.wait(what=f"{self.name} to close")
            return
        # joined outside the lock: a thread that has yet to enter run() takes it there
        if thread is not None and thread is not me:
            if isinstance(thread, HwThread):
                # a wait in its time base's domain: the closer may be a participant
                thread.timebase.join_thread(thread)
            else:
                thread.join()
        self._close_logical()
        with self._lifecycle:
            # From inside the routine (a callback that closes it), the routine still polls the
            # stop descriptor, so it releases it on its way out; anywhere else nobody polls it.
            inside = thread is me and self._serving
            self._release_on_exit = inside
        if not inside:
            os.close(self._stop_fd)
            os.close(self._look_fd)
        self._shut.set()

    def __enter__(self: _D) -> _D:
        """Start the thread (unless already started); the block ends with :meth:`close`."""
        if self._thread is None:
            self.start()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    # -- the service thread ----------------------------------------------------------------------
    def _serve(self) -> None:
        """Serve until the stop descriptor is written; LineClosed once the physical line is
        closed, and whatever the line's wait or ``_service`` raised."""
        line_fd = self._line.fileno()  # LineClosed if it is closed already
        ready_fds = self._waiter(line_fd)
        while True:
            ready = ready_fds()
            if self._stop_fd in ready:  # checked first: shutdown wins over an interrupt flood
                return
            if line_fd in ready:
                count = self._line.wait(0)
                if count:
                    self._service(count)
            if self._look_fd in ready:
                with contextlib.suppress(BlockingIOError):
                    os.eventfd_read(self._look_fd)
                self._look()

    def _waiter(self, line_fd: int) -> Callable[[], Collection[int]]:
        """How the service thread blocks until one of its descriptors is ready: a real poll, or
        through a virtual time base (which must see the wait)."""
        fds = (self._stop_fd, line_fd, self._look_fd)
        timebase = self._virtual
        if timebase is not None:
            what = f"{self.name}: its physical interrupt line"
            return lambda: timebase.poll(fds, None, what=what)
        poller = select.poll()
        poller.register(self._stop_fd, select.POLLIN)
        poller.register(line_fd, select.POLLIN | select.POLLERR)
        poller.register(self._look_fd, select.POLLIN)
        return lambda: dict(poller.poll())

    def _kick(self, fd: int) -> None:
        """Tell the time base that ``fd`` (the stop or look descriptor) was just written."""
        if self.timebase is not None:
            self.timebase.kick(fd)

    def _close_logical(self) -> None:
        for logical_line in self._lines.values():
            logical_line.close()

    # -- for subclasses ----------------------------------------------------------------------------
    def _raise(self, logical: K, count: int = 1, *, counted: bool = True) -> None:
        """Raise a logical interrupt and (unless ``counted`` is False) count it.

        Counted under the same lock as the trigger, so a notifier that has been woken always
        finds its interrupt in :attr:`counts`.
        """
        with self._stats:
            try:
                self._lines[logical].trigger(count)
            except LineClosed:
                log.debug("%s line closed by its user; interrupt dropped", _label(logical))
                return
            if counted:
                self._counts[logical] += count

    def _count(self, logical: K, count: int) -> None:
        """Count ``count`` interrupts of ``logical`` that the routine handled without raising
        its line."""
        with self._stats:
            self._counts[logical] += count

    def _count_spurious(self, count: int) -> None:
        with self._stats:
            self._spurious += count

    @abstractmethod
    def _service(self, count: int) -> None:
        """Decode ``count`` coalesced physical interrupts into logical ones."""

    def _look(self) -> None:
        """:meth:`recheck` asked: read the devices with no interrupt behind it, raising what
        they say has happened. Nothing by default (a routine whose devices keep no state to
        read again)."""

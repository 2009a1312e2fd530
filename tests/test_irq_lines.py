"""Interrupt lines: EventFdLine, UioLine (on a socket pair) and PollLine, plus the kind registry."""

from __future__ import annotations

import errno
import os
import select
import socket
import struct
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field

import pytest

from biris_hw.errors import BusError, LineClosed, UnknownKind
from biris_hw.irq import (
    LINE_KINDS,
    EventFdLine,
    FdLine,
    InterruptLine,
    PollLine,
    UioLine,
    open_line,
    register_line,
    registry,
)
from biris_hw.timebase import HwThread, ScaledTime, VirtualTime, VirtualTimeDeadlock
from tests.conftest import until

RELEASE_BOUND = 2.0
"""Real seconds within which close() must free a blocked waiter: at once, on a quiet machine a
millisecond; the bound allows a 2-core host running three CPU-bound processes beside the
tests (make test-under-load), where a woken thread may wait a second for a core."""

WAIT = 5.0
"""Timeout for things that should happen almost at once; only reached when a test fails."""

TOTAL = struct.Struct("=i")


def open_fds() -> int:
    return len(os.listdir("/proc/self/fd"))


@dataclass
class Waiter:
    """A thread blocked in ``line.wait()`` with no timeout; records how it ended, and when."""

    line: InterruptLine
    result: object = None
    ended_at: float = 0.0
    done: threading.Event = field(default_factory=threading.Event)

    def __post_init__(self) -> None:
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        try:
            self.result = self.line.wait()
        except Exception as exc:
            self.result = exc
        self.ended_at = time.monotonic()
        self.done.set()

    def blocked(self) -> bool:
        assert isinstance(self.line, FdLine)
        return until(lambda: self.line._waiters == 1)  # type: ignore[attr-defined]


def assert_close_releases(line: InterruptLine) -> None:
    waiter = Waiter(line)
    assert waiter.blocked(), "the waiter never blocked"
    assert not waiter.done.is_set()
    started = time.monotonic()
    line.close()
    assert waiter.done.wait(WAIT)
    assert isinstance(waiter.result, LineClosed)
    assert waiter.ended_at - started < RELEASE_BOUND
    waiter.thread.join(WAIT)


def readable(line: InterruptLine) -> bool:
    poller = select.poll()
    poller.register(line.fileno(), select.POLLIN)
    return bool(poller.poll(0))


# -- EventFdLine ---------------------------------------------------------------------------------


def test_eventfd_trigger_then_wait_returns_one() -> None:
    line = EventFdLine()
    with line:
        assert not readable(line)
        line.trigger()
        assert readable(line)
        assert line.wait(WAIT) == 1
        assert not readable(line)


def test_eventfd_coalesces_triggers() -> None:
    line = EventFdLine()
    with line:
        line.trigger()
        line.trigger(2)
        assert line.wait(WAIT) == 3
        assert line.wait(0) == 0


def test_eventfd_timeout_returns_zero_after_the_timeout() -> None:
    with EventFdLine() as line:
        started = time.monotonic()
        assert line.wait(0.05) == 0
        assert time.monotonic() - started >= 0.04


def test_eventfd_refuses_a_count_below_one() -> None:
    line = EventFdLine()
    with line, pytest.raises(ValueError):
        line.trigger(0)


def test_eventfd_closed_line_raises_line_closed() -> None:
    line = EventFdLine()
    line.trigger()
    line.close()
    line.close()  # idempotent
    assert line.closed
    with pytest.raises(LineClosed):
        line.wait(0)
    with pytest.raises(LineClosed):
        line.trigger()
    with pytest.raises(LineClosed):
        line.fileno()


def test_eventfd_close_releases_a_blocked_waiter() -> None:
    assert_close_releases(EventFdLine())


def test_eventfd_close_wakes_a_thread_polling_its_fileno() -> None:
    line = EventFdLine()
    poller = select.poll()
    poller.register(line.fileno(), select.POLLIN)
    line.close()
    assert poller.poll(int(WAIT * 1000)), "closing did not make the descriptor readable"
    with pytest.raises(LineClosed):
        line.wait(0)


def test_eventfd_triggers_racing_close_never_hit_a_dead_descriptor() -> None:
    for _ in range(20):
        line = EventFdLine()
        errors: list[BaseException] = []

        def hammer(target: EventFdLine = line, sink: list[BaseException] = errors) -> None:
            while True:
                try:
                    target.trigger()
                except LineClosed:
                    return
                except BaseException as exc:
                    sink.append(exc)
                    return

        thread = threading.Thread(target=hammer)
        thread.start()
        line.close()
        thread.join(WAIT)
        assert not thread.is_alive()
        assert errors == []


def test_eventfd_leaks_no_descriptor() -> None:
    before = open_fds()
    line = EventFdLine()
    line.trigger()
    assert line.wait(WAIT) == 1
    assert_close_releases(line)
    assert open_fds() == before


# -- UioLine ---------------------------------------------------------------------------------------


@pytest.fixture
def uio() -> Iterator[tuple[UioLine, socket.socket]]:
    """A UioLine on one end of a socket pair; the test plays the kernel on the other end."""
    ours, kernel = socket.socketpair()
    kernel.settimeout(WAIT)
    line = UioLine(fd=ours.detach())
    try:
        yield line, kernel
    finally:
        line.close()
        kernel.close()


def test_uio_first_read_counts_as_one_then_deltas(uio: tuple[UioLine, socket.socket]) -> None:
    line, kernel = uio
    kernel.sendall(TOTAL.pack(57))  # interrupts from before we listened are not ours
    assert line.wait(WAIT) == 1
    assert kernel.recv(4) == TOTAL.pack(1)
    kernel.sendall(TOTAL.pack(58))
    assert line.wait(WAIT) == 1
    assert kernel.recv(4) == TOTAL.pack(1)


def test_uio_gap_in_totals_is_coalesced_interrupts(uio: tuple[UioLine, socket.socket]) -> None:
    line, kernel = uio
    kernel.sendall(TOTAL.pack(1))
    assert line.wait(WAIT) == 1
    kernel.sendall(TOTAL.pack(4))
    assert line.wait(WAIT) == 3
    assert kernel.recv(8) == TOTAL.pack(1) * 2


def test_uio_total_wrapping_past_s32(uio: tuple[UioLine, socket.socket]) -> None:
    line, kernel = uio
    kernel.sendall(TOTAL.pack(0x7FFF_FFFF))
    assert line.wait(WAIT) == 1
    kernel.sendall(TOTAL.pack(-0x8000_0000 + 1))
    assert line.wait(WAIT) == 2


def test_uio_timeout_returns_zero(uio: tuple[UioLine, socket.socket]) -> None:
    line, _ = uio
    assert line.wait(0.02) == 0


def test_uio_without_reenable_writes_nothing() -> None:
    ours, kernel = socket.socketpair()
    with UioLine(fd=ours.detach(), reenable=False) as line:
        kernel.sendall(TOTAL.pack(3))
        assert line.wait(WAIT) == 1
        kernel.setblocking(False)
        with pytest.raises(BlockingIOError):
            kernel.recv(4)
    kernel.close()


def test_uio_short_read_is_a_bus_error(uio: tuple[UioLine, socket.socket]) -> None:
    line, kernel = uio
    kernel.sendall(b"\x01\x00")
    with pytest.raises(BusError, match="2 byte"):
        line.wait(WAIT)


def test_uio_vanished_device_is_a_bus_error(uio: tuple[UioLine, socket.socket]) -> None:
    line, kernel = uio
    kernel.close()
    with pytest.raises(BusError, match="0 byte"):
        line.wait(WAIT)


def test_uio_open_failure_is_a_clear_bus_error(tmp_path: os.PathLike[str]) -> None:
    missing = os.path.join(os.fspath(tmp_path), "uio9")
    with pytest.raises(BusError) as info:
        UioLine(missing)
    assert isinstance(info.value, OSError)
    assert info.value.errno == errno.ENOENT
    assert missing in str(info.value)


def test_uio_close_releases_a_blocked_waiter(uio: tuple[UioLine, socket.socket]) -> None:
    line, _ = uio
    assert_close_releases(line)


def test_uio_leaks_no_descriptor() -> None:
    before = open_fds()
    ours, kernel = socket.socketpair()
    line = UioLine(fd=ours.detach())
    kernel.sendall(TOTAL.pack(1))
    assert line.wait(WAIT) == 1
    assert_close_releases(line)
    kernel.close()
    assert open_fds() == before


# -- PollLine --------------------------------------------------------------------------------------


def poll_threads() -> int:
    return sum(thread.name == "biris-poll-line" for thread in threading.enumerate())


class Flag:
    """A sticky status bit with write-1-to-clear acknowledgement, as a register would have."""

    def __init__(self) -> None:
        self.set = False
        self.acks = 0

    def is_set(self) -> bool:
        return self.set

    def acknowledge(self) -> None:
        self.acks += 1
        self.set = False


def test_poll_fires_on_the_predicate_and_acknowledges() -> None:
    flag = Flag()
    with PollLine(flag.is_set, 0.002, acknowledge=flag.acknowledge) as line:
        assert line.wait(0.05) == 0
        assert flag.acks == 0
        flag.set = True
        assert line.wait(WAIT) == 1
        assert flag.acks == 1
        assert not flag.set
        assert line.wait(0.05) == 0  # acknowledged: the level no longer fires


def test_poll_without_acknowledge_fires_while_the_level_holds() -> None:
    with PollLine(lambda: True, 0.002) as line:
        assert line.wait(WAIT) >= 1
        assert line.wait(WAIT) >= 1


def test_poll_predicate_failure_is_raised_by_wait() -> None:
    calls = 0

    def predicate() -> bool:
        nonlocal calls
        calls += 1
        if calls == 1:
            return True
        raise RuntimeError("status register unreadable")

    line = PollLine(predicate, 0.002)
    with line:
        assert line.wait(WAIT) == 1  # what fired before the failure is still delivered
        for _ in range(2):  # and the line stays broken
            with pytest.raises(BusError, match="unreadable") as info:
                line.wait(WAIT)
            assert isinstance(info.value.__cause__, RuntimeError)
        assert isinstance(line.error, RuntimeError)
        assert readable(line)


def test_poll_acknowledge_failure_is_raised_by_wait() -> None:
    def acknowledge() -> None:
        raise OSError(errno.EIO, "write failed")

    with PollLine(lambda: True, 0.002, acknowledge=acknowledge) as line:
        with pytest.raises(BusError) as info:
            line.wait(WAIT)
        assert isinstance(info.value.__cause__, OSError)


@pytest.mark.parametrize("period", [0, -1.0, float("nan"), float("inf")])
def test_poll_refuses_a_bad_period(period: float) -> None:
    with pytest.raises(ValueError):
        PollLine(lambda: False, period)


def test_poll_close_is_prompt_even_with_a_long_period() -> None:
    threads = poll_threads()
    line = PollLine(lambda: False, 30.0)
    assert poll_threads() == threads + 1
    assert_close_releases(line)
    assert poll_threads() == threads  # close() joined the thread


def test_poll_closed_from_its_own_acknowledge() -> None:
    before = open_fds()
    threads = poll_threads()
    holder: list[PollLine] = []
    acked = threading.Event()

    def acknowledge() -> None:
        acked.set()
        holder[0].close()

    line = PollLine(lambda: acked.is_set() or bool(holder), 0.002, acknowledge=acknowledge)
    waiter = Waiter(line)
    assert waiter.blocked()
    holder.append(line)
    assert waiter.done.wait(WAIT)
    assert isinstance(waiter.result, LineClosed)
    assert line.closed
    assert until(lambda: poll_threads() == threads)
    line.close()  # idempotent from outside too
    assert open_fds() == before


def test_poll_leaks_no_descriptor() -> None:
    before = open_fds()
    flag = Flag()
    flag.set = True
    line = PollLine(flag.is_set, 0.002, acknowledge=flag.acknowledge)
    assert line.wait(WAIT) == 1
    assert_close_releases(line)
    assert open_fds() == before


# -- registry -------------------------------------------------------------------------------------


def test_open_line_builds_each_builtin_kind() -> None:
    assert set(LINE_KINDS) >= {"eventfd", "uio", "poll"}
    with open_line("eventfd") as line:
        assert isinstance(line, EventFdLine) and line.kind == "eventfd"
    ours, kernel = socket.socketpair()
    with open_line("uio", fd=ours.detach()) as line:
        assert isinstance(line, UioLine) and line.kind == "uio"
    kernel.close()
    with open_line("poll", predicate=lambda: False, period=1.0) as line:
        assert isinstance(line, PollLine) and line.kind == "poll"


def test_open_line_unknown_kind() -> None:
    with pytest.raises(UnknownKind, match="vfio"):
        open_line("vfio")


def test_register_line_adds_a_kind() -> None:
    class Loopback(EventFdLine):
        kind = "loopback-test"

    register_line("loopback-test", Loopback)
    try:
        with open_line("loopback-test") as line:
            assert isinstance(line, Loopback)
    finally:
        registry._REGISTRY.unregister("loopback-test")
    assert "loopback-test" not in LINE_KINDS


# -- on virtual time ------------------------------------------------------------------------------
# The test's thread drives the domain: time moves only while it waits in it, so every instant is
# exact. A stall_timeout makes a wait the domain cannot see (a real poll) fail, naming who is
# stuck, instead of hanging.


class VirtualWaiter:
    """A thread of ``tb`` blocked in ``line.wait(timeout)``; records how it ended, and when."""

    def __init__(self, tb: VirtualTime, line: InterruptLine, timeout: float | None = None) -> None:
        self.tb = tb
        self.ended: tuple[object, float] | None = None

        def run() -> None:
            try:
                result: object = line.wait(timeout)
            except Exception as exc:
                result = exc
            self.ended = (result, tb.now())

        self.thread: HwThread = tb.Thread(run, name="notifier", daemon=True)
        self.thread.start()

    def result(self) -> tuple[object, float]:
        assert self.tb.join_thread(self.thread), "the waiter never ended"
        assert self.ended is not None
        return self.ended


def test_virtual_eventfd_waiter_is_woken_by_a_trigger_at_that_instant() -> None:
    tb = VirtualTime(stall_timeout=WAIT)
    before = open_fds()
    with EventFdLine(timebase=tb) as line:
        waiter = VirtualWaiter(tb, line)
        tb.sleep(2.0)  # the waiter waits on the line all the while: time can pass
        line.trigger(3)
        assert waiter.result() == (3, 2.0)
        assert line.wait(0) == 0  # all three taken at once

        def interrupt() -> None:  # what the simulator does from its own thread
            tb.sleep(0.5)
            line.trigger()

        raiser = tb.Thread(interrupt, name="simulator", daemon=True)
        raiser.start()
        assert line.wait(WAIT) == 1
        assert tb.now() == 2.5
        assert tb.join_thread(raiser)
    assert open_fds() == before and tb.deadlock is None


def test_virtual_eventfd_wait_times_out_at_its_virtual_deadline() -> None:
    tb = VirtualTime(start=1.0 / 3.0, stall_timeout=WAIT, nominal_scale=10.0)
    with EventFdLine(timebase=tb) as line:
        t0 = tb.now()
        assert line.wait(0.25) == 0  # a caller's 0.25 s: 2.5 hardware seconds
        assert tb.now() == t0 + tb.timeout_hw(0.25)
        assert line.wait(0) == 0  # a look, not a wait: no time passes
        assert tb.now() == t0 + tb.timeout_hw(0.25)
        line.trigger()
        assert line.wait(0.25) == 1  # pending already: no time passes either
        assert tb.now() == t0 + tb.timeout_hw(0.25)
        waiter = VirtualWaiter(tb, line, timeout=0.1)
        assert waiter.result() == (0, t0 + tb.timeout_hw(0.25) + tb.timeout_hw(0.1))


def test_virtual_eventfd_close_wakes_the_waiter_with_line_closed() -> None:
    tb = VirtualTime(stall_timeout=WAIT)
    before = open_fds()
    line = EventFdLine(timebase=tb)
    waiter = VirtualWaiter(tb, line)
    tb.sleep(1.0)
    line.close()
    result, at = waiter.result()
    assert isinstance(result, LineClosed) and at == 1.0
    assert open_fds() == before  # the waiter, last out, released the descriptors


def test_a_virtual_eventfd_nobody_triggers_is_a_deadlock_naming_the_line() -> None:
    tb = VirtualTime(stall_timeout=WAIT)
    with EventFdLine(timebase=tb) as line:
        with pytest.raises(VirtualTimeDeadlock, match="interrupt line eventfd"):
            line.wait()
        assert line._waiters == 0


def test_an_eventfd_on_scaled_time_waits_for_real() -> None:
    with EventFdLine(timebase=ScaledTime(1000.0)) as line:  # timeouts stay the caller's seconds
        started = time.monotonic()
        assert line.wait(0.05) == 0
        assert time.monotonic() - started >= 0.04
        line.trigger()
        assert line.wait(WAIT) == 1


def test_virtual_poll_line_checks_once_a_period_of_hardware_time() -> None:
    tb = VirtualTime(stall_timeout=WAIT)
    before = open_fds()
    flag = Flag()
    checks: list[float] = []

    def predicate() -> bool:
        checks.append(tb.now())
        return flag.is_set()

    def raise_level() -> None:
        tb.sleep_until(1.1)
        flag.set = True

    line = PollLine(predicate, 0.25, acknowledge=flag.acknowledge, timebase=tb)
    raiser = tb.Thread(raise_level, name="device", daemon=True)
    raiser.start()
    assert line.wait(10.0) == 1
    assert tb.now() == 1.25  # the first check after the level rose
    assert checks == [0.0, 0.25, 0.5, 0.75, 1.0, 1.25]
    assert flag.acks == 1 and tb.join_thread(raiser)
    assert line.wait(0.3) == 0 and tb.now() == 1.25 + 0.3
    line.close()  # joins the polling thread in the domain
    assert line.closed and not line._thread.is_alive()
    assert open_fds() == before

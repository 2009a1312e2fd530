"""A lost target is a ``bus`` fault (issue 11; review defect 9), noticed whether or not a register
is being read, within a stated bound, during initialisation too.

The pieces first: the interrupt service routine under supervision (a physical line closed under
it, a board that can no longer be read) and the remote target's interrupt line (the simulator's
socket hung up). Then end to end: an in-process rig closed under a continuous scan, and a
``biris sim`` process killed under one. In each, every blocked caller gets HardwareFault("bus")
within :data:`DETECTION_S`, and the next reset does too.

Detection bounds (stated in ``biris_hw.irq.demux``, ``biris_hw.simlink`` and
``biris_hw.server.tasks``): a closed line or a hung-up socket wakes the routine's ``poll`` at
once. There is no timer and no polling period, so what is measured here is one thread wake-up,
a one-way post and one administrator case: milliseconds.
"""

from __future__ import annotations

import contextlib
import errno
import os
import pathlib
import select
import signal
import socket
import subprocess
import sys
import threading
import time
import types
import uuid
from collections.abc import Callable, Iterator
from multiprocessing import resource_tracker
from typing import Any, cast

import pytest

from biris_hw import BirisInitRecord, ConnectionKind
from biris_hw.bus.memory import MemoryWindow
from biris_hw.bus.remote import default_socket_path
from biris_hw.errors import BusError, HardwareFault
from biris_hw.irq import EventFdLine
from biris_hw.server import BirisServer
from biris_hw.server.isr import Level3Demux, Logical
from biris_hw.simlink import LinkedLine, RemoteHardware, attach
from regs.tech80 import MOTION_WINDOW_SIZE, AxisBit, BoardReg
from sim.rig import SimulatedBiris
from tests.conftest import WAIT, until

DETECTION_S = 1.0
"""Bound asserted from the target's loss to every blocked caller holding HardwareFault("bus").
Measured in milliseconds (see the module notes); generous for a loaded 2-core machine."""


# -- the routine and the line ---------------------------------------------------------------------


def _serve_in_thread(
    demux: Level3Demux,
) -> tuple[threading.Thread, list[tuple[BaseException, float]]]:
    """Run ``demux.serve`` (as the server's supervisor does) and keep what it raised, and when."""
    raised: list[tuple[BaseException, float]] = []

    def body() -> None:
        try:
            demux.serve()
        except BaseException as exc:
            raised.append((exc, time.monotonic()))

    thread = threading.Thread(target=body, name=demux.name)
    thread.start()
    until(lambda: demux.running, what="the routine to start")
    return thread, raised


def test_a_physical_line_closed_under_the_routine_is_a_bus_error(no_leaks: None) -> None:
    with EventFdLine() as physical, MemoryWindow(MOTION_WINDOW_SIZE) as motion:
        demux = Level3Demux(physical, motion)
        thread, raised = _serve_in_thread(demux)
        closed = time.monotonic()
        physical.close()  # the hardware bundle closed under the server
        thread.join(WAIT)
        assert not thread.is_alive() and len(raised) == 1
        error, when = raised[0]
        assert isinstance(error, BusError) and error.errno == errno.ENODEV
        assert "closed under it" in str(error) and "target is gone" in str(error)
        assert when - closed < DETECTION_S
        # the logical lines stay open: the notifiers keep waiting, nothing ends quietly
        assert demux.line(Logical.MOTOR_END_OF_SCAN).wait(0) == 0
        demux.close()


def test_a_routine_started_on_a_closed_line_fails_the_same_way(no_leaks: None) -> None:
    """What a routine run again by a reset meets when the target is still gone."""
    with EventFdLine() as physical, MemoryWindow(MOTION_WINDOW_SIZE) as motion:
        physical.close()
        demux = Level3Demux(physical, motion)
        try:
            with pytest.raises(BusError, match="closed under it"):
                demux.serve()
        finally:
            demux.close()


def test_an_unreadable_motor_board_is_a_bus_error_not_a_stall(no_leaks: None) -> None:
    with EventFdLine() as physical, MemoryWindow(MOTION_WINDOW_SIZE) as motion:
        motion.write8(BoardReg.IRQ_STATUS, int(AxisBit.AZIMUTH))
        demux = Level3Demux(physical, motion)
        thread, raised = _serve_in_thread(demux)
        motion.close()  # the board is gone; the end of a move arrives
        physical.trigger()
        thread.join(WAIT)
        assert len(raised) == 1 and isinstance(raised[0][0], BusError)
        assert "closed" in str(raised[0][0])
        demux.close()


@pytest.fixture
def linked(no_leaks: None) -> Iterator[tuple[LinkedLine, socket.socket, int]]:
    """A linked line on an eventfd and one end of a socket pair: the other end plays the
    simulator. Yields the line, the simulator's end, and the eventfd (for raising interrupts)."""
    ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    fd = os.eventfd(0, os.EFD_CLOEXEC | os.EFD_NONBLOCK)
    line = LinkedLine(fd, ours, "simulator 'test'")
    try:
        yield line, theirs, fd
    finally:
        line.close()
        ours.close()
        theirs.close()


def test_a_linked_line_turns_the_simulators_hang_up_into_a_bus_error(
    linked: tuple[LinkedLine, socket.socket, int],
) -> None:
    line, simulator, fd = linked
    simulator.send(b"a reply nobody has read yet")  # traffic on the link is not an interrupt
    assert line.wait(0) == 0
    os.eventfd_write(fd, 2)
    assert line.wait(timeout=WAIT) == 2
    outcome: list[tuple[BaseException | int, float]] = []

    def wait() -> None:
        try:
            outcome.append((line.wait(), time.monotonic()))  # no timeout: only the end wakes it
        except BaseException as exc:
            outcome.append((exc, time.monotonic()))

    waiter = threading.Thread(target=wait)
    waiter.start()
    os.eventfd_write(fd, 1)  # raised before the end: still delivered
    waiter.join(WAIT)
    assert outcome and outcome[0][0] == 1
    outcome.clear()
    waiter = threading.Thread(target=wait)
    waiter.start()
    hung_up = time.monotonic()
    simulator.close()  # what the kernel does for a process that dies
    waiter.join(WAIT)
    assert not waiter.is_alive() and len(outcome) == 1
    error, when = outcome[0]
    assert isinstance(error, BusError) and error.errno == errno.ECONNRESET
    assert "simulator 'test': connection lost" in str(error)
    assert when - hung_up < DETECTION_S
    with pytest.raises(BusError):
        line.wait(0)  # and stays lost
    poller = select.poll()
    poller.register(line.fileno(), select.POLLIN)
    assert poller.poll(0), "a thread polling the line's descriptor is woken by the end too"


class _LostLink:
    """What a reconnection reads of a link that broke: why, and a way to let it go."""

    broken = "connection lost (the simulator went away)"

    def drop_connection(self) -> None:
        """Nothing to drop: the old connection is already gone."""


def test_a_simulator_dying_while_it_accepts_is_still_gone(
    no_leaks: None, tmp_path: pathlib.Path
) -> None:
    """A killed ``biris sim`` can still accept a connection on its socket and then drop it
    before its handshake (on a loaded host its end takes a moment): the reset says the
    simulator is still gone and why it was lost, as when nothing listens at all."""
    path = str(tmp_path / "dying.sock")
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    listener.bind(path)
    listener.listen(1)

    def accept_and_die() -> None:
        conn, _ = listener.accept()
        conn.close()

    dying = threading.Thread(target=accept_and_die)
    dying.start()
    bundle = types.SimpleNamespace(name="dying", socket_path=path, link_timeout=WAIT)
    try:
        with pytest.raises(BusError) as gone:
            RemoteHardware._reconnect(cast(Any, bundle), cast(Any, _LostLink()), cast(Any, None))
    finally:
        dying.join(WAIT)
        listener.close()
    assert "still gone" in str(gone.value) and "connection lost" in str(gone.value)
    assert gone.value.errno == errno.ECONNRESET
    listener_gone = str(tmp_path / "nobody.sock")
    bundle.socket_path = listener_gone
    with pytest.raises(BusError, match=r"still gone \(connection lost"):
        RemoteHardware._reconnect(cast(Any, bundle), cast(Any, _LostLink()), cast(Any, None))


# -- end to end ------------------------------------------------------------------------------------


class Callers:
    """A client blocked in wait_idle (continuous scanning is never idle) and a DATA client
    taking every buffer as it comes. Each records the exception that ended it, and when."""

    def __init__(self, server: BirisServer) -> None:
        self.normal = server.open()
        self.data = server.open(ConnectionKind.DATA)
        self.buffers = 0
        self.ended: dict[str, tuple[BaseException, float]] = {}
        self._threads = [
            threading.Thread(target=self._run, args=("wait_idle", self._wait_idle)),
            threading.Thread(target=self._run, args=("ready_for_data", self._take_data)),
        ]
        self._admin = server.admin

    def _wait_idle(self) -> None:
        self.normal.wait_idle(timeout=WAIT)
        raise AssertionError("continuous scanning was idle")

    def _take_data(self) -> None:
        while True:
            self.data.ready_for_data(timeout=WAIT)
            self.buffers += 1

    def _run(self, name: str, call: Callable[[], None]) -> None:
        try:
            call()
        except BaseException as exc:
            self.ended[name] = (exc, time.monotonic())

    def block(self) -> None:
        """Start both; return once scans are being delivered and wait_idle is parked."""
        for thread in self._threads:
            thread.start()
        until(lambda: self.buffers >= 1, WAIT, "a first scan delivered")
        until(lambda: self._admin.life.idle_waiters, WAIT, "wait_idle parked")

    def faults(self, since: float) -> dict[str, tuple[str, float]]:
        """Each caller's fault kind, and how long after ``since`` it came."""
        for thread in self._threads:
            thread.join(WAIT)
            assert not thread.is_alive()
        out: dict[str, tuple[str, float]] = {}
        for name, (exc, when) in self.ended.items():
            assert isinstance(exc, HardwareFault), f"{name} ended with {exc!r}"
            out[name] = (exc.kind, when - since)
        return out


def _check_bus_everywhere(faults: dict[str, tuple[str, float]]) -> float:
    assert {name: kind for name, (kind, _) in faults.items()} == {
        "wait_idle": "bus",
        "ready_for_data": "bus",
    }
    slowest = max(after for _, after in faults.values())
    assert slowest < DETECTION_S, faults
    return slowest


def test_a_rig_closed_under_a_continuous_scan_is_a_bus_fault(
    rig: SimulatedBiris, server: BirisServer
) -> None:
    """The review's ``clients.py hardware_gone_first``: the simulator and its windows close
    under a running server with blocked clients (motor_stall after 0.7 s before)."""
    conn = server.open()
    conn.continuous_scan(-90.0, 90.0)
    callers = Callers(server)
    callers.block()

    gone = time.monotonic()
    rig.close()
    slowest = _check_bus_everywhere(callers.faults(since=gone))
    print(f"closed rig: every caller told in {slowest * 1000:.1f} ms")
    assert server.status()["state"] == "fault:bus"
    supervisor = server.supervisor
    # each interrupt routine reports its dead line in its own thread, in no set order
    until(
        lambda: {"level2_isr", "level3_isr"} <= supervisor.failure_counts().keys(),
        what="both interrupt routines to report",
    )
    assert supervisor.failures["level2_isr"] == 1  # once: a dead line does not spin a routine
    assert supervisor.failures["level3_isr"] == 1
    assert {"level2_isr", "level3_isr"} <= supervisor.down

    with pytest.raises(HardwareFault) as reset:
        conn.reset()  # the initialiser's re-link meets a closed window: bus, not protocol
    assert reset.value.kind == "bus"
    assert server.status()["state"] == "fault:bus"
    # the routines are not run again on lines still lost (they would only fail again): they
    # wait, down, for a reset whose re-link succeeds
    assert supervisor.failures["level2_isr"] == supervisor.failures["level3_isr"] == 1
    assert {"level2_isr", "level3_isr"} <= supervisor.down


# -- a simulator process killed under a running server --------------------------------------------


@pytest.fixture(scope="module", autouse=True)
def _tracker_running() -> None:
    """Before 3.13, attaching to a segment starts this process's resource tracker, whose pipe
    would otherwise count as a descriptor leaked by the first test that attaches."""
    if sys.version_info < (3, 13):
        resource_tracker.ensure_running()


class SimProcess:
    """``python -m sim.process`` in a child; the test kills it with SIGKILL."""

    def __init__(self) -> None:
        self.name = f"biris-test-lost-{os.getpid()}-{uuid.uuid4().hex[:8]}"
        self.proc = subprocess.Popen(
            [
                *(sys.executable, "-m", "sim.process", "--shm", self.name),
                *("--time-scale", "20", "--scene", "circle:2.0", "--seed", "3"),
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
        )

    def wait_ready(self) -> None:
        assert self.proc.stdout is not None
        fd = self.proc.stdout.fileno()
        readable, _, _ = select.select([fd], [], [], WAIT)
        line = os.read(fd, 4096) if readable else b""
        if not line.startswith(b"ready"):
            self.proc.kill()
            _, err = self.proc.communicate(timeout=WAIT)
            pytest.fail(f"the simulator did not start: {line!r} {err.decode()}")

    def close(self) -> None:
        """Reap it, and remove what a killed simulator could not."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGKILL)
        self.proc.communicate(timeout=WAIT)
        for leftover in (default_socket_path(self.name), f"/dev/shm/{self.name}"):
            with contextlib.suppress(FileNotFoundError):
                os.unlink(leftover)


@pytest.fixture
def sim_process(no_leaks: None) -> Iterator[SimProcess]:
    sim = SimProcess()
    try:
        yield sim
    finally:
        sim.close()


def test_a_killed_simulator_process_is_a_bus_fault(sim_process: SimProcess) -> None:
    """The review's ``proc_kill_A.sh``: kill -9 of ``biris sim`` during continuous scanning
    (motor_stall after 0.7 s, or timeout, before; and reset said protocol)."""
    sim_process.wait_ready()
    hw = attach(sim_process.name, timeout=WAIT)
    try:
        with BirisServer(hw, BirisInitRecord()) as server:
            conn = server.open()
            conn.continuous_scan(-90.0, 90.0)
            callers = Callers(server)
            callers.block()

            killed = time.monotonic()
            sim_process.proc.send_signal(signal.SIGKILL)
            slowest = _check_bus_everywhere(callers.faults(since=killed))
            print(f"killed simulator: every caller told in {slowest * 1000:.1f} ms")
            assert server.status()["state"] == "fault:bus"
            with pytest.raises(HardwareFault) as reset:
                conn.reset()
            assert reset.value.kind == "bus"
            assert "connection lost" in reset.value.message or "closed" in reset.value.message
    finally:
        hw.close()

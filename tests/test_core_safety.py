"""The safety rules of the administrator, on the thread-free core (no simulator, no real time).

A move is done only where the head stands at its destination; a reset aborts what runs and
leaves the server's parameters equal to the chips'; the BIRIS timeout is on unless the record
turns it off; a task's failure or a bug in a case is a fault every caller hears of; a refused
request leaves nothing behind. The simulator-backed tests check the same end to end.
"""

from __future__ import annotations

import dataclasses

import pytest

from biris_hw import protocol as p
from biris_hw.data import ConnectionKind
from biris_hw.errors import HardwareFault, RequestError
from biris_hw.ipc import Ticket
from biris_hw.records import BirisInitRecord, MotorParams
from biris_hw.server import messages as m
from biris_hw.server.motion import ARRIVAL_TOLERANCE_COUNTS
from biris_hw.server.scan_timing import ScanTiming
from biris_hw.status import ServerState
from regs.biexec import BiCommand
from regs.tech80 import Axis
from tests.core import Core


def _scan(core: Core, conn: int, dest: int) -> tuple[m.TransferOrder, m.MoveOrder]:
    assert core.call(p.SingleScanRqst(conn, dest)) == dest
    acquire, move = core.command(), core.move()
    assert acquire is not None and acquire.code == BiCommand.BI_ACQUIRE
    assert isinstance(move, m.MoveOrder)
    return acquire, move


def test_a_move_that_ends_away_from_its_destination_is_a_motor_stall_not_a_scan(
    core: Core,
) -> None:
    conn = core.open()
    acquire, move = _scan(core, conn, 1024)
    waiter = core.send(p.WaitIdle(conn))
    core.acquisitions(acquire.seq_id, range(acquire.n_acquisitions), azimuth=lambda k: 0)
    core.complete(acquire)
    core.arrive(position=0, token=move.token)  # the profile ended; the shaft never moved
    status = core.admin.status()
    assert status["state"] == "fault:motor_stall"
    assert status.counters["scans"] == 0
    with pytest.raises(HardwareFault) as info:
        waiter.wait(0)
    assert info.value.kind == "motor_stall" and "did not follow" in str(info.value)


def test_a_move_within_the_tolerance_completes(core: Core) -> None:
    conn = core.open()
    acquire, move = _scan(core, conn, 1024)
    core.acquisitions(acquire.seq_id, range(acquire.n_acquisitions))
    core.complete(acquire)
    core.arrive(position=1024 - ARRIVAL_TOLERANCE_COUNTS, token=move.token)
    assert core.admin.state() is ServerState.IDLE
    assert core.admin.counters.scans == 1


def test_a_head_that_never_came_to_rest_is_a_fault_even_near_its_destination(core: Core) -> None:
    """A head ringing under a filter it cannot hold passes its destination; one reading there
    is not an arrival (the random requests' seed 273 saw status "idle" 18 counts away)."""
    conn = core.open()
    acquire, move = _scan(core, conn, 1024)
    core.acquisitions(acquire.seq_id, range(acquire.n_acquisitions))
    core.complete(acquire)
    core.arrive(position=1024, settled=False, token=move.token)
    assert core.admin.state() is ServerState.FAULT
    assert core.admin.counters.scans == 0
    assert core.admin.life.fault is not None and "had not come to rest" in str(
        core.admin.life.fault
    )


def test_the_end_of_an_abandoned_move_is_not_taken_for_the_next_one(core: Core) -> None:
    conn = core.open()
    _, move = _scan(core, conn, 1024)
    core.arrive(position=1024, token=move.token - 1)  # a move a reset abandoned, reporting late
    assert core.admin.counters.spurious_motor_end == 1
    assert core.admin.state() is ServerState.SCANNING
    assert core.admin.az.current is not None


def test_reset_aborts_the_command_in_flight_and_arms_no_timeout_for_it(core: Core) -> None:
    conn = core.open()
    acquire, _ = _scan(core, conn, 4096)
    assert core.biris_timeout.deadline is not None  # on by default
    core.send(p.ResetRequest(conn))
    assert core.biris_timeout.deadline is None
    assert core.admin.commands.current is None
    core.complete(acquire)  # BIRIS finishes the old BI_ACQUIRE while the initialiser waits
    assert core.admin.counters.stale_completions == 1
    core.init_done()
    core.advance(60.0)
    assert core.admin.life.fault is None
    assert core.admin.state() is ServerState.IDLE


def test_reset_gives_the_server_the_parameters_the_chips_were_given(core: Core) -> None:
    conn = core.open()
    slow = dataclasses.replace(core.record.motor, max_vel=1)
    core.call(p.BirisMotorParams(conn, slow))
    order = core.move()
    assert isinstance(order, m.ParamsOrder)
    assert core.admin.az.motor == slow
    core.initialise()  # reset: the initialiser loads the record's parameters into the chip
    assert core.admin.az.motor == core.record.motor
    acquire, _ = _scan(core, conn, 2048)
    assert acquire.n_acquisitions == ScanTiming(Core.PERIOD).acquisitions(2048, core.record.motor)


def test_the_biris_timeout_is_on_unless_the_record_turns_it_off() -> None:
    for enabled in (True, False):
        core = Core(BirisInitRecord(timeout_enabled=enabled))
        core.initialise()
        conn = core.open()
        _scan(core, conn, 1024)
        core.advance(core.record.timeout_s + 0.5)
        fault = core.admin.life.fault
        assert (fault is not None and fault.kind == "timeout") is enabled


@pytest.mark.parametrize("kind", ["bus", "internal"])
def test_a_failed_task_is_a_fault_of_its_kind_for_every_caller(core: Core, kind: str) -> None:
    conn = core.open()
    data = core.open(ConnectionKind.DATA)
    _scan(core, conn, 1024)
    waiting = [core.send(p.WaitIdle(conn)), core.send(p.ReadyForData(data))]
    core.send(m.TaskFailed("biris_az_notifier", kind, "it broke"))
    assert core.admin.status()["state"] == f"fault:{kind}"
    for ticket in waiting:
        with pytest.raises(HardwareFault) as info:
            ticket.wait(0)
        assert info.value.kind == kind


def test_a_bug_in_a_case_is_an_internal_fault_and_reset_recovers(
    core: Core, monkeypatch: pytest.MonkeyPatch
) -> None:
    conn = core.open()
    acquire, _ = _scan(core, conn, 1024)
    waiter = core.send(p.WaitIdle(conn))  # parked: a scan is under way

    def broken(*args: object, **kwargs: object) -> None:
        raise ValueError("a bug")

    monkeypatch.setattr(core.admin.scans, "keep", broken)
    core.acquisitions(acquire.seq_id, range(1))  # NEW_POINT's case meets the bug
    assert core.admin.status()["state"] == "fault:internal"
    with pytest.raises(HardwareFault) as info:
        waiter.wait(0)
    assert info.value.kind == "internal"
    monkeypatch.undo()
    core.initialise()
    assert core.admin.state() is ServerState.IDLE
    _scan(core, conn, -1024)


def test_a_refused_continuous_scan_leaves_nothing_behind(
    core: Core, monkeypatch: pytest.MonkeyPatch
) -> None:
    conn = core.open()

    def refuse(dest: int, after: object = None) -> None:
        raise RequestError("refused")

    monkeypatch.setattr(core.admin, "_start_scan", refuse)
    with pytest.raises(RequestError):
        core.call(p.ContScanRqst(conn, -1024, 1024))
    monkeypatch.undo()
    assert core.admin.state() is ServerState.IDLE
    assert core.admin.scans.continuous is None
    assert core.call(p.WaitIdle(conn)) is None
    _scan(core, conn, 512)


def test_wait_idle_with_poll_answers_at_once(core: Core) -> None:
    conn = core.open()
    assert core.call(p.WaitIdle(conn, poll=True)) is None
    _scan(core, conn, 512)
    with pytest.raises(TimeoutError):
        core.call(p.WaitIdle(conn, poll=True))
    assert core.admin.life.idle_waiters == []


def test_a_parameter_that_cannot_move_the_head_is_refused_up_front() -> None:
    for bad in ({"max_vel": 0}, {"max_accel": 0}, {"gain": 0}):
        with pytest.raises(RequestError):
            MotorParams(**bad)


def _faulted_and_resetting(core: Core) -> tuple[int, Ticket]:
    """A task fails under a scan (supervisor generation 0) and a reset begins; returns the
    connection and the reset's ticket."""
    conn = core.open()
    _scan(core, conn, 1024)
    core.send(m.TaskFailed("az_scan_start", "bus", "SDO read failed", generation=0))
    assert core.admin.status()["state"] == "fault:bus"
    return conn, core.send(p.ResetRequest(conn))


@pytest.mark.parametrize("restarted", [False, True], ids=["restart_pending", "restarted"])
def test_a_task_failure_read_during_the_reset_that_restarts_the_task_is_not_a_fault(
    core: Core, restarted: bool
) -> None:
    """A worker blocked on a drive whose cable was pulled fails only once its SDO read times out
    -- after the reset has begun. The reset's initialiser restarts it (before or after the
    report is read): the report is logged and counted, and the initialisation goes on (it once
    waited 6.6 s on a command the stale fault had stopped, then failed as a ``timeout``)."""
    _, reset = _faulted_and_resetting(core)
    core.send(m.TaskFailed("az_scan_start", "bus", "SDO read failed again", generation=0))
    if restarted:
        core.task_resets = 1  # the initialiser's relink restarted the tasks down
    assert core.admin.life.fault is None and core.admin.counters.overtaken_task_failures == 1
    stop = core.send(m.InitCommand(int(BiCommand.BI_STOP_CONTINUOUS), ""))
    order = core.command()
    assert order is not None and order.code == BiCommand.BI_STOP_CONTINUOUS
    core.complete(order, param=b"0")
    assert stop.done and stop.wait(0) == (0, b"0")
    core.init_done()
    assert reset.done and core.admin.state() is ServerState.IDLE


def test_a_task_failing_after_the_reset_restarted_it_fails_the_initialisation_at_once(
    core: Core,
) -> None:
    """The restarted task fails again (generation 1): a fault of the initialisation. What the
    initialiser waits on fails with it, and so does what it asks for next, at once."""
    _, reset = _faulted_and_resetting(core)
    core.task_resets = 1
    stop = core.send(m.InitCommand(int(BiCommand.BI_STOP_CONTINUOUS), ""))
    assert core.command() is not None  # issued; BIRIS is executing it
    core.send(m.TaskFailed("level2_isr", "bus", "the line is gone", generation=1))
    assert core.admin.counters.overtaken_task_failures == 0
    later = [
        core.send(m.InitCommand(int(BiCommand.BI_BOOT), "x")),
        core.send(m.InitMove(0, Axis.AZIMUTH, start=0)),
    ]
    for ticket in (stop, *later):
        assert ticket.done, ticket
        with pytest.raises(HardwareFault) as info:
            ticket.wait(0)
        assert info.value.kind == "bus" and "level2_isr" in str(info.value)
    assert core.move() is None  # nothing was handed to a worker
    assert not reset.done  # answered by INIT_DONE, with the initialiser's error

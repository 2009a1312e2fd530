"""The report's rules, checked on the administrator alone: no thread, no simulator, no real time.

Each test plays the server's tasks by hand through :class:`tests.core.Core` (a message in, the
replies and orders out) on a virtual clock, so a rule that breaks fails here exactly and at once.
The simulator-backed tests (test_server_*.py) check the same behaviour end to end.
"""

from __future__ import annotations

import pytest

from biris_hw import protocol as p
from biris_hw.data import ConnectionKind, DeliveryPolicy, Direction, Scan
from biris_hw.errors import HardwareFault, RequestError
from biris_hw.records import BirisInitRecord, MotorParams
from biris_hw.server import messages as m
from biris_hw.server.continuous_mode import TRANSITIONS, Ring, RingState
from biris_hw.server.motion import RECHECK_GRACE_S
from biris_hw.server.scan_timing import ScanTiming
from biris_hw.status import ServerState
from regs.biexec import BiCommand, BiStatus
from regs.tech80 import Axis
from tests.core import Core


def _scan(core: Core, conn: int, dest: int) -> tuple[m.TransferOrder, m.MoveOrder]:
    """Start a report-mode single scan; returns BI_ACQUIRE and the move as the workers got them."""
    assert core.call(p.SingleScanRqst(conn, dest)) == dest
    acquire = core.command()
    move = core.move()
    assert acquire is not None and acquire.code == BiCommand.BI_ACQUIRE
    assert isinstance(move, m.MoveOrder) and move.destination == dest
    return acquire, move


def test_a_scan_completes_only_when_both_the_motor_and_biris_are_done(core: Core) -> None:
    conn = core.open()
    data = core.open(ConnectionKind.DATA)
    for motor_first in (True, False):
        dest = 512 if motor_first else 0
        acquire, _ = _scan(core, conn, dest)
        ready = core.send(p.ReadyForData(data))
        core.acquisitions(acquire.seq_id, range(acquire.n_acquisitions))
        if motor_first:
            core.arrive()
            assert not ready.done and core.admin.state() is ServerState.SCANNING
            core.complete(acquire)
        else:
            core.complete(acquire)
            assert not ready.done and core.admin.state() is ServerState.SCANNING
            core.arrive()
        assert ready.done
        scan, dropped = ready.wait(0)
        assert isinstance(scan, Scan) and dropped == 0
        assert len(scan.azimuth) == acquire.n_acquisitions
        assert core.admin.state() is ServerState.IDLE


def test_one_biris_command_at_a_time(core: Core) -> None:
    """A second command waits until BIRIS_CMD of the first was serviced (Biris_ready)."""
    first = core.send(m.InitCommand(int(BiCommand.BI_GET_VME_INC_FRAME), ""))
    second = core.send(m.InitCommand(int(BiCommand.BI_GET_VME_ADDR_DIST), ""))
    order = core.command()
    assert order is not None and order.code == BiCommand.BI_GET_VME_INC_FRAME
    assert core.command() is None  # the second waits for BIRIS
    core.complete(order, param=b"130\0")
    assert first.wait(0) == (0, b"130\0") and not second.done
    # BIRIS is ready again: the second is issued at once, and the notifier was put back on
    # its interrupt just before it
    assert core.notifier is not None and core.notifier.done
    order2 = core.command()
    assert order2 is not None and order2.code == BiCommand.BI_GET_VME_ADDR_DIST
    core.complete(order2, param=b"0x1000\0")
    assert second.wait(0) == (0, b"0x1000\0")
    assert not core.notifier.done  # no next command: it stays parked


def test_a_late_completion_of_an_abandoned_command_is_ignored(core: Core) -> None:
    order = core.send(m.InitCommand(int(BiCommand.BI_GET_VME_INC_FRAME), ""))
    transfer = core.command()
    assert transfer is not None and order is not None
    core.send(m.BirisCmdComplete(0, b"", transfer.token + 7))
    assert core.admin.counters.stale_completions == 1 and not order.done


def test_home_waits_for_the_scan_then_drives_home(core: Core) -> None:
    conn = core.open()
    acquire, _ = _scan(core, conn, 400)
    assert core.call(p.BirisHome(conn)) is None
    assert core.move() is None  # pending: no motion while the scan runs
    core.acquisitions(acquire.seq_id, range(acquire.n_acquisitions))
    core.complete(acquire)
    core.arrive()
    home = core.move()
    assert isinstance(home, m.MoveOrder) and home.destination == 0
    assert core.admin.state() is ServerState.HOMING
    core.arrive()
    assert core.admin.state() is ServerState.IDLE and core.admin.position == 0


def test_buffers_are_double_buffered_per_direction(core: Core) -> None:
    conn = core.open()
    acquire, _ = _scan(core, conn, 300)
    core.acquisitions(acquire.seq_id, range(acquire.n_acquisitions))
    core.complete(acquire)
    core.arrive()
    first = core.call(p.RequestScanData(conn, Direction.CCW))
    assert isinstance(first, Scan) and first.seq == 1
    assert core.call(p.RequestScanData(conn, Direction.CW)) is None
    acquire, _ = _scan(core, conn, 0)  # back, clockwise
    core.acquisitions(acquire.seq_id, range(2))  # half-way: CW is still empty, CCW unchanged
    assert core.call(p.RequestScanData(conn, Direction.CW)) is None
    again = core.call(p.RequestScanData(conn, Direction.CCW))
    assert isinstance(again, Scan) and again.seq == 1
    core.acquisitions(acquire.seq_id, range(2, acquire.n_acquisitions))
    core.complete(acquire)
    core.arrive()
    cw = core.call(p.RequestScanData(conn, Direction.CW))
    assert isinstance(cw, Scan) and cw.seq == 1 and cw.direction is Direction.CW


def test_continuous_scanning_alternates_and_stop_ends_at_the_sweep_end(core: Core) -> None:
    conn = core.open()
    assert core.call(p.ContScanRqst(conn, -200, 200)) == (-200, 200)
    destinations = []
    for _ in range(3):
        acquire = core.command()
        move = core.move()
        assert acquire is not None and isinstance(move, m.MoveOrder)
        destinations.append(move.destination)
        core.complete(acquire)
        core.arrive()
    assert destinations == [-200, 200, -200]
    acquire = core.command()
    assert acquire is not None and core.move() is not None
    assert core.call(p.StopScanRqst(conn)) is None
    assert core.admin.state() is ServerState.SCANNING  # the sweep under way completes
    core.complete(acquire)
    core.arrive()
    assert core.command() is None and core.move() is None
    assert core.admin.state() is ServerState.IDLE
    assert core.admin.counters.scans == 4


def test_a_fault_reaches_every_caller_and_every_later_request(core: Core) -> None:
    conn = core.open()
    data = core.open(ConnectionKind.DATA)
    _scan(core, conn, 800)
    idle = core.send(p.WaitIdle(conn))
    ready = core.send(p.ReadyForData(data))
    assert not idle.done and not ready.done
    core.send(m.BirisBusErr())
    for ticket in (idle, ready):
        with pytest.raises(HardwareFault) as info:
            ticket.wait(0)
        assert info.value.kind == "bus"
    with pytest.raises(HardwareFault):
        core.call(p.RequestPoint(conn))
    status = core.admin.status()
    assert status.state is ServerState.FAULT and status.fault == "bus"
    assert status["state"] == "fault:bus"
    core.initialise()  # reset is the way back
    assert core.admin.status().state is ServerState.IDLE and core.initialiser_starts == 2


def test_the_biris_timeout_fires_on_silence_not_while_acquisitions_arrive(core: Core) -> None:
    conn = core.open()
    core.call(p.TimeoutEnable(conn))
    acquire, _ = _scan(core, conn, 1000)
    core.arrive()  # the motor is done; BIRIS still owes BI_ACQUIRE's completion
    for k in range(6):  # 6 s of acquisitions, one per second: BIRIS is alive
        core.advance(1.0)
        core.acquisitions(acquire.seq_id, range(k, k + 1))
    assert core.admin.life.fault is None
    core.advance(3.9)
    assert core.admin.life.fault is None
    core.advance(0.2)
    fault = core.admin.life.fault
    assert fault is not None and fault.kind == "timeout"


def test_a_stale_timer_expiry_is_not_a_fault(core: Core) -> None:
    conn = core.open()
    core.call(p.TimeoutEnable(conn))
    acquire, _ = _scan(core, conn, 100)
    stale = core.biris_timeout.generation
    core.acquisitions(acquire.seq_id, range(1))  # re-armed: a new generation
    core.send(m.BirisTimeoutErr(stale))
    assert core.admin.life.fault is None


NOTHING_NOTICED: dict[Axis, int | None] = {Axis.AZIMUTH: None, Axis.ELEVATION: None}
"""No notifier woke for an end (MotionRechecked.noticed)."""


def test_a_move_that_never_ends_is_a_motor_stall_once_the_controller_says_so(
    core: Core,
) -> None:
    conn = core.open()
    core.call(p.TimeoutDisable(conn))  # BIRIS's own 4 s would come first: the motor is judged
    _acquire, move = _scan(core, conn, 1024)
    started = core.clock.now
    assert core.az_watchdog.deadline is not None
    core.advance(core.az_watchdog.deadline - core.clock.now + 0.01)
    # first the level-3 routine is asked to read the board (an end whose interrupt was lost)
    assert core.admin.life.fault is None and core.rechecks == 1
    assert core.az_watchdog.arms[-1] == RECHECK_GRACE_S
    # no answer yet (a host too busy to run the routine): the watchdog asks again, no verdict
    assert core.az_watchdog.deadline is not None
    core.advance(core.az_watchdog.deadline - core.clock.now + 0.01)
    assert core.admin.life.fault is None and core.rechecks == 2
    # the controller's answer: the move it started long ago has not ended
    core.send(m.MotionRechecked(0, {Axis.AZIMUTH: (move.token, started)}, NOTHING_NOTICED))
    fault = core.admin.life.fault
    assert fault is not None and fault.kind == "motor_stall" and "asked" in fault.message


def test_a_move_its_worker_started_late_is_given_its_time_from_its_start(core: Core) -> None:
    """A watchdog armed when the move was ordered runs out early if the host ran the worker
    late: the controller, asked, has not ended a move that started only just now. That is
    no stall: the watchdog is armed again for what the move has from its start."""
    conn = core.open()
    core.call(p.TimeoutDisable(conn))
    _acquire, move = _scan(core, conn, 1024)
    assert core.az_watchdog.deadline is not None
    core.advance(core.az_watchdog.deadline - core.clock.now + 0.01)
    assert core.rechecks == 1
    # not started at all yet (still the previous move's record): all of its time
    core.send(m.MotionRechecked(0, {Axis.AZIMUTH: None}, NOTHING_NOTICED))
    assert core.admin.life.fault is None
    allowed = core.az_watchdog.arms[-1]
    assert allowed > RECHECK_GRACE_S
    # started half its allowance ago: the rest of it
    core.advance(allowed + 0.01)
    assert core.rechecks == 2
    half = allowed / 2
    started = (move.token, core.clock.now - half)
    core.send(m.MotionRechecked(0, {Axis.AZIMUTH: started}, NOTHING_NOTICED))
    assert core.admin.life.fault is None
    assert core.az_watchdog.arms[-1] == pytest.approx(allowed - half)
    # and once it has had all of it, not ended is a stall
    core.advance(allowed)
    core.send(m.MotionRechecked(0, {Axis.AZIMUTH: started}, NOTHING_NOTICED))
    fault = core.admin.life.fault
    assert fault is not None and fault.kind == "motor_stall"


def test_a_move_the_controller_had_ended_is_left_to_its_notifier(core: Core) -> None:
    conn = core.open()
    core.call(p.TimeoutDisable(conn))
    _scan(core, conn, 1024)
    assert core.az_watchdog.deadline is not None
    core.advance(core.az_watchdog.deadline - core.clock.now + 0.01)
    core.send(m.MotionRechecked(1, {Axis.AZIMUTH: None}, NOTHING_NOTICED))
    assert core.admin.life.fault is None
    assert core.az_watchdog.deadline is None  # the notifier verifies the arrival, however late
    core.advance(60.0)
    assert core.admin.life.fault is None


def test_an_end_the_notifier_took_already_is_no_stall(core: Core) -> None:
    """The level-3 routine acknowledged the end and woke the notifier, which is still settling
    (a host that polls late watches longer): asked, the controller shows nothing latched, but
    the notifier's record names this move, so the watchdog leaves it to the notifier."""
    conn = core.open()
    core.call(p.TimeoutDisable(conn))
    _acquire, move = _scan(core, conn, 1024)
    assert core.az_watchdog.deadline is not None
    core.advance(core.az_watchdog.deadline - core.clock.now + 0.01)
    long_ago = (move.token, core.clock.now - 100.0)
    core.send(m.MotionRechecked(0, {Axis.AZIMUTH: long_ago}, {Axis.AZIMUTH: move.token}))
    assert core.admin.life.fault is None and core.az_watchdog.deadline is None


def _owing_biris() -> tuple[Core, m.TransferOrder]:
    """A core whose BIRIS timeout asks the level-2 routine first, mid-scan with the motor done:
    BIRIS owes BI_ACQUIRE's completion (returned)."""
    core = Core(recheck_biris=True)
    core.initialise()
    conn = core.open()
    core.call(p.TimeoutEnable(conn))
    acquire, _ = _scan(core, conn, 1000)
    core.arrive()
    return core, acquire


def test_a_biris_timeout_is_a_fault_only_if_biris_made_nothing_when_read_afresh() -> None:
    """The countdown runs from the last life the host saw; before calling BIRIS hung the
    level-2 routine reads it afresh: new acquisitions (posted ahead of the answer) or a
    completion re-arm it; nothing new is a timeout."""
    core, acquire = _owing_biris()
    core.advance(4.2)  # the host saw nothing for 4 s
    assert core.admin.life.fault is None and core.biris_rechecks == 1
    # the routine found acquisitions made meanwhile: they come first, then its answer
    core.acquisitions(acquire.seq_id, range(0, 3))
    core.send(m.BirisRechecked(True))
    assert core.admin.life.fault is None
    assert core.biris_timeout.deadline is not None  # counting again, from the new life
    core.advance(4.2)
    assert core.biris_rechecks == 2
    core.advance(4.2)  # no answer yet: asked again, still no verdict
    assert core.biris_rechecks == 3 and core.admin.life.fault is None
    core.send(m.BirisRechecked(False))  # nothing new at all: BIRIS is hung
    fault = core.admin.life.fault
    assert fault is not None and fault.kind == "timeout"


@pytest.mark.parametrize(("lag", "said"), [(0.14, True), (0.0, False)])
def test_a_fault_met_while_the_simulator_lagged_says_so(lag: float, said: bool) -> None:
    """A timeout or motor_stall judged while the hardware (a simulator the host cannot keep up
    with) ran behind its clock names the lag; on time, it does not."""
    core = Core(lag=lambda: lag)
    core.initialise()
    conn = core.open()
    core.call(p.TimeoutEnable(conn))
    _scan(core, conn, 1000)
    core.arrive()
    core.advance(4.2)  # no routine to ask (recheck_biris off): a timeout at once
    fault = core.admin.life.fault
    assert fault is not None and fault.kind == "timeout"
    assert ("140 ms behind its clock" in fault.message) is said, fault.message


def test_life_seen_while_a_biris_recheck_is_out_proves_biris_alive() -> None:
    core, acquire = _owing_biris()
    core.advance(4.2)
    assert core.biris_rechecks == 1
    core.acquisitions(acquire.seq_id, range(0, 1))  # a data interrupt came meanwhile
    core.send(m.BirisRechecked(False))  # the look itself found nothing more
    assert core.admin.life.fault is None


def test_a_move_whose_end_is_found_on_asking_completes(core: Core) -> None:
    conn = core.open()
    acquire, _ = _scan(core, conn, 1024)
    assert core.az_watchdog.deadline is not None
    core.advance(core.az_watchdog.deadline - core.clock.now + 0.01)
    assert core.rechecks == 1
    core.acquisitions(acquire.seq_id, range(acquire.n_acquisitions))
    core.complete(acquire)
    core.arrive()  # the notifier, woken by the routine's look, verified the arrival
    assert core.az_watchdog.deadline is None  # disarmed by the end
    core.advance(RECHECK_GRACE_S * 2)
    assert core.admin.life.fault is None
    assert core.admin.state() is ServerState.IDLE
    # the next move gets the whole bound and its own one question
    _scan(core, conn, 0)
    assert core.admin.az.rechecked is False and core.az_watchdog.arms[-1] > RECHECK_GRACE_S


def test_a_refused_request_changes_nothing(core: Core) -> None:
    conn = core.open()
    before = core.admin.status()
    with pytest.raises(RequestError):
        core.call(p.SingleScanRqst(conn, 0))  # already there
    with pytest.raises(RequestError):
        core.call(p.ContScanRqst(conn, 100, -100))  # limits the wrong way round
    with pytest.raises(RequestError):
        core.call(object())  # not a message of the server
    after = core.admin.status()
    assert after.state is before.state is ServerState.IDLE
    assert core.command() is None and core.move() is None


def test_motor_params_wait_for_the_scan_and_are_used_for_the_next(core: Core) -> None:
    conn = core.open()
    acquire, _ = _scan(core, conn, 600)
    slow = MotorParams(max_vel=1)
    core.call(p.BirisMotorParams(conn, slow))
    core.complete(acquire)
    core.arrive()
    load = core.move()
    assert isinstance(load, m.ParamsOrder) and load.params == slow
    # the worker reported ready again after the load (Core.move): the load is done
    assert core.admin.az.motor == slow
    acquire2, _ = _scan(core, conn, 0)
    assert acquire2.n_acquisitions == _prompt().acquisitions(600, slow)
    # half the speed: about twice the acquisitions (the arrival, a spare and, for the first
    # scan, a period allowed for the motor's start are on top of the motion's)
    assert acquire2.n_acquisitions > 1.6 * acquire.n_acquisitions


def test_a_tilt_defers_a_scan_and_loads_the_calibration(core: Core) -> None:
    conn = core.open()
    assert core.call(p.SetElevation(conn, 100)) == 100
    tilt = core.move(Axis.ELEVATION)
    lut = core.command()
    assert isinstance(tilt, m.MoveOrder) and tilt.destination == 100
    assert lut is not None and lut.code == BiCommand.BI_LOAD_LUT and lut.param == "100"
    assert core.call(p.SingleScanRqst(conn, 300)) == 300
    assert core.admin.state() is ServerState.TILTING and core.move() is None  # deferred
    core.complete(lut, int(BiStatus.OK))
    assert core.move() is None  # the tilt motor has not arrived yet
    core.arrive(Axis.ELEVATION)
    acquire = core.command()
    move = core.move()
    assert acquire is not None and acquire.code == BiCommand.BI_ACQUIRE
    assert isinstance(move, m.MoveOrder) and move.destination == 300
    assert core.admin.status().calibration == 100


def test_continuous_acquisition_starts_the_ring_before_the_first_sweep() -> None:
    core = Core(BirisInitRecord(continuous_acquisition=True))
    core.initialise()
    start = core.command()
    assert start is not None and start.code == BiCommand.BI_START_CONTINUOUS
    conn = core.open()
    core.call(p.SingleScanRqst(conn, 200))
    core.complete(start, param=b"32\0")
    assert core.move() is None  # the ring is not live yet: the sweep waits
    core.send(m.ContinuousLive())
    move = core.move()
    assert isinstance(move, m.MoveOrder) and move.sweep > 0
    assert core.admin.status().ring == "live"


def test_the_ring_only_takes_the_transitions_of_its_table() -> None:
    ring = Ring(mode=True)
    assert ring.start() and ring.state is RingState.STARTING
    assert not ring.start()  # already starting
    assert ring.went_live() and ring.live
    with pytest.raises(AssertionError):
        ring.stopped()  # off without stopping first
    assert ring.stop() and not ring.stop()
    ring.stopped()
    assert ring.off
    assert all(
        RingState.OFF not in targets
        for s, targets in TRANSITIONS.items()
        if s is not RingState.STOPPING
    )


def test_every_acquisition_reaches_a_streaming_client_in_order(core: Core) -> None:
    conn = core.open()
    data = core.open(ConnectionKind.DATA, DeliveryPolicy.EVERY_ACQUISITION)
    acquire, _ = _scan(core, conn, 200)
    core.acquisitions(acquire.seq_id, range(3))
    got = []
    for _ in range(3):
        point, _dropped = core.call(p.ReadyForData(data))  # type: ignore[misc]
        got.append(point.acq)
    assert got == [0, 1, 2]


def _prompt() -> ScanTiming:
    """The timing of a server that has seen its motor start on time (as Core starts it)."""
    timing = ScanTiming(Core.PERIOD)
    timing.note_lateness(0.0)
    return timing

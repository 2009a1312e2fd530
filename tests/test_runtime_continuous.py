"""Appendix D at run time: START_CONTINUOUS and STOP_CONTINUOUS as client messages.

``conn.start_continuous()`` switches BIRIS to its continuous ring (at once when no scan runs,
pending like BIRIS_HOME while one does), ``conn.stop_continuous()`` "ceases all acquisitions
immediately" (even under a sweep, which keeps what was acquired before the stop), both are
idempotent and refused like every request in a fault or while initialising, and a reset returns
to the init record's mode. ``status()`` says the mode in force and a switch that waits; every
``Scan`` and ``Point`` says the mode it was taken in.

End to end against the simulator (whose audit is checked for every rig at teardown), plus the
administrator's decisions on the thread-free :class:`tests.core.Core` harness, and the new data
fields through validation and scan files.
"""

from __future__ import annotations

import pickle
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from biris_hw import (
    BirisInitRecord,
    ConnectionKind,
    DeliveryPolicy,
    Direction,
    HardwareFault,
    MotorParams,
    Point,
    RequestError,
    Scan,
)
from biris_hw import protocol as p
from biris_hw.io.scanfile import load_scans, save_scans
from biris_hw.server import BirisServer
from biris_hw.server import messages as m
from biris_hw.status import ServerState
from regs.biexec import OFF_CURRENT_FRAME, BiCommand
from sim import SimulatedBiris
from tests.conftest import RigFactory, until
from tests.core import Core

WAIT = 10.0
CONTINUOUS = BirisInitRecord(continuous_acquisition=True)
SLOW_CONTINUOUS = BirisInitRecord(continuous_acquisition=True, motor=MotorParams(max_vel=1))
"""Half the default pan speed (~62 deg/s): a long sweep lasts long enough, even at x30 on a busy
machine, to stop the ring well before the head arrives."""


@pytest.fixture
def cserver(rig: SimulatedBiris) -> Iterator[BirisServer]:
    """A server built in continuous acquisition, its ring live."""
    with BirisServer(rig.hardware, CONTINUOUS) as server:
        server.open().wait_idle(timeout=WAIT)
        yield server


def _mode(server: BirisServer) -> tuple[str, str | None, str]:
    status = server.status()
    return status["acquisition"], status["acquisition_pending"], status["ring"]


def _acquiring(rig: SimulatedBiris) -> bool:
    """BIRIS acquires continuously (the simulator's view: BI_START_CONTINUOUS accepted and not
    stopped)."""
    return rig.supervisor.continuous


def _drained(rig: SimulatedBiris, server: BirisServer) -> None:
    """With the ring stopped and nothing under way, every acquisition BIRIS made is accounted
    for exactly, and each has gone somewhere."""
    accounts = server.status().accounts()
    assert accounts.adds_up, accounts
    assert accounts.accounted == rig.supervisor.acquisitions_made, accounts


# -- end to end ---------------------------------------------------------------------------------


def test_start_continuous_while_idle_starts_the_ring_and_scans_are_sweeps_over_it(
    rig: SimulatedBiris, server: BirisServer
) -> None:
    conn = server.open()
    assert _mode(server) == ("single", None, "off")
    started = rig.supervisor.sequences_started
    conn.start_continuous()
    assert server.status()["acquisition"] == "continuous"  # in force as soon as accepted
    conn.wait_idle(timeout=WAIT)  # the start-up is paid now, not by the next scan
    assert _mode(server) == ("continuous", None, "live")
    assert _acquiring(rig)  # BI_START_CONTINUOUS
    assert rig.supervisor.sequences_started == started + 1
    start = 0
    for deg in (40.0, -25.0):
        dest = conn.single_scan(deg)
        conn.wait_idle(timeout=WAIT)
        scan = conn.request_scan_data(Direction.of_motion(start, dest))
        assert scan is not None and scan.n_acq > 0
        assert abs(int(scan.azimuth[-1]) - dest) <= 2  # a ring sweep ends at its destination
        start = dest
    assert rig.supervisor.sequences_started == started + 1  # no BI_ACQUIRE: data from the ring
    counters = server.status()["counters"]
    assert counters["continuous_starts"] == 1 and counters["scans"] == 2
    assert server.status().accounts().adds_up


@pytest.mark.slow  # fast-tier budget (issues 13-15); make test-slow
def test_start_continuous_during_continuous_scanning_waits_for_its_end(
    rig: SimulatedBiris, server: BirisServer
) -> None:
    conn = server.open()
    data = server.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_BUFFER)
    conn.continuous_scan(-20.0, 20.0)
    data.ready_for_data(timeout=WAIT)
    conn.start_continuous()
    assert _mode(server) == ("single", "continuous", "off")  # pending, like BIRIS_HOME
    conn.start_continuous()  # asking again changes nothing
    data.ready_for_data(timeout=WAIT)  # scanning goes on as it began
    assert _mode(server) == ("single", "continuous", "off")
    assert not _acquiring(rig)
    conn.stop_scan()
    conn.wait_idle(timeout=WAIT)  # the last sweep ends, then the ring starts and goes live
    assert _mode(server) == ("continuous", None, "live")
    assert _acquiring(rig)
    started = rig.supervisor.sequences_started
    start = server.status()["azimuth"]  # at one of the limits
    dest = conn.single_scan(45.0)
    conn.wait_idle(timeout=WAIT)
    scan = conn.request_scan_data(Direction.of_motion(start, dest))
    assert scan is not None and abs(int(scan.azimuth[-1]) - dest) <= 2
    assert rig.supervisor.sequences_started == started  # a sweep over the ring
    assert server.status().accounts().adds_up


@pytest.mark.slow  # fast-tier budget (issue 13 added the transports); make test-slow
def test_stop_continuous_mid_sweep_ceases_acquisitions_at_once(make_rig: RigFactory) -> None:
    rig = make_rig()
    with BirisServer(rig.hardware, SLOW_CONTINUOUS) as server:
        conn = server.open()
        conn.wait_idle(timeout=WAIT)
        dest = conn.single_scan(300.0)
        until(lambda: rig.azimuth_counts > 500, WAIT, "the head well into its sweep")
        conn.stop_continuous()
        assert server.status()["acquisition"] == "single"  # at once
        assert rig.supervisor.wait_for(lambda s: not s.continuous, WAIT)
        stopped_at = rig.azimuth_counts
        made = rig.supervisor.acquisitions_made
        started = rig.supervisor.sequences_started
        assert stopped_at < dest - 500  # BIRIS stopped long before the head arrived
        conn.wait_idle(timeout=WAIT)  # the head finishes its move; the sweep is delivered
        assert abs(rig.azimuth_counts - dest) <= 2
        # nothing acquired after the stop: no frame, no new sequence
        assert rig.supervisor.acquisitions_made == made
        assert rig.supervisor.sequences_started == started
        assert _mode(server) == ("single", None, "off")
        scan = conn.request_scan_data(Direction.CCW)
        assert scan is not None and scan.n_acq > 5
        az = scan.azimuth.astype(np.int64)
        assert np.all(np.diff(az) > 0)
        assert int(az[-1]) <= stopped_at  # every acquisition made before the stop ...
        assert int(az[-1]) < dest - 500  # ... so the sweep covers only part of its length
        assert scan.partial and scan.acquisition == "continuous"  # and says so
        assert server.status()["counters"]["scans"] == 1
        _drained(rig, server)  # the accounts add up, and nothing is missing
        # single acquisition from now on: a BI_ACQUIRE sequence per scan
        conn.single_scan(270.0)
        conn.wait_idle(timeout=WAIT)
        assert rig.supervisor.sequences_started == started + 1
        assert conn.request_scan_data(Direction.CW) is not None
        _drained(rig, server)


@pytest.mark.slow  # a variant; the Core tests keep the rule in the fast tier
def test_stop_continuous_during_continuous_scanning_goes_on_in_single_acquisition(
    rig: SimulatedBiris, cserver: BirisServer
) -> None:
    conn = cserver.open()
    data = cserver.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_BUFFER)
    conn.continuous_scan(-20.0, 20.0)
    data.ready_for_data(timeout=WAIT)
    started = rig.supervisor.sequences_started
    conn.stop_continuous()
    scans = [data.ready_for_data(timeout=WAIT) for _ in range(3)]
    conn.stop_scan()
    conn.wait_idle(timeout=WAIT)
    # the sweep the stop caught ends with its data; the next ones are BI_ACQUIRE sequences
    assert rig.supervisor.sequences_started >= started + 2
    assert [s.direction for s in scans] == [Direction.CCW, Direction.CW, Direction.CCW]
    assert all(s.n_acq > 0 for s in scans[1:])
    assert _mode(cserver) == ("single", None, "off")
    assert data.dropped == 0
    _drained(rig, cserver)


@pytest.mark.slow  # a variant; the Core tests keep the rule in the fast tier
def test_both_are_idempotent(rig: SimulatedBiris, server: BirisServer) -> None:
    conn = server.open()
    started = rig.supervisor.sequences_started
    conn.stop_continuous()  # in single acquisition: nothing to stop
    conn.stop_continuous()
    conn.wait_idle(timeout=0)  # idle at once: no command was issued
    assert _mode(server) == ("single", None, "off")
    assert rig.supervisor.sequences_started == started
    conn.start_continuous()
    conn.start_continuous()  # the ring is starting: nothing more
    conn.wait_idle(timeout=WAIT)
    conn.start_continuous()  # live: nothing more
    conn.wait_idle(timeout=0)
    assert _mode(server) == ("continuous", None, "live")
    assert rig.supervisor.sequences_started == started + 1
    assert server.status()["counters"]["continuous_starts"] == 1
    # let the ring complete a frame or two: a stop within its first frame is abandoned by BIRIS
    # and leaves CURRENT_FRAME where it was, which the reader cannot tell from a completed first
    # frame (AcquisitionReader._frames_done counts it as made): the exact accounts below would
    # then be off by that one frame
    assert rig.supervisor.wait_for(lambda s: s.acquisitions_made >= 2, WAIT)
    conn.stop_continuous()
    conn.stop_continuous()  # the stop is on its way: nothing more
    conn.wait_idle(timeout=WAIT)
    conn.stop_continuous()
    conn.wait_idle(timeout=0)
    assert _mode(server) == ("single", None, "off")
    assert not _acquiring(rig)
    assert server.status()["counters"]["faults"] == 0
    _drained(rig, server)


def test_refused_in_a_fault_changing_nothing(rig: SimulatedBiris, cserver: BirisServer) -> None:
    conn = cserver.open()
    rig.faults.parity_error()
    until(lambda: cserver.status().fault == "parity", WAIT, "the parity fault")
    made = rig.supervisor.acquisitions_made
    for call in (conn.stop_continuous, conn.start_continuous):
        with pytest.raises(HardwareFault) as refused:
            call()
        assert refused.value.kind == "parity"
    assert _mode(cserver) == ("continuous", None, "live")  # nothing changed ...
    assert _acquiring(rig)  # ... BIRIS was not stopped
    assert rig.supervisor.wait_for(lambda s: s.acquisitions_made > made, WAIT)
    conn.reset()
    conn.wait_idle(timeout=WAIT)
    assert _mode(cserver) == ("continuous", None, "live")


def test_a_reset_returns_to_the_init_records_mode(rig: SimulatedBiris, server: BirisServer) -> None:
    conn = server.open()
    conn.start_continuous()
    conn.wait_idle(timeout=WAIT)
    assert _mode(server) == ("continuous", None, "live")
    conn.reset()  # the initialiser stops BIRIS; the record says single acquisition
    conn.wait_idle(timeout=WAIT)
    assert _mode(server) == ("single", None, "off")
    assert not _acquiring(rig)
    started = rig.supervisor.sequences_started
    conn.single_scan(20.0)
    conn.wait_idle(timeout=WAIT)
    assert rig.supervisor.sequences_started == started + 1  # a BI_ACQUIRE
    _drained(rig, server)


@pytest.mark.slow  # a variant; the Core tests keep the rule in the fast tier
def test_a_reset_restarts_the_ring_of_a_continuous_server(
    rig: SimulatedBiris, cserver: BirisServer
) -> None:
    conn = cserver.open()
    conn.stop_continuous()
    conn.wait_idle(timeout=WAIT)
    assert _mode(cserver) == ("single", None, "off") and not _acquiring(rig)
    conn.reset()
    conn.wait_idle(timeout=WAIT)
    assert _mode(cserver) == ("continuous", None, "live") and _acquiring(rig)


def test_every_client_is_told_the_mode_through_its_data(
    rig: SimulatedBiris, server: BirisServer
) -> None:
    """Each Scan and Point says how BIRIS acquired it, whoever switched the mode.

    The server sets ``acquisition`` where it assembles scans and points
    (``biris_hw.server.scan_assembly``, from the sweep's ``ring``).
    """
    conn = server.open()
    points = server.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_ACQUISITION)
    conn.single_scan(20.0)
    conn.wait_idle(timeout=WAIT)
    single, first = conn.request_scan_data(Direction.CCW), conn.request_point()
    with server.open() as other:
        other.start_continuous()  # another client switches
    conn.wait_idle(timeout=WAIT)
    conn.single_scan(-20.0)
    conn.wait_idle(timeout=WAIT)
    ring, last = conn.request_scan_data(Direction.CW), conn.request_point()
    assert single is not None and ring is not None and first is not None and last is not None
    assert (single.acquisition, single.partial) == ("single", False)
    assert first.acquisition == "single"
    assert ring.acquisition == "continuous"
    assert last.acquisition == "continuous"
    streamed: list[str] = []
    while True:
        try:
            streamed.append(points.ready_for_data(timeout=0).acquisition)
        except TimeoutError:
            break
    # streamed as they were read: the single scan's, then the ring's, each marked
    n_single = streamed.count("single")
    assert n_single > 0 and streamed == ["single"] * n_single + ["continuous"] * ring.n_acq


# -- the administrator alone (no thread, no simulator) --------------------------------------------


def _live(core: Core) -> None:
    """Complete BI_START_CONTINUOUS and make the ring live."""
    start = core.command()
    assert start is not None and start.code == BiCommand.BI_START_CONTINUOUS
    core.complete(start, param=b"32\0")
    core.send(m.ContinuousLive())
    assert core.admin.status().ring == "live"


def test_core_refused_while_initialising_and_in_a_fault() -> None:
    core = Core()  # initialising until INIT_DONE
    conn = core.open()
    for message in (p.StartContinuous(conn), p.StopContinuous(conn)):
        with pytest.raises(RequestError, match="initialising"):
            core.call(message)
    core.initialise()
    assert core.command() is None and core.admin.status().acquisition == "single"
    core.send(m.BirisParityErr())
    for message in (p.StartContinuous(conn), p.StopContinuous(conn)):
        with pytest.raises(HardwareFault):
            core.call(message)
    status = core.admin.status()
    assert (status.acquisition, status.acquisition_pending, status.ring) == ("single", None, "off")
    assert core.command() is None


def test_core_a_stop_under_a_sweep_ends_its_data_and_it_completes_on_arrival() -> None:
    core = Core(CONTINUOUS)
    core.initialise()
    _live(core)
    conn = core.open()
    data = core.open(ConnectionKind.DATA, DeliveryPolicy.EVERY_BUFFER)
    assert core.call(p.SingleScanRqst(conn, 400)) == 400
    move = core.move()
    assert isinstance(move, m.MoveOrder) and move.sweep
    core.acquisitions(move.sweep, range(5), azimuth=lambda k: 20 + 40 * k)
    core.call(p.StopContinuous(conn))
    stop = core.command()
    assert stop is not None and stop.code == BiCommand.BI_STOP_CONTINUOUS  # at once
    assert core.admin.status().acquisition == "single"
    # the reader hands over what BIRIS completed before it stopped, then the completion
    core.acquisitions(move.sweep, range(5, 7), azimuth=lambda k: 20 + 40 * k)
    core.complete(stop)
    ready = core.send(p.ReadyForData(data))
    assert not ready.done and core.admin.status().ring == "off"  # the head is still moving
    core.arrive(position=400)
    answer = ready.wait(0)
    assert isinstance(answer, tuple)
    scan, dropped = answer
    assert isinstance(scan, Scan) and scan.n_acq == 7 and dropped == 0
    assert scan.partial and scan.acquisition == "continuous"
    assert core.admin.state() is ServerState.IDLE and core.command() is None
    accounts = core.admin.status().accounts()
    assert accounts.adds_up and accounts.in_scans == 7


def test_core_a_scan_waiting_for_the_ring_waits_for_its_stop_instead() -> None:
    """BIRIS refuses BI_ACQUIRE while its ring runs: a scan asked for before the ring went live
    starts in single acquisition only once BI_STOP_CONTINUOUS has completed."""
    core = Core(CONTINUOUS)
    core.initialise()
    start = core.command()
    assert start is not None and start.code == BiCommand.BI_START_CONTINUOUS
    conn = core.open()
    core.call(p.SingleScanRqst(conn, 200))  # deferred: the ring is not live
    core.call(p.StopContinuous(conn))
    assert core.command() is None  # BIRIS is still busy with BI_START_CONTINUOUS
    core.complete(start, param=b"32\0")
    stop = core.command()
    assert stop is not None and stop.code == BiCommand.BI_STOP_CONTINUOUS
    core.send(m.ContinuousLive())  # the first frame, from before the stop: ignored
    assert core.admin.status().ring == "stopping" and core.move() is None
    core.complete(stop)
    acquire = core.command()
    assert acquire is not None and acquire.code == BiCommand.BI_ACQUIRE


def test_core_stop_withdraws_a_pending_start_and_a_reset_restores_the_record() -> None:
    core = Core()
    core.initialise()
    conn = core.open()
    core.call(p.ContScanRqst(conn, -100, 100))
    core.call(p.StartContinuous(conn))
    status = core.admin.status()
    assert (status.acquisition, status.acquisition_pending) == ("single", "continuous")
    core.call(p.StopContinuous(conn))  # withdrawn
    assert core.admin.status().acquisition_pending is None
    core.call(p.StartContinuous(conn))
    core.send(p.ResetRequest(conn))  # a reset drops it, and the record says single
    core.init_done()
    status = core.admin.status()
    assert (status.acquisition, status.acquisition_pending, status.ring) == ("single", None, "off")
    assert all(order.code != BiCommand.BI_START_CONTINUOUS for order in iter(core.command, None))

    core = Core(CONTINUOUS)
    core.initialise()
    _live(core)
    conn = core.open()
    core.call(p.StopContinuous(conn))
    stop = core.command()
    assert stop is not None and stop.code == BiCommand.BI_STOP_CONTINUOUS
    core.send(p.ResetRequest(conn))
    core.init_done()
    assert core.admin.status().acquisition == "continuous"
    start = core.command()  # the ring starts again after initialisation
    assert start is not None and start.code == BiCommand.BI_START_CONTINUOUS


def test_core_a_live_ring_is_watched_and_one_standing_still_is_a_timeout(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """BIRIS owes a live ring's progress: with the head idle the BIRIS timeout still runs, each
    expiry asks the level-2 routine to look (quietly: it is routine), a ring seen moving re-arms
    it, one standing still is the ``timeout`` fault. Disabled, nothing is asked."""
    core = Core(CONTINUOUS, recheck_biris=True)
    core.initialise()
    _live(core)
    timeout_s = CONTINUOUS.timeout_s
    with caplog.at_level("INFO", logger="biris_hw.server"):
        core.advance(timeout_s)
        assert core.biris_rechecks == 1
        core.send(m.BirisRechecked(True))  # the ring has moved since the last look
        assert core.admin.state() is ServerState.IDLE
        core.advance(timeout_s - 0.01)
        assert core.biris_rechecks == 1  # re-armed from the look, not from before
        core.advance(0.02)
        assert core.biris_rechecks == 2
    assert not [r for r in caplog.records if "reading BIRIS afresh" in r.getMessage()]
    core.send(m.BirisRechecked(False))  # it stands where the last look saw it
    status = core.admin.status()
    assert (status.state, status.fault) == (ServerState.FAULT, "timeout")
    fault = core.admin.life.fault
    assert fault is not None and "ring did not advance" in fault.message
    core.advance(3 * timeout_s)
    assert core.biris_rechecks == 2  # a fault stops the watch; a reset starts the ring anew

    core = Core(CONTINUOUS, recheck_biris=True)
    core.initialise()
    _live(core)
    core.call(p.TimeoutDisable(core.open()))
    core.advance(5 * timeout_s)
    assert core.biris_rechecks == 0 and core.admin.state() is ServerState.IDLE


def test_a_ring_stopped_in_its_start_up_leaves_no_frame_of_an_earlier_ring(
    rig: SimulatedBiris, server: BirisServer
) -> None:
    """CURRENT_FRAME after a stop names the last slot that ring completed, -1 when none: what an
    earlier ring left there would otherwise read as this ring's frames (the review's random
    runs: +82 and +4 accounted that BIRIS never made)."""
    conn = server.open()
    conn.start_continuous()
    conn.wait_idle(timeout=WAIT)
    rig.timebase.sleep(0.5)  # the first ring completes a dozen frames
    conn.stop_continuous()
    conn.wait_idle(timeout=WAIT)
    link = server.link
    assert link.window.read16(link.base + OFF_CURRENT_FRAME) > 0
    made = rig.supervisor.acquisitions_made
    conn.start_continuous()
    conn.stop_continuous()  # issued as the start completes: inside BIRIS's 250 ms start-up
    conn.wait_idle(timeout=WAIT)
    assert rig.supervisor.acquisitions_made == made
    assert link.window.read16(link.base + OFF_CURRENT_FRAME) == 0xFFFF  # -1: none
    _drained(rig, server)


# -- the data fields -----------------------------------------------------------------------------


def _scan(**extra: object) -> Scan:
    return Scan(
        direction=Direction.CCW,
        seq=1,
        azimuth=np.arange(3, dtype=np.int32),
        range_mm=np.ones((3, 4), dtype=np.int16),
        closest_mm=np.ones(3, dtype=np.int16),
        intensity=np.ones((3, 4), dtype=np.int16),
        t=np.arange(3, dtype=np.float64),
        **extra,  # type: ignore[arg-type]
    )


def _point(**extra: object) -> Point:
    profile = np.ones(4, dtype=np.int16)
    return Point(1, 2, profile, profile, 0.5, 0, 1, **extra)  # type: ignore[arg-type]


def test_scan_and_point_know_their_mode_and_check_it() -> None:
    assert (_scan().acquisition, _scan().partial) == ("single", False)  # old constructors
    assert _point().acquisition == "single"
    scan = _scan(acquisition="continuous", partial=np.bool_(True))
    assert scan.acquisition == "continuous" and scan.partial is True
    assert _point(acquisition="continuous").acquisition == "continuous"
    for bad in ({"acquisition": "ring"}, {"acquisition": None}, {"partial": 1}, {"partial": "no"}):
        with pytest.raises(ValueError):
            _scan(**bad)
    with pytest.raises(ValueError):
        _point(acquisition="Continuous")
    copy = pickle.loads(pickle.dumps(scan))
    assert (copy.acquisition, copy.partial) == ("continuous", True)


def test_scan_files_keep_the_mode(tmp_path: Path) -> None:
    saved = [_scan(acquisition="continuous", partial=True), _scan()]
    loaded = load_scans(save_scans(tmp_path / "run", saved))
    assert [(s.acquisition, s.partial) for s in loaded] == [("continuous", True), ("single", False)]
    assert type(loaded[0].acquisition) is str and type(loaded[0].partial) is bool
    # a version-2 file has neither: single and whole, as every scan of its day was
    with np.load(tmp_path / "run.npz", allow_pickle=False) as data:
        arrays = {key: data[key] for key in data.files if key not in ("acquisition", "partial")}
    arrays["format_version"] = np.array(2, dtype=np.int64)
    np.savez(tmp_path / "v2.npz", **arrays)
    old = load_scans(tmp_path / "v2.npz")
    assert [(s.acquisition, s.partial) for s in old] == [("single", False)] * 2

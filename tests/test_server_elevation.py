"""The tilt axis: homing, SET_ELEVATION, calibration tables, and no acquisition while tilting.

The simulated head tilts on the Model 7600's second HCTL-1000; its optics read wrong ranges
under a calibration table made for another elevation, and the supervisor's audit records any
acquisition made while tilting or under the wrong table -- so a clean audit at the end of each
test (conftest) is itself the check that the server never did either.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from biris_hw import (
    BirisInitRecord,
    ConnectionKind,
    DeliveryPolicy,
    Direction,
    MotorParams,
    RequestError,
)
from biris_hw.errors import HardwareFault
from biris_hw.server import BirisServer
from regs.hctl1000 import Reg
from sim import Scene, SimulatedBiris
from sim.audit import Rule
from tests.conftest import RigFactory

WAIT = 30.0


@pytest.fixture
def time_scale() -> float:
    return 30.0


def _deg(counts: float) -> float:
    return counts * 360.0 / 4096.0


def test_initialisation_homes_the_tilt_to_its_index(make_rig: RigFactory) -> None:
    rig = make_rig(initial_elevation_counts=150.0)
    with BirisServer(rig.hardware) as server:
        status = server.status()
        assert status["elevation"] == 0 and status["calibration"] == 0
        assert abs(rig.elevation_counts) <= 3.0  # level, wherever it woke up
        assert rig.supervisor.loaded_lut == 0
        assert status["interrupts"]["ELEVATION_END_OF_SCAN"] > 0  # homed with its interrupt


def test_the_tilt_runs_on_its_own_motor_parameters(rig: SimulatedBiris) -> None:
    tilt = MotorParams(gain=0x30, max_vel=1, max_accel=0x1000)
    record = BirisInitRecord(elevation_motor=tilt)
    assert record.tilt_motor == tilt and BirisInitRecord().tilt_motor == BirisInitRecord().motor
    with BirisServer(rig.hardware, record) as server:
        conn = server.open()
        for chip, params in ((rig.board.azimuth, record.motor), (rig.board.elevation, tilt)):
            assert (chip.peek(Reg.FILTER_GAIN), chip.peek(Reg.MAX_VELOCITY)) == (
                params.gain,
                params.max_vel,
            )
            assert chip.peek(Reg.ACCEL_LSB) | chip.peek(Reg.ACCEL_MSB) << 8 == params.max_accel
        assert conn.set_elevation(10.0) == 114
        conn.wait_idle(timeout=WAIT)
        assert abs(rig.elevation_counts - 114) <= 3.0
        conn.single_scan(20.0)  # the pan is untouched: its own set
        conn.wait_idle(timeout=WAIT)
        assert conn.request_scan_data(Direction.CCW) is not None


@pytest.mark.parametrize(
    ("asked", "used"),
    [
        (10.0, 114),
        pytest.param(-8.0, -91, marks=pytest.mark.slow),
        pytest.param(80.0, 512, marks=pytest.mark.slow),
        (-90.0, -512),
    ],
)
def test_set_elevation_tilts_loads_the_table_and_tags_the_data(
    rig: SimulatedBiris, asked: float, used: int
) -> None:
    with BirisServer(rig.hardware) as server:
        conn = server.open()
        assert conn.set_elevation(asked) == used  # clamped to elevation_limits_counts
        conn.wait_idle(timeout=WAIT)
        assert abs(rig.elevation_counts - used) <= 3.0  # index and settling: a count each
        assert rig.supervisor.loaded_lut == used
        status = server.status()
        assert status["state"] == "idle" and status["elevation"] == used
        assert status["counters"]["lut_loads"] == 1
        conn.single_scan(30.0)
        conn.wait_idle(timeout=WAIT)
        scan = conn.request_scan_data(Direction.CCW)
        point = conn.request_point()
    assert scan is not None and point is not None
    assert scan.elevation == used and point.elevation == used


def test_bad_elevations_are_refused(server: BirisServer) -> None:
    conn = server.open()
    for bad in (math.nan, math.inf, "10"):
        with pytest.raises(RequestError):
            conn.set_elevation(bad)  # type: ignore[arg-type]
    assert server.status()["elevation"] == 0
    assert conn.set_elevation(0.0) == 0  # already there: nothing to do
    assert server.status()["counters"]["tilts"] == 0


def test_tilted_points_lie_on_the_cylinder(make_rig: RigFactory) -> None:
    """With the right table loaded, range is still depth along the (tilted) optical axis."""
    rig = make_rig(scene=Scene.circle(2.0), noise=False)
    with BirisServer(rig.hardware) as server:
        conn = server.open()
        for deg, sweep in ((12.0, 60.0), (-9.0, -60.0)):
            used = conn.set_elevation(deg)
            conn.single_scan(sweep)
            conn.wait_idle(timeout=WAIT)
            scan = conn.request_scan_data(Direction.CCW if sweep > 0 else Direction.CW)
            assert scan is not None and scan.elevation == used
            pts = scan.points("vehicle")
            assert pts.shape[0] > 0.9 * scan.range_mm.size
            assert np.abs(np.hypot(pts[:, 0], pts[:, 1]) - 2.0).max() < 0.01
            # the fan's centre now looks at the tilt: mean height 0.5 + 2 tan(tilt)
            centre = 0.5 + 2.0 * math.tan(math.radians(_deg(used)))
            assert np.median(pts[:, 2]) == pytest.approx(centre, abs=0.03)
            # depths along the tilted axis differ from the radius: the table did its job
            assert abs(int(np.median(scan.range_mm)) - 2000) > 15


@pytest.mark.slow  # fast-tier budget (issues 13-15); make test-slow
def test_a_scan_asked_for_during_a_tilt_waits_for_it(
    rig: SimulatedBiris, server: BirisServer
) -> None:
    """The table load cannot finish while BIRIS is hung, so the tilt is held open for sure."""
    conn = server.open()
    rig.faults.hang_supervisor()
    assert conn.set_elevation(10.0) == 114
    assert server.status()["state"] == "tilting"
    made = rig.supervisor.acquisitions_made
    assert conn.single_scan(45.0) == 512  # accepted, and waits
    with pytest.raises(RequestError):
        conn.single_scan(-45.0)  # one scan at a time, waiting or not
    status = server.status()
    assert status["state"] == "tilting" and status["azimuth"] == 0
    with pytest.raises(TimeoutError):
        conn.wait_idle(timeout=0.1)  # 3 hardware s at x30: within the 4 s BIRIS timeout
    assert rig.supervisor.acquisitions_made == made
    rig.faults.clear_hang()
    conn.wait_idle(timeout=WAIT)
    scan = conn.request_scan_data(Direction.CCW)
    assert scan is not None and scan.elevation == 114
    assert abs(int(scan.azimuth[-1]) - 512) <= 2
    assert rig.supervisor.loaded_lut == 114


@pytest.mark.slow  # fast-tier budget (issues 13-15); make test-slow
def test_a_tilt_asked_for_during_continuous_scanning_happens_between_sweeps(
    rig: SimulatedBiris, server: BirisServer
) -> None:
    conn = server.open()
    data = server.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_BUFFER)
    conn.continuous_scan(-15.0, 15.0)
    first = data.ready_for_data(timeout=WAIT)
    assert first.elevation == 0
    conn.set_elevation(6.0)  # the sweep under way finishes at elevation 0
    seen: list[int] = []
    while len(seen) < 3 or seen[-1] == 0:
        scan = data.ready_for_data(timeout=WAIT)
        seen.append(scan.elevation)
        assert scan.n_acq > 0
    conn.stop_scan()
    conn.wait_idle(timeout=WAIT)
    assert set(seen) <= {0, 68} and seen[-1] == 68
    assert seen == sorted(seen)  # every sweep at one elevation: 0 until the tilt, 68 after
    assert data.dropped == 0
    assert rig.supervisor.loaded_lut == 68


@pytest.mark.slow  # fast-tier budget (issues 13-15); make test-slow
def test_tilt_while_homing_runs_both_axes(rig: SimulatedBiris, server: BirisServer) -> None:
    conn = server.open()
    conn.single_scan(60.0)
    conn.wait_idle(timeout=WAIT)
    conn.home()
    conn.set_elevation(-5.0)
    conn.wait_idle(timeout=WAIT)
    assert abs(rig.azimuth_counts) <= 3.0 and abs(rig.elevation_counts + 57) <= 3.0


@pytest.mark.slow  # fast-tier budget (issues 13-15); make test-slow
def test_the_simulator_catches_a_tilt_behind_the_servers_back(
    make_rig: RigFactory,
) -> None:
    """What the server prevents: tilting the head without loading its table gives bent ranges
    and WRONG_CALIBRATION (the server's own elevation driver, bypassing the administrator)."""
    rig = make_rig(scene=Scene.circle(2.0), noise=False)
    with BirisServer(rig.hardware) as server:
        conn = server.open()
        server.elevation.start_trapezoid(228)  # 20 degrees up; BIRIS still holds table 0
        assert rig.supervisor.wait_for(lambda s: abs(rig.elevation_counts - 228) < 4, WAIT)
        conn.single_scan(20.0)
        conn.wait_idle(timeout=WAIT)
        scan = conn.request_scan_data(Direction.CCW)
    assert scan is not None and scan.elevation == 0  # the server never knew
    rules = {v.rule for v in rig.audit.violations}
    assert Rule.WRONG_CALIBRATION in rules
    valid = scan.range_mm[scan.range_mm > 0].astype(np.int64)
    # true depth along the tilted axis is 2 m / cos(20 deg + e); the stale table reads it wrong
    assert abs(np.median(valid) - 2000 / math.cos(math.radians(20.0))) > 20
    rig.audit.clear()  # recorded on purpose


def test_elevation_limits_come_from_the_init_record(rig: SimulatedBiris) -> None:
    record = BirisInitRecord(elevation_limits_counts=(-100, 50))
    with BirisServer(rig.hardware, record) as server:
        conn = server.open()
        assert conn.set_elevation(30.0) == 50
        assert conn.set_elevation(-30.0) == -100
        conn.wait_idle(timeout=WAIT)
        assert server.status()["elevation"] == -100
        assert abs(rig.elevation_counts + 100) <= 3.0


@pytest.mark.slow  # fast-tier budget (issue 13 added the transports); make test-slow
def test_a_reset_under_a_hung_acquisition_at_a_tilt_leaves_the_calibration_right(
    make_rig: RigFactory,
) -> None:
    """A reset resets the tilt's chip (its counter reads 0 where the head stands) before it
    waits for a BI_ACQUIRE that a hang left running; that acquisition goes on with the table
    of where the head truly stands, which is right. The simulator judges the table against the
    true tilt, not against the encoder the reset just zeroed (it used to record
    WRONG_CALIBRATION LUT=28 ELEVATION=0 here: the random-request test's finding)."""
    rig = make_rig(scene=Scene.circle(2.0))
    with BirisServer(rig.hardware) as server:
        conn = server.open()
        conn.set_elevation(2.5)
        conn.wait_idle(timeout=WAIT)
        before = rig.supervisor.sequences_started
        conn.single_scan(120.0)
        assert rig.supervisor.wait_for(lambda s: s.sequences_started > before, WAIT)
        rig.faults.hang_supervisor()
        with pytest.raises(HardwareFault) as fault:
            conn.wait_idle(timeout=WAIT)
        assert fault.value.kind == "timeout"
        rig.faults.clear_all()  # BIRIS resumes the BI_ACQUIRE of the 120 degree scan
        conn.reset()
        assert server.status()["calibration"] == 0 and abs(rig.elevation_counts) <= 3.0
        assert rig.supervisor.loaded_lut == 0
        assert rig.audit.violations == []

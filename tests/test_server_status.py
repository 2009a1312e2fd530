"""``server.status()``: state, axes, counters, interrupts and per-connection delivery latency."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from biris_hw import ConnectionKind, DeliveryPolicy, Direction, HardwareFault
from biris_hw.protocol import ResetRequest
from biris_hw.server import BirisServer
from biris_hw.server.latency import LatencyHistogram
from sim import SimulatedBiris
from tests.conftest import RigFactory

WAIT = 30.0


@pytest.fixture
def time_scale() -> float:
    return 20.0


# --- the histogram on its own ----------------------------------------------------------------


def test_histogram_percentiles_are_close() -> None:
    rng = np.random.default_rng(3)
    values = rng.lognormal(mean=np.log(0.03), sigma=0.6, size=5000)
    hist = LatencyHistogram()
    assert hist.percentile(50) is None and hist.summary()["p99"] is None
    for v in values:
        hist.add(float(v))
    for q in (50.0, 99.0):
        assert hist.percentile(q) == pytest.approx(np.percentile(values, q), rel=0.15)
    summary = hist.summary()
    assert summary["count"] == 5000
    assert sum(count for _, _, count in summary["histogram"]) == 5000
    assert summary["max"] == pytest.approx(values.max())
    assert summary["p50"] <= summary["p99"] <= summary["max"]


def test_histogram_edges() -> None:
    hist = LatencyHistogram()
    for v in (-1.0, 0.0, 5e-5, 1e4):
        hist.add(v)
    summary = hist.summary()
    assert summary["count"] == 4 and summary["max"] == 1e4
    bins = summary["histogram"]
    assert bins[0][:2] == [0.0, 1e-4] and bins[0][2] == 3
    assert bins[-1][2] == 1 and bins[-1][1] == float("inf")


# --- states ----------------------------------------------------------------------------------


def test_states_follow_what_the_server_does(rig: SimulatedBiris, server: BirisServer) -> None:
    conn = server.open()
    assert server.status()["state"] == "idle"
    conn.single_scan(45.0)
    assert server.status()["state"] == "scanning"
    conn.wait_idle(timeout=WAIT)
    conn.home()
    assert server.status()["state"] == "homing"
    conn.wait_idle(timeout=WAIT)
    rig.faults.hang_supervisor()  # holds the tilt's table load open
    conn.set_elevation(5.0)
    assert server.status()["state"] == "tilting"
    rig.faults.clear_hang()
    conn.wait_idle(timeout=WAIT)
    status = server.status()
    assert status["state"] == "idle" and status["azimuth"] == 0 and status["elevation"] == 57
    assert status["calibration"] == 57


def test_initialising_and_fault_states(rig: SimulatedBiris, server: BirisServer) -> None:
    conn = server.open()
    conn.single_scan(90.0)
    rig.faults.parity_error()
    with pytest.raises(HardwareFault):
        conn.wait_idle(timeout=WAIT)
    status = server.status()
    assert status["state"] == "fault:parity" and status["counters"]["faults"] == 1
    # a reset queued ahead of a status request: the status sees initialisation under way
    ticket = server.inbox.post(ResetRequest(0))
    status = server.status()
    assert status["state"] == "initialising"
    assert status["azimuth_live"] is None and status["elevation_live"] is None  # not homed
    ticket.wait(WAIT)
    assert server.status()["state"] == "idle"


@pytest.mark.slow  # fast-tier budget (issue 13 added the transports); make test-slow
def test_live_positions_are_the_encoders_not_the_destinations(make_rig: RigFactory) -> None:
    # x10 and half a turn: the head is between the ends for ~0.14 s of real time, so a busy
    # machine still catches it there
    rig = make_rig(time_scale=10.0)
    with BirisServer(rig.hardware) as server:
        conn = server.open()
        status = server.status()
        assert abs(status["azimuth_live"] - status["azimuth"]) <= 2
        dest = conn.single_scan(180.0)
        deadline = time.monotonic() + WAIT
        while True:  # on its way: sent to the destination, seen between
            status = server.status()
            if 50 < status["azimuth_live"] < dest - 50:
                break
            assert status["state"] == "scanning" and time.monotonic() < deadline
        assert status["azimuth"] == dest
        conn.wait_idle(timeout=WAIT)
        status = server.status()
        assert abs(status["azimuth_live"] - dest) <= 2 and abs(rig.azimuth_counts - dest) <= 3
        assert status["elevation_live"] is not None and abs(status["elevation_live"]) <= 2


# --- counters and latency --------------------------------------------------------------------


@pytest.mark.slow  # fast-tier budget (issues 13-15); make test-slow
def test_counters_interrupts_and_latency(server: BirisServer) -> None:
    conn = server.open()
    latest = server.open(ConnectionKind.DATA)
    stream = server.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_ACQUISITION, depth=1024)
    seen: list[float] = []
    oldest: list[float] = []
    done = threading.Event()

    def consume() -> None:
        while not done.is_set():
            try:
                scan = latest.ready_for_data(timeout=0.5)
            except TimeoutError:
                continue
            age, ages = scan.age, scan.ages
            assert age is not None and ages is not None
            seen.append(age)
            oldest.append(float(ages.max()))

    reader = threading.Thread(target=consume)
    reader.start()
    conn.continuous_scan(-15.0, 15.0)
    while len(seen) < 3:
        stream.ready_for_data(timeout=WAIT)
    conn.stop_scan()
    conn.wait_idle(timeout=WAIT)
    done.set()
    reader.join(WAIT)
    conn.set_elevation(3.0)
    conn.wait_idle(timeout=WAIT)

    status = server.status()
    counters = status["counters"]
    scans = [conn.request_scan_data(d) for d in Direction]
    assert counters["scans"] >= 3 and counters["tilts"] == 1 and counters["lut_loads"] == 1
    assert counters["acquisitions"] >= sum(s.n_acq for s in scans if s is not None)
    assert counters["dropped_acquisitions"] == 0 and counters["faults"] == 0
    interrupts = status["interrupts"]
    assert interrupts["BIRIS_DATA_DEV"] >= counters["acquisitions"]
    assert interrupts["MOTOR_END_OF_SCAN"] >= counters["scans"]
    assert interrupts["ELEVATION_END_OF_SCAN"] >= 1
    assert interrupts["BIRIS_CMD"] >= counters["scans"]

    entry = status["connections"][latest.ident]
    assert entry["policy"] == "LATEST" and entry["delivered"] == len(seen)
    latency = entry["latency"]
    assert latency["count"] == len(seen)
    assert 0.0 < latency["p50"] <= latency["p99"] <= latency["max"] + 1e-12
    assert latency["max"] == pytest.approx(max(seen))
    points = status["connections"][stream.ident]["latency"]
    # a point is handed over as soon as it is read; a scan's first acquisitions wait a sweep
    assert points["count"] > 0 and points["p50"] < min(oldest)

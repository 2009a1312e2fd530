"""``biris_hw.io.sweeps.sweeping`` against the simulator: every sweep in order, then the head at
rest and both connections closed, however the block ends."""

from __future__ import annotations

import math

import pytest

from biris_hw import BirisServer, Direction, deg_to_counts
from biris_hw.errors import RequestError
from biris_hw.io.sweeps import sweeping

WAIT_S = 30.0


def _open_idents(server: BirisServer) -> set[int]:
    return set(server.status()["connections"])


def test_sweeps_arrive_in_order_and_the_head_is_left_at_rest(server: BirisServer) -> None:
    before = _open_idents(server)
    with sweeping(server, -20.0, 20.0, timeout=WAIT_S) as sweeps:
        assert sweeps.limits == (deg_to_counts(-20.0), deg_to_counts(20.0))
        assert _open_idents(server) == before | {sweeps.conn.ident, sweeps.data.ident}
        got = []
        for scan in sweeps:
            got.append(scan)
            if len(got) == 3:
                break
    assert [(s.direction, s.seq) for s in got] == [
        (Direction.CW, 1),
        (Direction.CCW, 1),
        (Direction.CW, 2),
    ]
    assert all(s.n_acq > 0 for s in got)
    assert sweeps.stopped and sweeps.conn.closed and sweeps.data.closed
    assert _open_idents(server) == before
    status = server.status()
    assert status["state"] == "idle" and not status["continuous"]


def test_stop_hands_over_the_sweep_that_completes_after_it(server: BirisServer) -> None:
    scans_before = int(server.status()["counters"]["scans"])  # idle: none under way
    with sweeping(server, -20.0, 20.0, timeout=WAIT_S) as sweeps:
        first = next(iter(sweeps))
        rest = sweeps.stop()
        assert sweeps.stop() == []  # once only
        assert list(sweeps) == []  # nothing more comes once stopped
    assert first.direction is Direction.CW
    # STOP lets the sweep under way complete; a LATEST connection keeps the newest of any more
    assert len(rest) == 1 and rest[0].seq >= 1
    assert sweeps.received == 2
    completed = int(server.status()["counters"]["scans"]) - scans_before
    assert sweeps.received + sweeps.dropped == completed


@pytest.mark.slow  # fast-tier budget (issues 13-15); make test-slow
def test_next_says_none_when_no_sweep_is_ready(server: BirisServer) -> None:
    with sweeping(server, -20.0, 20.0, timeout=WAIT_S) as sweeps:
        assert sweeps.next(timeout=0.0) is None  # the head has only just set off
        scan = sweeps.next()
        assert scan is not None and scan.direction is Direction.CW
    assert sweeps.conn.closed and sweeps.data.closed


@pytest.mark.slow  # fast-tier budget (issues 13-15); make test-slow
def test_an_error_in_the_block_stops_the_scan_and_closes_both(server: BirisServer) -> None:
    before = _open_idents(server)
    with pytest.raises(KeyError, match="the caller's own"), sweeping(server, -20.0, 20.0) as sweeps:
        raise KeyError("the caller's own")
    assert sweeps.conn.closed and sweeps.data.closed
    assert _open_idents(server) == before
    # STOP was sent on the way out: the sweep under way ends and the head comes to rest
    with server.open() as conn:
        conn.wait_idle(timeout=WAIT_S)
    assert not server.status()["continuous"]


def test_a_bad_request_moves_nothing_and_leaves_nothing_open(server: BirisServer) -> None:
    before = _open_idents(server)
    azimuth = server.status()["azimuth"]
    with pytest.raises(RequestError), sweeping(server, math.nan, 20.0):
        pytest.fail("the block must not run")  # pragma: no cover
    assert _open_idents(server) == before
    assert server.status()["azimuth"] == azimuth and server.status()["state"] == "idle"

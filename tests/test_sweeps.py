"""``biris_hw.io.sweeps.sweeping`` against the simulator: every sweep in order, then the head at
rest and both connections closed, however the block ends."""

from __future__ import annotations

import math

import pytest

from biris_hw import BirisServer, Direction, deg_to_counts
from biris_hw.errors import ConnectionLost, Initialising, RequestError
from biris_hw.io import sweeps as sweeps_module
from biris_hw.io.sweeps import Sweeps, sweeping

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


class _Scripted:
    """A DATA connection that answers READY_FOR_DATA from a script: an exception is raised,
    anything else handed out."""

    def __init__(self, script: list[object]) -> None:
        self.script = script
        self.dropped = 0

    def ready_for_data(self, timeout: float | None = None) -> object:
        item = self.script.pop(0)
        if isinstance(item, BaseException):
            raise item
        return item


def _scripted(script: list[object]) -> Sweeps:
    return Sweeps(None, None, _Scripted(script), (0, 0), 1.0, 0)  # type: ignore[arg-type]


def test_next_rides_out_a_reset_and_a_short_loss_of_the_network() -> None:
    scan = object()
    sweeps = _scripted(
        [Initialising("the server is initialising"), ConnectionLost("lost"), scan, TimeoutError()]
    )
    assert [sweeps.next(), sweeps.next(), sweeps.next(), sweeps.next()] == [None, None, scan, None]
    assert sweeps.received == 1


def test_next_raises_a_loss_longer_than_the_ride_out_naming_it(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(sweeps_module, "RIDE_OUT_S", 0.0)  # any loss is too long
    sweeps = _scripted([ConnectionLost("lost"), ConnectionLost("still lost"), RequestError("no")])
    assert sweeps.next() is None  # the first sign starts the span
    with pytest.raises(ConnectionLost, match=r"still lost \(no sweep for .* s, more than the 0 s"):
        sweeps.next()
    with pytest.raises(RequestError):  # a refusal is never ridden out
        sweeps.next()

"""A recording served as a sensor: equal scans and points, every policy, motion refused."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np
import pytest

from biris_hw import BirisInitRecord, BirisServer, ConnectionKind, DeliveryPolicy, Direction
from biris_hw.data import Point, Scan
from biris_hw.errors import BirisError, ConnectionClosed, RequestError
from biris_hw.io.net.keys import CONTROL_OPS
from biris_hw.io.record import Recorder
from biris_hw.io.record.replay import EndOfRecording, ReplayError, ReplayRefused, ReplayServer
from biris_hw.records import MotorParams
from sim import Scene, SimulatedBiris
from tests.conftest import Run
from tests.test_record_support import (
    assert_same_scan,
    damaged_recording,
    points_of,
    synthetic_scans,
    write_raw,
)

WAIT = 10.0


def _drain(conn: object) -> list[Scan | Point]:
    items: list[Scan | Point] = []
    while True:
        try:
            items.append(conn.ready_for_data(timeout=WAIT))  # type: ignore[attr-defined]
        except EndOfRecording:
            return items


def test_every_policy_gets_the_recorded_data(tmp_path: Path) -> None:
    scans = synthetic_scans(6)
    path = write_raw(tmp_path / "run.mcap", scans)
    with ReplayServer(path, speed=None, autostart=False) as replay:
        every = replay.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_BUFFER, depth=1)
        points = replay.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_ACQUISITION, depth=2)
        latest = replay.open(ConnectionKind.DATA)
        normal = replay.open()
        got_points: list[Scan | Point] = []
        reader = threading.Thread(target=lambda: got_points.extend(_drain(points)))
        reader.start()
        replay.start()
        got = _drain(every)  # depth 1, as fast as possible: nothing dropped, it waits for us
        reader.join()
        assert replay.wait_done(WAIT) and replay.error is None
        assert len(got) == len(scans) and every.dropped == 0
        for a, b in zip(got, scans, strict=False):
            assert isinstance(a, Scan)
            assert_same_scan(a, b)
        want_points = [p for s in scans for p in points_of(s)]
        assert len(got_points) == len(want_points) and points.dropped == 0
        for p, q in zip(got_points, want_points, strict=False):
            assert isinstance(p, Point)
            assert (p.azimuth, p.acq, p.scan_seq, p.t) == (q.azimuth, q.acq, q.scan_seq, q.t)
            assert np.array_equal(p.profile, q.profile)
        last = latest.ready_for_data(timeout=0)  # LATEST: the newest only, the rest dropped
        assert isinstance(last, Scan) and last.seq == scans[-1].seq
        assert latest.dropped == len(scans) - 1
        with pytest.raises(EndOfRecording):
            latest.ready_for_data(timeout=0)
        newest = normal.request_scan_data(Direction.CW)
        assert newest is not None and newest.seq == scans[-2].seq
        point = normal.request_point()
        assert point is not None and point.t == want_points[-1].t
        normal.wait_idle(timeout=WAIT)
        assert replay.status()["state"] == "idle"
        with pytest.raises(RequestError):
            normal.ready_for_data(timeout=0)


def test_motion_and_configuration_are_refused(tmp_path: Path) -> None:
    """Every control operation (the service's list of them: one list, checked here against the
    replay's methods) is refused, and changes nothing."""
    path = write_raw(tmp_path / "run.mcap", synthetic_scans(1))
    arguments: dict[str, tuple[object, ...]] = {
        "single_scan": (10.0,),
        "continuous_scan": (-10.0, 10.0),
        "set_elevation": (5.0,),
        "set_motor_params": (MotorParams(),),
    }
    with ReplayServer(path) as replay, replay.open() as conn:
        for op in sorted(CONTROL_OPS):
            with pytest.raises(ReplayRefused, match=f"^{op}: .*cannot move or configure"):
                getattr(conn, op)(*arguments.get(op, ()))
        assert issubclass(ReplayRefused, RequestError)
    with pytest.raises(ConnectionClosed):
        conn.request_point()


def test_recorded_timing_is_kept_at_the_speed_asked(tmp_path: Path) -> None:
    scans = synthetic_scans(2, n_acq=6)
    span = scans[-1].t_delivered - scans[0].t[0]  # type: ignore[operator]
    path = write_raw(tmp_path / "run.mcap", scans)
    speed = 4.0
    begun = time.monotonic()  # before the replay's clock starts: it is never faster than asked
    with ReplayServer(path, speed=speed) as replay:
        data = replay.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_BUFFER)
        got = _drain(data)
        took = time.monotonic() - begun
    assert len(got) == 2
    # a loaded host may make it later (a few real seconds allowed), never earlier
    assert span / speed * 0.9 <= took < span / speed + 5.0


def test_not_a_recording_is_a_replay_error(tmp_path: Path) -> None:
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not mcap at all")
    for path in (junk, tmp_path / "missing.mcap"):
        with pytest.raises(ReplayError):
            ReplayServer(path)
    with pytest.raises(ValueError):
        ReplayServer(junk, speed=0.0)


def test_a_damaged_recording_is_played_to_the_damage_then_a_replay_error(tmp_path: Path) -> None:
    scans = synthetic_scans(4)
    path = damaged_recording(tmp_path / "bad.mcap", scans)
    with ReplayServer(path, speed=None, autostart=False) as replay:
        data = replay.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_BUFFER, depth=8)
        normal = replay.open()
        replay.start()
        got: list[Scan] = []
        with pytest.raises(ReplayError, match="is damaged: playing stopped after") as caught:
            while True:  # never EndOfRecording: a damaged file does not pass for a whole one
                got.append(data.ready_for_data(timeout=WAIT))
        assert caught.value.__cause__ is replay.error is not None
        assert isinstance(caught.value, BirisError)
        assert 0 < len(got) < len(scans)  # what came before the damage, equal
        for a, b in zip(got, scans, strict=False):
            assert_same_scan(a, b)
        with pytest.raises(ReplayError):
            data.ready_for_data(timeout=0)  # and again, for as long as it is asked
        with pytest.raises(ReplayError):
            normal.wait_idle(timeout=WAIT)


def test_replay_command_reports_a_damaged_file_on_one_line(biris: Run, tmp_path: Path) -> None:
    path = damaged_recording(tmp_path / "bad.mcap", synthetic_scans(4))
    code, out, err = biris("replay", str(path))
    assert code == 1
    assert out.count(" acquisitions") >= 1 and "replayed" not in out  # the scans before it
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"biris replay: {path} is damaged"), err


@pytest.mark.slow
def test_a_live_recording_replays_equal(tmp_path: Path) -> None:
    """Record a simulated run end to end, then replay: the client's scans come back equal."""
    out = tmp_path / "live.mcap"
    received: list[Scan] = []
    with SimulatedBiris(scene=Scene.room(), samples=128, time_scale=10.0, seed=2) as rig:
        rig.start()
        with BirisServer(rig.hardware, BirisInitRecord()) as server:
            data = server.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_BUFFER, depth=16)
            conn = server.open()
            with Recorder(server, out):
                conn.continuous_scan(-30.0, 30.0)
                while len(received) < 4:
                    received.append(data.ready_for_data(timeout=WAIT))
                conn.stop_scan()
                conn.wait_idle(timeout=WAIT)
                while len(received) < server.status()["counters"]["scans"]:
                    received.append(data.ready_for_data(timeout=WAIT))
            conn.close()
            data.close()
    with ReplayServer(out, speed=None) as replay:
        again = _drain(replay.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_BUFFER))
    assert len(again) == len(received)
    for a, b in zip(again, received, strict=False):
        assert isinstance(a, Scan)
        assert_same_scan(a, b)


@pytest.mark.slow
def test_replay_command_prints_and_plots(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import argparse

    from biris_hw.commands import replay as command

    path = write_raw(tmp_path / "run.mcap", synthetic_scans(4))
    parser = argparse.ArgumentParser()
    command.add_arguments(parser)
    args = parser.parse_args([str(path), "--plot", str(tmp_path / "p.png")])
    assert command.run(args) == 0
    out = capsys.readouterr().out
    assert out.count(" acquisitions") >= 4 and "replayed" in out
    assert (tmp_path / "p.png").stat().st_size > 0

"""``biris replay --check`` on good and bad recordings, the new Scan fields through a recording
and a replay, the partial reasons the commands print, warnings on stderr, and the test suite's
own scan check (tests/conftest.py)."""

from __future__ import annotations

import dataclasses
import json
import logging
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from biris_hw import BirisInitRecord, BirisServer, ConnectionKind, DeliveryPolicy, Direction
from biris_hw import protocol as p
from biris_hw.commands.console import log_to_stderr
from biris_hw.commands.scan import scan_summary, scan_to_json
from biris_hw.data import Point, Scan
from biris_hw.io import codec as wire
from biris_hw.io.record import RAW_SCAN_TOPIC, Recorder, write_scans
from biris_hw.io.record.mcapfile import McapFile
from biris_hw.io.record.replay import EndOfRecording, ReplayServer
from biris_hw.io.scanfile import save_scans
from sim import Scene, SimulatedBiris
from sim.optics import OpticsParams
from tests.conftest import Run, _Delivered, _scan_problems, _Watch
from tests.core import Core
from tests.test_record_support import damaged_recording, synthetic_scans, write_raw
from tests.test_scancheck import OLD_SCAN_DEFINITION, _old_payload

WAIT = 10.0


def _replayed(path: Path) -> list[Scan]:
    with ReplayServer(path, speed=None) as replay:
        data = replay.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_BUFFER)
        scans: list[Scan] = []
        while True:
            try:
                scans.append(data.ready_for_data(timeout=WAIT))
            except EndOfRecording:
                return scans


def _bad_scans() -> list[Scan]:
    """Four synthetic sweeps (CW, CCW, CW, CCW) with two faults: CCW #1's row 5 stamped at row
    4's time, and CW #2's row 6 being CW #1's row 6 again (azimuth, ranges, intensities)."""
    scans = synthetic_scans(4)
    t = scans[1].t.copy()
    t[5] = t[4]
    scans[1] = dataclasses.replace(scans[1], t=t)
    ranges, intensity = scans[2].range_mm.copy(), scans[2].intensity.copy()
    ranges[6], intensity[6] = scans[0].range_mm[6], scans[0].intensity[6]
    scans[2] = dataclasses.replace(scans[2], range_mm=ranges, intensity=intensity)
    assert scans[2].azimuth[6] == scans[0].azimuth[6]
    return scans


BAD_REPORT = [
    "scan 2, CCW #1: row 5: t 10.800000 s is not after row 4's 10.800000 s",
    "scan 3, CW #2: row 6 (azimuth -18) repeats CW #1 row 6 (scan 1 of the stream): one "
    "acquisition delivered twice",
]


# -- biris replay --check ------------------------------------------------------------------------


def test_check_reports_every_bad_scan_and_row_and_exits_1(biris: Run, tmp_path: Path) -> None:
    path = write_scans(tmp_path / "bad.mcap", _bad_scans())
    code, out, err = biris("replay", "--check", str(path))
    assert code == 1 and err == "", err
    assert out.splitlines() == [*BAD_REPORT, f"{path}: 2 violations in 2 scans (of 4 checked)"]


def test_check_reads_scan_files_too(biris: Run, tmp_path: Path) -> None:
    path = save_scans(tmp_path / "bad", _bad_scans())
    code, out, _ = biris("replay", "--check", str(path))
    assert code == 1 and out.splitlines()[:-1] == BAD_REPORT
    good = save_scans(tmp_path / "good", synthetic_scans(3))
    code, out, _ = biris("replay", "--check", str(good))
    assert (code, out) == (0, f"{good}: checked 3 scans: OK\n")
    not_scans = tmp_path / "other.npz"
    np.savez(not_scans, x=np.zeros(2))
    code, _, err = biris("replay", "--check", str(not_scans))
    assert code == 2 and err.startswith(f"biris replay: not a scan file: {not_scans}"), err


def test_check_of_a_damaged_recording_says_how_far_it_got(biris: Run, tmp_path: Path) -> None:
    path = damaged_recording(tmp_path / "cut.mcap", synthetic_scans(4))
    code, out, err = biris("replay", "--check", str(path))
    assert code == 1
    last = out.splitlines()[-1]
    assert last.startswith(f"{path}: checked ") and last.endswith(": OK before the damage"), out
    assert err.startswith(f"biris replay: {path} is damaged"), err


def test_check_goes_with_no_other_output(biris: Run, tmp_path: Path) -> None:
    path = write_scans(tmp_path / "x.mcap", synthetic_scans(2))
    for extra in (["--json"], ["--plot", str(tmp_path / "p.png")]):
        code, _, err = biris("replay", "--check", str(path), *extra)
        assert code == 2 and "--check prints violations" in err, err


def test_check_passes_a_recording_of_the_simulator(biris: Run, tmp_path: Path) -> None:
    """Continuous sweeps of the simulator, recorded: every scan keeps the invariants (the test
    suite's own check judges the same scans as the server delivered them). On virtual time, as
    test_record's sweep: the recorder's feed is an outsider that only polls."""
    out = tmp_path / "live.mcap"
    received: list[Scan] = []
    with SimulatedBiris(
        scene=Scene.circle(2.0), samples=64, time_scale=8.0, seed=5, clock="virtual"
    ) as rig:
        rig.start()
        record = BirisInitRecord(continuous_acquisition=True)
        with BirisServer(rig.hardware, record) as server:
            data = server.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_BUFFER, depth=16)
            conn = server.open()
            with Recorder(server, out, status_period_s=0.05):
                conn.continuous_scan(-20.0, 20.0)
                while sum(1 for s in received if not s.partial) < 2:
                    received.append(data.ready_for_data(timeout=WAIT))
                conn.stop_scan()
                conn.wait_idle(timeout=WAIT)
                while len(received) < server.status()["counters"]["scans"]:
                    received.append(data.ready_for_data(timeout=WAIT))
            conn.close()
            data.close()
    code, text, err = biris("replay", "--check", str(out))
    assert (code, err) == (0, ""), text
    assert text == f"{out}: checked {len(received)} scans: OK\n"


# -- the new fields through recordings -----------------------------------------------------------


def _partial_scans() -> list[Scan]:
    """Synthetic sweeps with spans, one partial with its reason, one whole, one empty."""
    scans = synthetic_scans(3)
    return [
        dataclasses.replace(
            scans[0],
            span=(260, -200),
            partial=True,
            partial_reason="began 60 counts (5.3 deg) before its start 260",
        ),
        dataclasses.replace(scans[1], span=(-200, 200)),
        dataclasses.replace(
            scans[2],
            azimuth=np.zeros(0, np.int32),
            range_mm=np.zeros((0, 64), np.int16),
            intensity=np.zeros((0, 64), np.int16),
            closest_mm=np.zeros(0, np.int16),
            t=np.zeros(0),
            span=(200, -200),
            partial=True,
            partial_reason="no acquisition",
        ),
    ]


def _fields(scan: Scan) -> tuple[object, ...]:
    return (scan.direction, scan.seq, scan.n_acq, scan.partial, scan.partial_reason, scan.span)


def test_a_recording_of_a_replay_keeps_partial_reason_and_span(tmp_path: Path) -> None:
    """write_raw (the recorder's lossless channels) -> ReplayServer -> Recorder -> ReplayServer:
    the fields come back, and the recorder's summary names the partial scans."""
    scans = _partial_scans()
    source = ReplayServer(write_raw(tmp_path / "source.mcap", scans), speed=None, autostart=False)
    with source, Recorder(source, tmp_path / "again.mcap") as recorder:
        source.start()
        assert source.wait_done(WAIT)
    summary = recorder.summary
    assert summary is not None and summary.scans == 3
    assert summary.partial_scans == (
        "CW #1 (partial: began 60 counts (5.3 deg) before its start 260)",
        "CW #2 (partial: no acquisition)",
    )
    assert str(summary).endswith(
        "; 2 partial scans: CW #1 (partial: began 60 counts (5.3 deg) before its start 260), "
        "CW #2 (partial: no acquisition)"
    )
    again = _replayed(tmp_path / "again.mcap")
    assert [_fields(s) for s in again] == [_fields(s) for s in scans]


def test_the_network_service_keeps_partial_reason_and_span(tmp_path: Path) -> None:
    """A recording served on Zenoh: a remote client's scans carry the fields too (the service
    and the client encode with biris_hw.io.wire, both ways)."""
    from biris_hw.io.net import connect, serve
    from tests.net_helpers import endpoint, free_port, warm_up_zenoh

    warm_up_zenoh()
    scans = _partial_scans()
    where = endpoint(free_port())
    with (
        ReplayServer(
            write_scans(tmp_path / "run.mcap", scans), speed=100.0, autostart=False
        ) as replay,
        serve(replay, name="rec", listen=[where], multicast=False),
        connect("rec", [where], multicast=False) as remote,
    ):
        data = remote.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_BUFFER, depth=8)
        replay.start()  # once the client listens (what `biris serve --replay` does)
        got = [data.ready_for_data(timeout=WAIT) for _ in scans]
        latest = remote.open().request_scan_data(Direction.CW)
    assert [_fields(s) for s in got] == [_fields(s) for s in scans]
    assert latest is not None and _fields(latest) == _fields(scans[2])


def test_a_recording_made_before_the_new_fields_still_replays(tmp_path: Path) -> None:
    """Scans written with the first definition (old payload and schema) replay with no reason
    and no span, everything else as recorded."""
    scans = [dataclasses.replace(s, partial=k == 0) for k, s in enumerate(synthetic_scans(2))]
    path = tmp_path / "old.mcap"
    file = McapFile(path)
    for scan in scans:
        assert scan.t_delivered is not None
        file.write(
            RAW_SCAN_TOPIC,
            wire.SCAN,
            OLD_SCAN_DEFINITION,
            _old_payload(scan),
            round(scan.t_delivered * 1e9),
        )
    assert file.close()
    back = _replayed(path)
    assert [(s.partial, s.partial_reason, s.span) for s in back] == [
        (True, "", None),
        (False, "", None),
    ]
    for got, want in zip(back, scans, strict=True):
        assert np.array_equal(got.range_mm, want.range_mm) and got.seq == want.seq


# -- what the commands print ---------------------------------------------------------------------


def test_scan_summaries_and_json_give_the_reason() -> None:
    partial, whole, _ = _partial_scans()
    assert scan_summary(partial).endswith(
        ", partial sweep (began 60 counts (5.3 deg) before its start 260)"
    )
    assert "partial" not in scan_summary(whole)
    old = dataclasses.replace(whole, partial=True)  # old data: partial, no reason known
    assert scan_summary(old).endswith(", partial sweep")
    as_json = scan_to_json(partial)
    assert as_json["partial_reason"] == partial.partial_reason
    assert as_json["span_counts"] == [260, -200]
    assert scan_to_json(synthetic_scans(1)[0])["span_counts"] is None


class _PointSensor:
    """A sensor with no point yet whose short scan comes out partial: what ``biris point``
    meets when the motor starts late (the latest point then lies short of --to)."""

    def __init__(self, made: Scan) -> None:
        self.made = made
        self.scanned = False

    def open(self) -> _PointSensor:
        return self

    def __enter__(self) -> _PointSensor:
        return self

    def __exit__(self, *exc: object) -> None:
        return None

    def status(self) -> dict[str, int]:
        return {"azimuth": 0}

    def request_point(self) -> Any:
        if not self.scanned:
            return None
        row = self.made.n_acq - 1
        return Point(
            azimuth=int(self.made.azimuth[row]),
            range_mm=int(self.made.closest_mm[row]),
            profile=self.made.range_mm[row],
            intensity=self.made.intensity[row],
            t=float(self.made.t[row]),
            acq=row,
            scan_seq=self.made.seq,
        )

    def single_scan(self, to_deg: float) -> int:
        self.scanned = True
        return 114

    def wait_idle(self, timeout: float) -> None:
        return None

    def request_scan_data(self, direction: Direction) -> Scan | None:
        return self.made if direction is self.made.direction else None


def test_point_says_when_the_scan_that_made_it_is_partial(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    import argparse
    import contextlib

    from biris_hw.commands import point as command
    from biris_hw.commands.session import Session

    whole = synthetic_scans(2)[1]  # CCW, -200 .. 200
    reason = "ended 50 counts (4.4 deg) short of its destination 114"
    made = dataclasses.replace(whole, span=(0, 114), partial=True, partial_reason=reason)
    sensor = _PointSensor(made)
    session = Session(server=sensor, hardware=None, record=BirisInitRecord())  # type: ignore[arg-type]
    monkeypatch.setattr(command, "open_session", lambda args: contextlib.nullcontext(session))
    parser = argparse.ArgumentParser()
    command.add_arguments(parser)
    assert command.run(parser.parse_args(["--sim", "--yes"])) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[-1] == f"  the scan that made it (CCW #1) is partial: {reason}"
    sensor.scanned = False
    assert command.run(parser.parse_args(["--sim", "--yes", "--json"])) == 0
    assert json.loads(capsys.readouterr().out)["scan_partial_reason"] == reason
    sensor.scanned, sensor.made = False, whole
    assert command.run(parser.parse_args(["--sim", "--yes", "--json"])) == 0
    assert json.loads(capsys.readouterr().out)["scan_partial_reason"] == ""


def test_the_demo_lists_its_partial_sweeps() -> None:
    import io

    from biris_hw.commands.demo import DemoConfig, DemoResult, DemoStatus, _print_summary

    status = DemoStatus(DemoConfig())
    status.partial = ["CW #1: began 12 counts (1.1 deg) after its start 0", "CCW #3"]
    out = io.StringIO()
    _print_summary(DemoResult(status, {}, [], None), out)
    lines = out.getvalue().splitlines()
    assert lines[1:3] == [
        "  partial: CW #1: began 12 counts (1.1 deg) after its start 0",
        "  partial: CCW #3",
    ]


def test_warnings_reach_stderr_as_one_plain_line(capsys: pytest.CaptureFixture[str]) -> None:
    admin = logging.getLogger("biris_hw.server.admin")
    with log_to_stderr(False):
        admin.warning("scan %d (%s): %d acquisitions lost", 3, "CW", 2)
        admin.info("an info record is not shown")
        logging.getLogger("sim.supervisor").warning("the simulator is late")
        try:
            raise ValueError("bad\nreply")
        except ValueError:
            logging.getLogger("biris_hw.io.net.service").exception("request\n  failed")
    admin.warning("after the command: not ours to show")
    assert capsys.readouterr().err.splitlines() == [
        "biris: warning: scan 3 (CW): 2 acquisitions lost",
        "biris: warning: simulator: the simulator is late",  # what the simulator warns of, named
        "biris: error: request failed (ValueError: bad reply)",
    ]
    with log_to_stderr(True):  # --debug: the whole log, named
        admin.info("shown with --debug")
        logging.getLogger("sim.supervisor").warning("so is the simulator's")
    err = capsys.readouterr().err
    assert "biris_hw.server.admin: shown with --debug" in err
    assert "sim.supervisor: so is the simulator's" in err


# -- the test suite's own check (tests/conftest.py) ----------------------------------------------


def _rig(scene: Scene) -> Any:
    """What the conftest check reads of a rig: its scene and its optics' parameters."""
    return SimpleNamespace(scene=scene, optics=SimpleNamespace(params=OpticsParams()))


def _silent_row(scan: Scan, k: int) -> Scan:
    ranges, intensity, closest = scan.range_mm.copy(), scan.intensity.copy(), scan.closest_mm.copy()
    ranges[k], intensity[k], closest[k] = 0, 0, 0
    return dataclasses.replace(scan, range_mm=ranges, intensity=intensity, closest_mm=closest)


def test_the_suites_check_uses_what_the_rigs_allow() -> None:
    good = synthetic_scans(2)
    silent = _silent_row(dataclasses.replace(good[1], seq=2), 3)
    log = _Delivered()
    one, other = object(), object()
    log.add(one, good[0])
    log.add(one, silent)
    log.add(other, good[0])  # another server's stream: judged on its own

    def problems(scene: Scene, **options: Any) -> list[str]:
        watch = _Watch()
        watch.rigs.append(_rig(scene))
        watch.rig_options.append(options)
        return _scan_problems(log, watch)

    (found,) = problems(Scene.circle(2.0))
    assert "CCW #2: row 3 (azimuth" in found and "is all zero" in found
    assert "1 violation in 1 scan (of 2 checked)" in found
    assert problems(Scene.room()) == []  # far corners out of reach: zero rows are real
    assert problems(Scene.circle(5.0)) == []  # beyond the optics' reach
    log.add(one, good[0])  # delivered again by the same server
    assert any("repeats CW #1 row 0" in p for p in problems(Scene.room()))
    assert problems(Scene.room(), noise=False) == []  # noiseless rows repeat by nature
    assert problems(Scene.circle(2.0), trajectory=object()) != []  # still the repeat


def test_every_scan_the_server_completes_is_recorded(
    core: Core, request: pytest.FixtureRequest
) -> None:
    log = _live_log(request)
    conn = core.open()
    assert core.call(p.SingleScanRqst(conn, 300)) == 300
    acquire = core.command()
    assert acquire is not None and core.move() is not None
    core.acquisitions(acquire.seq_id, range(acquire.n_acquisitions))
    core.complete(acquire)
    core.arrive()
    scan = core.call(p.RequestScanData(conn, Direction.CCW))
    assert isinstance(scan, Scan) and scan.n_acq == acquire.n_acquisitions
    (stream,) = log.streams()
    # the client's copy carries its delivery time; the rows are the ones the server completed
    assert len(stream) == 1 and stream[0].seq == scan.seq == 1
    assert np.array_equal(stream[0].azimuth, scan.azimuth) and np.array_equal(stream[0].t, scan.t)


@pytest.mark.scan_violations_expected
def test_the_marker_lets_a_test_deliver_bad_scans(request: pytest.FixtureRequest) -> None:
    """Without the marker this test would fail at teardown: the live log is handed an empty scan
    that is not marked partial, which breaks a rule even without a rig (the server's own
    bookkeeping), and scans whose rows break the physical rules, judged where a rig is."""
    empty = _partial_scans()[2]
    empty = dataclasses.replace(empty, partial=False, partial_reason="", span=None)
    log = _live_log(request)
    log.add(self_check, empty)
    (found,) = _scan_problems(log, _Watch())
    assert "CW #2: holds no acquisition, yet is not marked partial" in found
    other = object()
    for scan in _bad_scans():
        log.add(other, scan)
    watch = _Watch()
    watch.rigs.append(_rig(Scene.room()))
    watch.rig_options.append({})
    assert "2 violations in 2 scans (of 4 checked)" in _scan_problems(log, watch)[1]


self_check = object()
"""A stand-in for a ScanSequencer in the live log."""


def _live_log(request: pytest.FixtureRequest) -> _Delivered:
    """The running test's log of delivered scans, from the conftest module pytest loaded (test
    modules import a second copy as ``tests.conftest``, whose globals are not the live ones)."""
    for plugin in request.config.pluginmanager.get_plugins():
        log = getattr(plugin, "_delivered", None)
        if type(log).__name__ == "_Delivered":  # that copy's class, not tests.conftest's
            return log  # type: ignore[no-any-return]
    raise AssertionError("no live scan log: is the conftest scan check installed?")

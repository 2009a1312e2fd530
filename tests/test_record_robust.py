"""Recordings are never lost silently (issue 24).

A recording whose writer was killed (no DataEnd, summary or footer; cut at any byte) plays up to
its last complete chunk, and says so; a damaged one still fails as such. ``biris record`` refuses
an existing ``--out`` without ``--force``. ``Recorder.close()`` returns within its bound whatever
the backlog -- a slow disk, a hung one -- and counts what it had no time to write, in the summary
and in the file. A reset of the sensor mid-recording is ridden out. A Recorder a script forgets
to close is closed at exit, or when collected, and never keeps the process alive. Ctrl-C (and
SIGTERM, which the CLI turns into it) ends ``biris record`` with a complete file and its
summary.
"""

from __future__ import annotations

import io
import json
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader
from mcap.records import Chunk
from mcap.stream_reader import StreamReader, breakup_chunk

from biris_hw import BirisInitRecord, BirisServer, ConnectionKind, DeliveryPolicy
from biris_hw.data import Scan
from biris_hw.errors import RequestError
from biris_hw.io import codec
from biris_hw.io.record import Recorder, RecordError, cutfile, mcapfile
from biris_hw.io.record.replay import EndOfRecording, ReplayError, ReplayServer
from sim import Scene, SimulatedBiris
from tests.conftest import Run, join, spawn, until
from tests.test_feed import _Sensor
from tests.test_record_support import (
    assert_same_scan,
    damaged_recording,
    points_of,
    synthetic_scans,
    write_raw,
)

WAIT = 10.0
ROOT = Path(__file__).resolve().parent.parent


# -- a recording cut short ---------------------------------------------------------------------


def _record(tmp_path: Path, n: int = 8) -> Path:
    """A recording the Recorder made of a replayed run of ``n`` scans, in small chunks."""
    source = ReplayServer(
        write_raw(tmp_path / "source.mcap", synthetic_scans(n)), speed=None, autostart=False
    )
    out = tmp_path / "run.mcap"
    with source, Recorder(source, out, chunk_size=4096, status_period_s=0.01):
        source.start()
        assert source.wait_done(WAIT)
    return out


def _play(path: Path) -> tuple[list[Scan], ReplayServer]:
    """Every scan the replay of ``path`` hands over, to EndOfRecording."""
    replay = ReplayServer(path, speed=None)
    with replay:
        data = replay.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_BUFFER, depth=64)
        got: list[Scan] = []
        while True:
            try:
                got.append(data.ready_for_data(timeout=WAIT))
            except EndOfRecording:
                return got, replay


def _scans_in_chunks_before(path: Path, cut: int) -> int:
    """Raw scans in the chunks of the complete file ``path`` that end at or before byte
    ``cut``: what "up to its last complete chunk" means, read through the file's own index."""
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
        assert summary is not None
        raw = {i for i, c in summary.channels.items() if c.topic == codec.RAW_SCAN_TOPIC}
        n = 0
        for index in summary.chunk_indexes:
            if index.chunk_start_offset + index.chunk_length > cut:
                continue
            f.seek(index.chunk_start_offset)
            chunk = next(StreamReader(f, skip_magic=True, emit_chunks=True).records)
            assert isinstance(chunk, Chunk)
            n += sum(getattr(r, "channel_id", None) in raw for r in breakup_chunk(chunk))
    return n


def test_a_recording_cut_anywhere_plays_to_its_last_complete_chunk(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    whole = _record(tmp_path)
    full, replay = _play(whole)
    assert len(full) == 8 and replay.recovered is None
    data = whole.read_bytes()
    size = len(data)
    some = cutfile.cut_of(io.BytesIO(data[: size // 2]))  # a cut right at a record's end
    assert some is not None
    cuts = [size * k // 10 for k in (2, 4, 5, 7, 9)] + [some.end, size - 1, size - 8]
    for cut in cuts:
        copy = tmp_path / f"cut{cut}.mcap"
        copy.write_bytes(data[:cut])
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="biris_hw.io.record.replay"):
            got, replay = _play(copy)
        assert replay.recovered is not None and "ends without a footer" in replay.recovered
        assert f"of {cut:,} bytes" in replay.recovered
        assert [r.getMessage() for r in caplog.records] == [replay.recovered]
        expected = 8 if cut == size - 8 else _scans_in_chunks_before(whole, cut)
        assert len(got) == expected, (cut, len(got), expected)
        for a, b in zip(got, full, strict=False):
            assert_same_scan(a, b)
    assert _scans_in_chunks_before(whole, size * 2 // 10) < 8  # some cuts did lose scans


def test_a_cut_recording_with_a_damaged_chunk_still_stops_at_the_damage(tmp_path: Path) -> None:
    damaged = damaged_recording(tmp_path / "bad.mcap", synthetic_scans(8))
    with open(damaged, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    last = max(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
    cut = tmp_path / "badcut.mcap"
    cut.write_bytes(damaged.read_bytes()[: last.chunk_start_offset + last.chunk_length + 5])
    replay = ReplayServer(cut, speed=None)
    with replay:
        assert replay.recovered is not None
        data = replay.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_BUFFER, depth=64)
        got = []
        with pytest.raises(ReplayError, match="is damaged: playing stopped after"):
            while True:  # never EndOfRecording: the damage is not taken for the cut
                got.append(data.ready_for_data(timeout=WAIT))
    assert 0 < len(got) < 8


def test_a_file_cut_before_any_data_is_refused(tmp_path: Path) -> None:
    data = _record(tmp_path).read_bytes()
    for cut, said in ((0, "not a readable MCAP file"), (5, "not a readable MCAP file")):
        path = tmp_path / f"c{cut}.mcap"
        path.write_bytes(data[:cut])
        with pytest.raises(ReplayError, match=said):
            ReplayServer(path)
    path = tmp_path / "head.mcap"
    path.write_bytes(data[:200])  # the header and the start metadata, no chunk
    with pytest.raises(ReplayError, match="ends without a footer before any BIRIS data"):
        ReplayServer(path)


def test_replay_command_plays_a_cut_file_and_says_so(biris: Run, tmp_path: Path) -> None:
    data = _record(tmp_path).read_bytes()
    path = tmp_path / "killed.mcap"
    path.write_bytes(data[: len(data) * 6 // 10])
    code, out, err = biris("replay", str(path))
    assert code == 0, err
    assert err.startswith(f"biris: warning: {path} ends without a footer"), err
    assert out.splitlines()[-1].startswith(f"replayed {path}: ")
    assert out.splitlines()[-1].endswith("(up to its last complete chunk: it has no footer)")


def _biris_argv() -> list[str]:
    script = Path(sys.executable).with_name("biris")
    if script.exists():
        return [str(script)]
    return [sys.executable, "-c", "import sys; from biris_hw.cli import main; sys.exit(main())"]


def _chunks(path: Path) -> int:
    if not path.exists():
        return 0
    with open(path, "rb") as f:
        cut = cutfile.cut_of(f)
    return 0 if cut is None else cut.chunks


@pytest.mark.slow
def test_a_sigkilled_biris_record_plays(biris: Run, tmp_path: Path) -> None:
    """``biris record --sim`` SIGKILLed once it has written a chunk (the file watched, not a
    timer): the file has no footer, and plays up to its last complete chunk."""
    out = tmp_path / "killed.mcap"
    argv = [
        *_biris_argv(),
        *("record", "--sim", "--time-scale", "10", "--scene", "circle:2", "--seed", "3"),
        *("--out", str(out), "--duration", "120", "--cw", "-45", "--ccw", "45"),
    ]
    with open(tmp_path / "stderr", "wb") as err:
        proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=err, cwd=ROOT)
        try:
            until(lambda: _chunks(out) >= 2 or proc.poll() is not None, 60.0, "two chunks")
        finally:
            proc.send_signal(signal.SIGKILL)
            proc.wait(WAIT)
    assert proc.returncode == -signal.SIGKILL, (tmp_path / "stderr").read_text()
    with open(out, "rb") as f:
        assert not cutfile.ends_with_footer(f)
    got, replay = _play(out)
    assert replay.recovered is not None and len(got) >= 1
    assert replay.metadata["software"].startswith("biris-hw ")  # the start record is there
    code, stdout, stderr = biris("replay", str(out))
    assert code == 0 and "ends without a footer" in stderr
    assert stdout.splitlines()[-1].startswith(f"replayed {out}: {len(got)} scans, ")


# -- --force -------------------------------------------------------------------------------------


def test_record_refuses_an_existing_file_without_force(biris: Run, tmp_path: Path) -> None:
    out = tmp_path / "run.mcap"
    out.write_bytes(b"an earlier recording")
    before = out.stat()
    code, stdout, err = biris("record", "--sim", "--out", str(out), "--to", "10")
    assert code == 2 and stdout == ""
    assert err.strip() == (
        f"biris record: --out {out}: the file exists; give another name, or --force to overwrite it"
    )
    assert out.read_bytes() == b"an earlier recording" and out.stat().st_mtime == before.st_mtime


def test_an_existing_file_is_refused_by_the_recorder_too(tmp_path: Path) -> None:
    """The file is created exclusively: one that appears after the command's own check (another
    recording starting) is refused, untouched."""
    out = tmp_path / "run.mcap"
    out.write_bytes(b"theirs")
    with pytest.raises(RecordError, match="exists: not overwritten") as caught:
        Recorder(_Sensor(), out, overwrite=False)
    assert caught.value.errno == 17 and out.read_bytes() == b"theirs"
    fresh = tmp_path / "fresh.mcap"
    Recorder(_Sensor(), fresh, overwrite=False).close()
    with open(fresh, "rb") as f:
        assert make_reader(f).get_summary() is not None


@pytest.mark.slow
def test_record_force_overwrites(biris: Run, tmp_path: Path) -> None:
    out = tmp_path / "run.mcap"
    out.write_bytes(b"an earlier recording")
    sim = ["--sim", "--time-scale", "10", "--scene", "circle:2", "--seed", "3"]
    code, stdout, err = biris("record", *sim, "--out", str(out), "--to", "90", "--force")
    assert code == 0, err
    assert stdout.startswith(f"recorded {out}: 1 scans")
    _got, replay = _play(out)
    assert replay.played["scans"] == 1


# -- close() within its bound --------------------------------------------------------------------


def _disk(write: Callable[[io.FileIO, Any], None]) -> Callable[[Path], io.BufferedWriter]:
    """A stream opener whose disk runs ``write(file, data)`` before each write reaches it."""

    def opener(path: Path) -> io.BufferedWriter:
        class Disk(io.FileIO):
            def write(self, data: Any) -> int:
                write(self, data)
                return int(super().write(data))

        return io.BufferedWriter(Disk(path, "wb"))

    return opener


def _metadata(path: Path) -> dict[str, dict[str, str]]:
    with open(path, "rb") as f:
        return {m.name: dict(m.metadata) for m in make_reader(f).iter_metadata()}


def test_close_returns_within_its_bound_on_a_slow_disk_and_counts_what_it_left(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A disk of 0.5 MB/s under a recorder that has ~5 s of writing queued: close() returns
    within its 3 s; what it had no time to write is counted, in the summary and in the file,
    and every acquisition is either written or counted."""

    def slow(_file: io.FileIO, data: Any) -> None:
        time.sleep(memoryview(data).nbytes / 0.5e6)  # the disk's pace, not a synchronisation

    monkeypatch.setattr(mcapfile, "_open_stream", _disk(slow))
    sensor = _Sensor()
    out = tmp_path / "run.mcap"
    bound = 3.0
    recorder = Recorder(
        sensor,
        out,
        profiles=False,
        chunk_size=8192,
        point_depth=10_000,
        status_period_s=60.0,
        close_timeout_s=bound,
    ).start()
    points = [p for scan in synthetic_scans(40, n_acq=100) for p in points_of(scan)]
    sensor.put(*points)
    (conn,) = [c for c in sensor.data_connections() if c.policy.name == "EVERY_ACQUISITION"]
    until(lambda: not conn.items, what="the feed has taken every acquisition")
    begun = time.monotonic()
    summary = recorder.close()
    took = time.monotonic() - begun
    assert took < bound + 1.5, took
    assert summary.finished and summary.complete and summary.error is None
    assert summary.unwritten_points > 0
    assert summary.points + summary.dropped_points == len(points)  # nothing uncounted
    assert summary.dropped_points == summary.unwritten_points
    assert "still waiting to be written at close" in str(summary)
    end = _metadata(out)["biris.recording"]
    assert end["unwritten_points"] == str(summary.unwritten_points)
    assert end["dropped_points"] == str(summary.dropped_points)
    with open(out, "rb") as f:
        written = sum(1 for _ in make_reader(f).iter_messages(topics=[codec.RAW_POINT_TOPIC]))
    assert written == summary.points


def test_close_returns_on_a_hung_disk_and_the_file_is_finished_when_it_answers(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    gate = threading.Event()
    armed = threading.Event()
    blocked = threading.Event()

    def hung(_file: io.FileIO, _data: Any) -> None:
        if armed.is_set():
            blocked.set()
            gate.wait()  # a disk that does not answer (an NFS server away)

    monkeypatch.setattr(mcapfile, "_open_stream", _disk(hung))
    sensor = _Sensor()
    out = tmp_path / "run.mcap"
    recorder = Recorder(sensor, out, chunk_size=2048, status_period_s=60.0, close_timeout_s=1.0)
    recorder.start()
    armed.set()
    points = points_of(synthetic_scans(1, n_acq=40)[0])
    sensor.put(*points)
    assert blocked.wait(WAIT)
    try:
        begun = time.monotonic()
        summary = recorder.close()
        took = time.monotonic() - begun
        assert took < 1.0 + 1.5, took
        assert not summary.finished and not summary.complete
        assert summary.error is not None and "not finished within 1 s of close()" in summary.error
        assert isinstance(recorder.error, RecordError)
        assert "not finished at close" in str(summary)
    finally:
        gate.set()
    again = recorder.close()  # the write returned: the recorder's thread finished the file
    assert again.finished and again.complete and again.error is None
    assert again.points + again.dropped_points == len(points)
    assert _metadata(out)["biris.recording"]["points"] == str(again.points)


# -- a reset mid-recording -----------------------------------------------------------------------


class _Refusals:
    """A sensor as it is, whose data connections count the RequestErrors they raise (what a
    server says while a reset initialises it)."""

    def __init__(self, server: BirisServer) -> None:
        self._server = server
        self.refused = threading.Event()

    def __getattr__(self, name: str) -> Any:
        return getattr(self._server, name)

    def open(self, kind: ConnectionKind = ConnectionKind.NORMAL, **options: Any) -> Any:
        conn = self._server.open(kind, **options)
        if kind is ConnectionKind.DATA:
            asked = conn.ready_for_data

            def ready_for_data(timeout: Any = None) -> Any:
                try:
                    return asked(timeout)
                except RequestError:
                    self.refused.set()
                    raise

            conn.ready_for_data = ready_for_data  # type: ignore[method-assign]
        return conn


def test_a_reset_mid_recording_is_ridden_out(tmp_path: Path) -> None:
    """A local server reset while recorded: the feed meets "the server is initialising" (time
    is held still on virtual time until it has), the recording goes on, and the scan made
    after the reset is in the file."""
    out = tmp_path / "run.mcap"
    with SimulatedBiris(
        scene=Scene.circle(2.0), samples=64, time_scale=30.0, seed=5, clock="virtual"
    ) as rig:
        rig.start()
        with BirisServer(rig.hardware, BirisInitRecord()) as server:
            watched = _Refusals(server)
            conn = server.open()
            with Recorder(watched, out, status_period_s=0.05) as recorder:
                conn.single_scan(20.0)
                conn.wait_idle(timeout=WAIT)
                until(lambda: recorder.scans == 1, what="the scan before the reset")
                resetting = spawn(conn.reset, name="test-reset")
                until(lambda: server.status()["state"] == "initialising", what="initialising")
                # a real wait: the rig's time stands still meanwhile, so the reset is still
                # under way when the feed next asks for data
                assert watched.refused.wait(WAIT), "the feed never met the reset"
                assert join(resetting)
                conn.single_scan(-20.0)
                conn.wait_idle(timeout=WAIT)
                until(lambda: recorder.scans == 2, what="the scan after the reset")
            conn.close()
    summary = recorder.summary
    assert summary is not None and summary.error is None and summary.complete
    assert not recorder.failed.is_set() and summary.scans == 2
    got, _replay = _play(out)
    assert [s.direction.name for s in got] == ["CCW", "CW"]


# -- a Recorder never closed ---------------------------------------------------------------------

_FORGETFUL = """
import gc, sys
from mcap.reader import make_reader
from biris_hw.io.record import Recorder, ReplayServer
source = ReplayServer(sys.argv[1], speed=None)  # not closed either
recorder = Recorder(source, sys.argv[2]).start()
assert source.wait_done(10.0)
if sys.argv[3] == "gc":
    del recorder
    gc.collect()
    with open(sys.argv[2], "rb") as f:
        print("complete" if make_reader(f).get_summary() is not None else "not complete")
print("done", flush=True)
"""


@pytest.mark.slow
@pytest.mark.parametrize("end", ["exit", "gc"])
def test_an_unclosed_recorder_is_closed_and_lets_the_process_end(tmp_path: Path, end: str) -> None:
    """A script that forgets close(): the Recorder is closed when collected, or at exit; the
    process ends (within the subprocess timeout) and the file is complete and holds the run."""
    source = write_raw(tmp_path / "source.mcap", synthetic_scans(6))
    out = tmp_path / "forgotten.mcap"
    done = subprocess.run(
        [sys.executable, "-c", _FORGETFUL, str(source), str(out), end],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    assert done.returncode == 0, done.stderr
    lines = done.stdout.split()
    assert lines[-1] == "done" and (end == "exit" or lines[0] == "complete"), done.stdout
    assert "was not closed: closing it" in done.stderr
    with open(out, "rb") as f:
        assert make_reader(f).get_summary() is not None
    end_record = _metadata(out)["biris.recording"]
    assert end_record["scans"] == "6" and end_record["points"] == str(6 * 12)


# -- Ctrl-C (and SIGTERM, which the CLI turns into it) -------------------------------------------


@pytest.mark.slow
def test_record_interrupted_leaves_a_complete_file_and_its_summary(
    biris: Run, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from biris_hw.commands import record as command

    def interrupted(_session: Any, _args: Any, recorder: Recorder) -> None:
        until(lambda: recorder.statuses >= 1, what="something recorded")
        raise KeyboardInterrupt

    monkeypatch.setattr(command, "_scan", interrupted)
    out = tmp_path / "x.mcap"
    sim = ["--sim", "--time-scale", "10", "--scene", "circle:2", "--seed", "3"]
    code, stdout, err = biris("record", *sim, "--out", str(out), "--duration", "60")
    assert code == 130, err
    assert stdout.startswith(f"recorded {out}: ") and "dropped 0 acquisitions" in stdout
    assert err.splitlines()[-1] == f"biris record: interrupted: {out} is complete up to then"
    with open(out, "rb") as f:
        assert make_reader(f).get_summary() is not None
    assert json.loads(_metadata(out)["biris.recording"]["lost_spans"]) == []

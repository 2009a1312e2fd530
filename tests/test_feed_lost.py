"""A lost network under a feed (biris_hw.io.feed): a remote sensor's ConnectionLost is ridden out
with a back-off and the span kept; a sink whose limit passes fails naming the span; a recorder
says what it missed, in its summary and in its file, and ``biris record --connect`` exits
non-zero when the network does not come back.

The sensor is a fake in memory whose every call raises ConnectionLost while it is "down"; the
back-off and the limits are shortened (real time: the limit is a span of real time by design)."""

from __future__ import annotations

import contextlib
import json
import logging
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader

from biris_hw import ConnectionKind, DeliveryPolicy
from biris_hw.errors import ConnectionLost
from biris_hw.io import codec, feed
from biris_hw.io.record import Recorder
from biris_hw.io.record.replay import ReplayServer
from tests.conftest import Run, until
from tests.test_feed import _Collector, _Conn, _Sensor
from tests.test_record_support import points_of, synthetic_scans

WAIT = 10.0


class _Remote(_Sensor):
    """A remote sensor whose network can be taken away: while :attr:`down`, every ask for data
    or status raises ConnectionLost (counted in :attr:`lost_calls`); the connections stay (the
    remote client reopens its own)."""

    def __init__(self) -> None:
        super().__init__()
        self.down = False
        self.lost_calls = 0

    def _check_network(self) -> None:
        with self.cond:
            if self.down:
                self.lost_calls += 1
                self.cond.notify_all()
                raise ConnectionLost("no answer from service 'biris0' (the network is down)")

    def open(
        self,
        kind: ConnectionKind = ConnectionKind.NORMAL,
        *,
        policy: DeliveryPolicy = DeliveryPolicy.LATEST,
        depth: int | None = None,
    ) -> _Conn:
        conn = super().open(kind, policy=policy, depth=depth)
        asked = conn.ready_for_data

        def ready_for_data(timeout: float | None = None) -> Any:
            self._check_network()
            return asked(timeout)

        conn.ready_for_data = ready_for_data  # type: ignore[method-assign]
        return conn

    def _status(self, newer_than: int | None, timeout: float | None, conn: _Conn | None) -> Any:
        self._check_network()
        return super()._status(newer_than, timeout, conn)

    def go_down(self, asks: int = 3) -> None:
        """Take the network away and wait until the feed has met it ``asks`` times."""
        with self.cond:
            self.down = True
            begun = self.lost_calls
        until(lambda: self.lost_calls >= begun + asks, what=f"{asks} asks meeting the lost network")

    def come_back(self) -> None:
        with self.cond:
            self.down = False


@pytest.fixture(autouse=True)
def _short_backoff(monkeypatch: pytest.MonkeyPatch) -> None:
    """Asks every 20-80 ms while the network is lost (2 s at most by default)."""
    monkeypatch.setattr(feed, "LOST_RETRY_S", 0.02)
    monkeypatch.setattr(feed, "LOST_RETRY_MAX_S", 0.08)


def test_a_lost_network_is_ridden_out_and_its_span_kept(caplog: pytest.LogCaptureFixture) -> None:
    sensor = _Remote()
    got = _Collector()
    sink = feed.attach(sensor, got, topics={codec.RAW_POINT_TOPIC}, status_period_s=None)
    points = points_of(synthetic_scans(1, n_acq=8)[0])
    sensor.put(*points[:4])
    until(lambda: len(got.points) == 4, wake=got.changed, what="the points before")
    with caplog.at_level(logging.WARNING, logger="biris_hw.io.feed"):
        sensor.go_down()
        ongoing = sink.feed.lost_span
        assert ongoing is not None and sink.lost_spans == (ongoing,) and ongoing.ended is None
        sensor.come_back()
        sensor.put(*points[4:])
        until(lambda: len(got.points) == 8, wake=got.changed, what="the points after")
    assert not sink.failed.is_set() and sink.error is None
    assert got.points == points  # the same connections carry on
    (span,) = sink.lost_spans
    assert span.ended is not None and not span.gave_up and span.seconds > 0
    assert span.after_t == points[3].t  # the last data before it
    assert f"after hardware time {points[3].t:.3f} s" in str(span)
    assert sink.feed.lost_span is None
    said = [r.getMessage() for r in caplog.records]
    assert any("network to the sensor is lost" in m for m in said), said
    assert any("network to the sensor is back" in m for m in said), said
    sink.detach()


def test_a_sink_gives_up_at_its_limit_naming_the_span_and_the_others_wait_on() -> None:
    sensor = _Remote()
    quick, patient = _Collector(), _Collector()
    impatient = feed.attach(sensor, quick, name="quick", status_period_s=None, lost_limit_s=0.3)
    waiting = feed.attach(sensor, patient, name="patient", status_period_s=None, lost_limit_s=60)
    sensor.go_down()
    assert impatient.failed.wait(WAIT)
    error = impatient.error
    assert isinstance(error, ConnectionLost)
    text = str(error)
    assert "the network to the sensor was lost from " in text and " to " in text, text
    assert "within 0.3 s" in text and "nothing was received in that span" in text, text
    (span,) = impatient.lost_spans
    assert span.gave_up and span.ended is not None and span.seconds > 0.25  # wall clock
    assert not waiting.failed.is_set()
    sensor.come_back()
    point = points_of(synthetic_scans(1, n_acq=1)[0])[0]
    sensor.put(point)
    until(lambda: len(patient.points) == 1, wake=patient.changed, what="data again")
    assert len(waiting.lost_spans) == 1 and not waiting.lost_spans[0].gave_up
    assert impatient.lost_spans == (span,)  # its span ended when it gave up
    impatient.detach()
    waiting.detach()


def test_a_drop_count_that_starts_again_is_added_up() -> None:
    """A remote client's connections reopened after a lost network count their drops from 0:
    what was counted before is kept."""
    sensor = _Remote()
    got = _Collector()
    sink = feed.attach(sensor, got, status_period_s=None)
    (points_conn,) = [c for c in sensor.data_connections() if c.policy.name == "EVERY_ACQUISITION"]
    point = points_of(synthetic_scans(1, n_acq=1)[0])[0]
    points_conn.dropped = 5
    sensor.put(point)
    until(lambda: sink.dropped_points == 5, what="5 dropped")
    points_conn.dropped = 2  # reopened: its own count from 0
    sensor.put(point)
    until(lambda: sink.dropped_points == 7, what="5 + 2 dropped")
    sink.detach()


def _metadata(path: Path) -> dict[str, dict[str, str]]:
    with open(path, "rb") as f:
        return {m.name: dict(m.metadata) for m in make_reader(f).iter_metadata()}


def test_a_recording_through_a_lost_network_names_the_span(tmp_path: Path) -> None:
    sensor = _Remote()
    scans = synthetic_scans(2, n_acq=6)
    out = tmp_path / "run.mcap"
    with Recorder(sensor, out, status_period_s=0.05) as recorder:
        sensor.put(*points_of(scans[0]), scans[0])
        until(lambda: recorder.scans == 1, what="the first scan written")
        sensor.go_down()
        sensor.come_back()
        sensor.put(*points_of(scans[1]), scans[1])
        until(lambda: recorder.scans == 2, what="the second scan written")
    summary = recorder.summary
    assert summary is not None and summary.complete and summary.error is None
    assert summary.points == 12 and summary.dropped == 0
    assert len(summary.lost_spans) == 1 and summary.lost_seconds > 0
    text = str(summary)
    assert "without the network" in text and summary.lost_spans[0] in text
    assert "dropped 0" not in text  # never a claim that nothing was missed
    end = _metadata(out)["biris.recording"]
    assert json.loads(end["lost_spans"]) == list(summary.lost_spans)
    with ReplayServer(out, speed=None) as replay:  # what came either side is in the file
        data = replay.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_BUFFER)
        assert [data.ready_for_data(timeout=WAIT).seq for _ in range(2)] == [1, 1]


def test_a_recording_stops_when_the_network_does_not_come_back(tmp_path: Path) -> None:
    sensor = _Remote()
    out = tmp_path / "run.mcap"
    recorder = Recorder(sensor, out, lost_limit_s=0.3)
    with pytest.raises(ConnectionLost, match=r"was lost from .* to "), recorder:
        sensor.put(*points_of(synthetic_scans(1, n_acq=3)[0]))
        until(lambda: recorder.points == 3, what="the points written")
        sensor.go_down()
        assert recorder.failed.wait(WAIT)
    summary = recorder.summary
    assert summary is not None and summary.complete  # the file is whole up to the loss
    assert summary.error is not None and "was lost from" in summary.error
    assert len(summary.lost_spans) == 1 and "gave up" in summary.lost_spans[0]
    assert "dropped 0" not in str(summary)
    assert json.loads(_metadata(out)["biris.recording"]["lost_spans"]) == list(summary.lost_spans)


def test_record_connect_exits_non_zero_naming_the_span(
    biris: Run, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``biris record --connect`` on a service whose network never comes back (the remote
    stood in by the fake; the limit shortened): the summary, then the error's line naming the
    span, and a non-zero exit."""
    from biris_hw.commands import record as command
    from biris_hw.commands.session import Session
    from biris_hw.records import BirisInitRecord

    sensor = _Remote()

    @contextlib.contextmanager
    def remote_session(args: Any) -> Iterator[Session]:
        yield Session(sensor, None, BirisInitRecord(), None, False, "biris record", remote=True)

    monkeypatch.setattr(command, "open_session", remote_session)
    monkeypatch.setattr(feed, "LOST_LIMIT_S", 0.3)
    sensor.down = True
    out = tmp_path / "x.mcap"
    code, stdout, err = biris(
        "record", "--connect", "biris0", "--out", str(out), "--duration", "60"
    )
    assert code != 0
    assert stdout.startswith(f"recorded {out}: ") and "without the network" in stdout
    assert "dropped 0" not in stdout
    last = err.splitlines()[-1]
    assert last.startswith("biris record: the network to the sensor was lost from "), err
    with open(out, "rb") as f:
        assert make_reader(f).get_summary() is not None  # complete
    assert _metadata(out)["biris.recording"]["lost_spans"].startswith('["from ')

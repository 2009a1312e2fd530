"""One feed per sensor and process (biris_hw.io.feed): the sensor read once, each acquisition
encoded once, the same bytes handed to every sink; sinks come and go independently, a slow one
loses (and counts) what does not fit without holding up the others; the status is pushed. The
last test serves, records and shows one simulated sensor in one process and counts the
encodings of every acquisition."""

from __future__ import annotations

import collections
import dataclasses
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from biris_hw import BirisServer, ConnectionKind, DeliveryPolicy
from biris_hw.data import Point, Scan
from biris_hw.errors import ConnectionClosed, HardwareFault
from biris_hw.io import codec, feed
from biris_hw.status import ServerState
from sim import SimulatedBiris
from tests import foxglove_client as fox
from tests.conftest import idle_status, join, spawn, until
from tests.foxglove_client import SUBPROTOCOL
from tests.test_record_support import points_of, read_decoded, synthetic_scans

WAIT = 10.0


class _Conn:
    """A connection of :class:`_Sensor`."""

    def __init__(self, sensor: _Sensor, kind: ConnectionKind, policy: DeliveryPolicy) -> None:
        self.sensor = sensor
        self.kind = kind
        self.policy = policy
        self.items: collections.deque[Any] = collections.deque()
        self.dropped = 0
        self.closed = False

    def ready_for_data(self, timeout: float | None = None) -> Any:
        sensor = self.sensor
        with sensor.cond:
            sensor.cond.wait_for(lambda: self.closed or bool(self.items), timeout or 0.0)
            if self.closed:
                raise ConnectionClosed("closed")
            if sensor.fault is not None:
                sensor.faults_raised += 1
                raise sensor.fault
            if not self.items:
                raise TimeoutError("nothing waits")
            return self.items.popleft()

    def status(self, *, newer_than: int | None = None, timeout: float | None = None) -> Any:
        return self.sensor._status(newer_than, timeout, self)

    def close(self) -> None:
        with self.sensor.cond:
            self.closed = True
            self.sensor.cond.notify_all()


class _Sensor:
    """A sensor in memory: :meth:`put` hands an item to every DATA connection of its policy;
    :meth:`change` changes the status, which a wait for a newer one hears at once (the push);
    with :attr:`fault` set, every ask for data raises it."""

    playback = False
    paced = True
    record = None

    def __init__(self) -> None:
        self.cond = threading.Condition()
        self.opened: list[_Conn] = []
        self.now = idle_status()
        self.reads = 0
        """Statuses answered at once (a poll)."""
        self.waits = 0
        """Waits for a newer status begun (the push)."""
        self.fault: HardwareFault | None = None
        self.faults_raised = 0
        self.t = 0.0

    def clock(self) -> float:
        return self.t

    def open(
        self,
        kind: ConnectionKind = ConnectionKind.NORMAL,
        *,
        policy: DeliveryPolicy = DeliveryPolicy.LATEST,
        depth: int | None = None,
    ) -> _Conn:
        with self.cond:
            conn = _Conn(self, kind, policy)
            self.opened.append(conn)
            return conn

    def status(self, *, newer_than: int | None = None, timeout: float | None = None) -> Any:
        return self._status(newer_than, timeout, None)

    def _status(self, newer_than: int | None, timeout: float | None, conn: _Conn | None) -> Any:
        with self.cond:
            if newer_than is None:
                self.reads += 1
                return self.now
            self.waits += 1
            self.cond.notify_all()
            self.cond.wait_for(
                lambda: (conn is not None and conn.closed) or self.now.change > newer_than,
                timeout,
            )
            if conn is not None and conn.closed:
                raise ConnectionClosed("closed")
            if self.now.change <= newer_than:
                raise TimeoutError("no change")
            return self.now

    def change(self, **fields: Any) -> None:
        with self.cond:
            self.now = dataclasses.replace(self.now, change=self.now.change + 1, **fields)
            self.cond.notify_all()

    def put(self, *items: Point | Scan) -> None:
        with self.cond:
            for item in items:
                policy = (
                    DeliveryPolicy.EVERY_ACQUISITION
                    if isinstance(item, Point)
                    else DeliveryPolicy.EVERY_BUFFER
                )
                for conn in self.opened:
                    if conn.policy is policy and not conn.closed:
                        conn.items.append(item)
            self.cond.notify_all()

    def data_connections(self) -> list[_Conn]:
        return [c for c in self.opened if c.kind is ConnectionKind.DATA]


class _Collector:
    """A sink's ``on_batch``: keeps every batch, and says when one came."""

    def __init__(self, block: threading.Event | None = None) -> None:
        self.batches: list[feed.Batch] = []
        self.changed = threading.Condition()
        self.block = block
        self.blocked = threading.Event()

    def __call__(self, batch: feed.Batch) -> None:
        if self.block is not None:
            self.blocked.set()
            self.block.wait()
        with self.changed:
            self.batches.append(batch)
            self.changed.notify_all()

    @property
    def points(self) -> list[Point]:
        return [p for b in self.batches for p in b.points]

    def messages(self, topic: str | None = None) -> list[feed.Message]:
        return [m for b in self.batches for m in b.messages if topic in (None, m.topic)]

    def statuses(self) -> list[feed.StatusReading]:
        return [b.status for b in self.batches if b.status is not None]


def _feed_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name.startswith(("biris-feed", "biris-sink"))]


DATA_TOPICS = frozenset(
    {
        codec.RAW_POINT_TOPIC,
        codec.TF_TOPIC,
        codec.PROFILE_TOPIC,
        codec.RAW_SCAN_TOPIC,
        codec.POINTS_TOPIC,
    }
)


def test_one_feed_per_sensor_reads_it_once_and_stops_with_its_last_sink() -> None:
    sensor = _Sensor()
    sinks = [
        feed.attach(sensor, _Collector(), name=f"s{i}", status_period_s=None) for i in range(3)
    ]
    shared = feed.shared_feed(sensor)
    assert all(s.feed is shared for s in sinks)
    policies = sorted(c.policy.value for c in sensor.data_connections())
    assert policies == ["every_acquisition", "every_buffer"]  # two connections, whatever the sinks
    for sink in sinks[:2]:
        sink.detach()
    assert not any(c.closed for c in sensor.data_connections())  # one sink still reads
    sinks[2].detach()
    assert all(c.closed for c in sensor.opened)
    assert _feed_threads() == []
    again = feed.attach(sensor, _Collector(), status_period_s=None)
    assert again.feed is not shared and len(sensor.data_connections()) == 4
    again.detach()


def test_each_message_is_encoded_once_and_every_sink_gets_the_same_bytes(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Three sinks with overlapping topics: each acquisition's and scan's messages encoded once
    (counted per item, by wrapping the codec's functions), and a topic two sinks take is the
    same bytes object in both."""
    calls: collections.Counter[tuple[str, object]] = collections.Counter()

    def per_item(name: str, key: Callable[[Any], object]) -> None:
        original = getattr(codec, name)

        def counted(first: Any, *args: Any, **kwargs: Any) -> Any:
            for item in first if isinstance(first, list) else [first]:
                calls[(name, key(item))] += 1
            return original(first, *args, **kwargs)

        monkeypatch.setattr(codec, name, counted)

    for name in ("encode_point", "transforms", "profile_clouds"):
        per_item(name, lambda p: p.t)  # synthetic scans number acquisitions from 0 each
    for name in ("encode_scan", "scan_cloud"):
        per_item(name, lambda s: (s.direction, s.seq))
    sensor = _Sensor()
    takes = {
        "all": DATA_TOPICS,
        "raw": {codec.RAW_POINT_TOPIC, codec.RAW_SCAN_TOPIC},
        "views": {codec.TF_TOPIC, codec.PROFILE_TOPIC, codec.POINTS_TOPIC},
    }
    got = {name: _Collector() for name in takes}
    sinks = [
        feed.attach(sensor, got[name], name=name, topics=topics, status_period_s=None)
        for name, topics in takes.items()
    ]
    scans = synthetic_scans(3)
    for scan in scans:
        sensor.put(*points_of(scan), scan)
    for sink in sinks:
        sink.detach()  # hands each what waited
    n_points = sum(s.n_acq for s in scans)
    assert set(calls.values()) == {1}
    assert len(calls) == 3 * n_points + 2 * len(scans)
    shared = sinks[0].feed
    for topic in DATA_TOPICS:
        per_scan = topic in (codec.RAW_SCAN_TOPIC, codec.POINTS_TOPIC)
        want = len(scans) if per_scan else n_points
        assert shared.encoded[topic] == want, topic
        holders = [got[name].messages(topic) for name, topics in takes.items() if topic in topics]
        assert all(len(messages) == want for messages in holders), topic
        for other in holders[1:]:
            assert all(a.data is b.data for a, b in zip(holders[0], other, strict=True)), topic
    assert all(s.dropped_points == 0 and s.dropped_scans == 0 for s in sinks)
    # what a sink is handed is in order: each acquisition's profile, transforms, lossless point
    first = got["all"].messages()[:3]
    assert [m.topic for m in first] == [codec.PROFILE_TOPIC, codec.TF_TOPIC, codec.RAW_POINT_TOPIC]
    assert first[0].item is first[2].item and codec.decode_point(first[2].data).acq == 0


def test_a_slow_sink_loses_what_does_not_fit_and_holds_up_no_one() -> None:
    sensor = _Sensor()
    release = threading.Event()
    slow, fast = _Collector(block=release), _Collector()
    slow_sink = feed.attach(sensor, slow, name="slow", point_depth=5, status_period_s=None)
    fast_sink = feed.attach(sensor, fast, name="fast", status_period_s=None)
    points = points_of(synthetic_scans(1, n_acq=43)[0])
    try:
        sensor.put(*points[:3])
        assert slow.blocked.wait(WAIT)  # its thread is held in its first batch
        sensor.put(*points[3:])
        until(
            lambda: len(fast.points) == 43, wake=fast.changed, what="every point to the fast sink"
        )
    finally:
        release.set()
    slow_sink.detach()
    fast_sink.detach()
    assert [p.acq for p in fast.points] == list(range(43)) and fast_sink.dropped_points == 0
    kept = len(slow.points)
    assert slow_sink.points == kept and kept + slow_sink.dropped_points == 43
    assert slow_sink.dropped_points >= 40 - 5  # all but what its queue of five could hold


def test_detaching_hands_over_what_waits_at_once() -> None:
    """A batch period of a minute: the detach does not wait it out, and hands the sink what the
    sensor had queued (the reader rests on an event, not a timer)."""
    sensor = _Sensor()
    got = _Collector()
    sink = feed.attach(sensor, got, batch_s=60.0, status_period_s=None)
    scan = synthetic_scans(1)[0]
    sensor.put(*points_of(scan), scan)
    begun = time.monotonic()
    sink.detach()
    assert time.monotonic() - begun < WAIT
    assert len(got.points) == scan.n_acq and got.batches[-1].final


def test_a_prompt_sink_gets_each_acquisition_as_it_is_read() -> None:
    """A batch period of a minute, but a prompt sink: the reader waits on the acquisitions
    themselves, so each goes out as soon as it is read."""
    sensor = _Sensor()
    got = _Collector()
    sink = feed.attach(sensor, got, batch_s=60.0, prompt=True, status_period_s=None)
    for point in points_of(synthetic_scans(1, n_acq=3)[0]):
        sensor.put(point)
        until(lambda p=point: p in got.points, wake=got.changed, what=f"acquisition {point.acq}")
    sink.detach()


def test_the_status_is_pushed_and_asks_nothing_while_nothing_changes() -> None:
    sensor = _Sensor()
    got = _Collector()
    sink = feed.attach(
        sensor, got, status_changes=True, status_period_s=60.0, topics={codec.RAW_STATUS_TOPIC}
    )
    until(lambda: len(got.statuses()) == 1, wake=got.changed, what="the first status")
    until(lambda: sensor.waits >= 1, wake=sensor.cond, what="the feed to wait for a change")
    polled = sensor.reads
    sensor.change(azimuth=100)
    until(lambda: len(got.statuses()) == 2, wake=got.changed, what="the change")
    reading = got.statuses()[-1]
    assert reading.status is not None and reading.status.azimuth == 100
    assert sensor.reads == polled  # it came by the push: no poll
    raw = got.messages(codec.RAW_STATUS_TOPIC)[-1]
    assert codec.decode_status(raw.data).azimuth == 100
    begun = time.monotonic()
    sink.detach()  # ends the wait for the next change at once
    assert time.monotonic() - begun < WAIT
    assert _feed_threads() == []


def test_a_fault_is_said_once_as_the_sensor_enters_it() -> None:
    sensor = _Sensor()
    got = _Collector()
    sink = feed.attach(
        sensor,
        got,
        topics={codec.RAW_FAULT_TOPIC},
        status_changes=True,
        status_period_s=60.0,
    )

    def faults() -> list[HardwareFault]:
        return [codec.decode_fault(m.data) for m in got.messages(codec.RAW_FAULT_TOPIC)]

    sensor.fault = HardwareFault("parity", "PERR on level 2")
    until(lambda: any(b.faults for b in got.batches), wake=got.changed, what="the fault met")
    sensor.change(state=ServerState.FAULT, fault="parity")
    until(lambda: faults(), wake=got.changed, what="the fault said")
    sensor.change(azimuth=5)  # still in the fault: not said again
    until(lambda: len(got.statuses()) == 3, wake=got.changed, what="the status in the fault")
    sensor.fault = None
    sensor.change(state=ServerState.IDLE, fault=None)  # a reset
    until(lambda: len(got.statuses()) == 4, wake=got.changed, what="the status out of it")
    sensor.change(state=ServerState.FAULT, fault="bus")  # a new fault, not met on the data
    until(lambda: len(faults()) == 2, wake=got.changed, what="the second fault said")
    sensor.change(state=ServerState.FAULT, fault="timeout")  # another kind: said too
    until(lambda: len(faults()) == 3, wake=got.changed, what="the third fault said")
    sink.detach()
    said = faults()
    assert [(f.kind, f.message) for f in said] == [
        ("parity", "PERR on level 2"),  # the sensor's own words, met on the data
        ("bus", "the server is in a fault"),
        ("timeout", "the server is in a fault"),
    ]


def test_a_sink_that_raises_fails_alone() -> None:
    sensor = _Sensor()
    good = _Collector()

    def bad(batch: feed.Batch) -> None:
        if batch.points:
            raise ValueError("a sink's bug")

    broken = feed.attach(sensor, bad, name="bad", status_period_s=None)
    fine = feed.attach(sensor, good, name="good", status_period_s=None)
    points = points_of(synthetic_scans(1, n_acq=6)[0])
    sensor.put(*points[:3])
    assert broken.failed.wait(WAIT) and isinstance(broken.error, ValueError)
    sensor.put(*points[3:])
    until(lambda: len(good.points) == 6, wake=good.changed, what="the good sink's points")
    assert not fine.failed.is_set()
    broken.detach()
    fine.detach()


def test_a_batch_that_cannot_be_encoded_is_counted_and_the_feed_goes_on() -> None:
    """An acquisition outside the message types (acq beyond uint64): its batch is lost for
    every sink and counted in their drops; the next batch goes out as ever."""
    sensor = _Sensor()
    got = _Collector()
    sink = feed.attach(sensor, got, topics={codec.RAW_POINT_TOPIC}, status_period_s=None)
    good = points_of(synthetic_scans(1, n_acq=2)[0])
    sensor.put(dataclasses.replace(good[0], acq=2**64))
    until(lambda: sink.dropped_points == 1, what="the batch counted as dropped")
    sensor.put(good[1])
    until(lambda: len(got.points) == 1, wake=got.changed, what="the next batch")
    sink.detach()
    assert [codec.decode_point(m.data).acq for m in got.messages()] == [good[1].acq]
    assert sink.feed.dropped_points == 1


def test_a_sensor_that_cannot_be_read_is_an_error_at_attach() -> None:
    class Closed(_Sensor):
        def open(self, *args: Any, **kwargs: Any) -> _Conn:
            raise ConnectionClosed("the sensor has stopped")

    sensor = Closed()
    for _ in range(2):  # and a second try is not left waiting for the first
        with pytest.raises(ConnectionClosed):
            feed.attach(sensor, _Collector())
    assert _feed_threads() == []


def test_sensor_time_is_the_sensors_clock_and_never_before_what_was_seen() -> None:
    sensor = _Sensor()
    sensor.t = 7.0
    assert feed.sensor_time(sensor, 3.0) == 7.0
    assert feed.sensor_time(sensor, 9.0) == 9.0


def test_unknown_topics_and_frames_are_refused() -> None:
    sensor = _Sensor()
    with pytest.raises(ValueError, match="/diagnostics"):
        feed.attach(sensor, _Collector(), topics={codec.DIAGNOSTICS_TOPIC})
    with pytest.raises(ValueError, match="frame"):
        feed.attach(sensor, _Collector(), frame="world")  # type: ignore[arg-type]
    assert sensor.opened == []


# -- one sensor served, recorded and shown in one process ------------------------------------------


@pytest.fixture(scope="module")
def _runtimes() -> None:
    """Zenoh's and foxglove-sdk's runtimes live as long as the process once started: start them
    before the leak check's snapshot (as tests/test_net.py and tests/test_liveview.py do)."""
    import foxglove

    from tests.net_helpers import warm_up_zenoh

    warm_up_zenoh()
    foxglove.start_server(port=0, context=foxglove.Context()).stop()


VIEWED = ("/diagnostics", codec.TF_TOPIC, codec.PROFILE_TOPIC, codec.POINTS_TOPIC)


def _view_client(port: int) -> Iterator[tuple[str, bytes]]:
    """A Foxglove WebSocket client subscribed to :data:`VIEWED`: (topic, payload) of every
    message, until the view closes."""
    from websockets.exceptions import ConnectionClosed as SocketClosed
    from websockets.sync.client import connect

    with connect(f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL], max_queue=None) as ws:  # type: ignore[list-item]
        channels = fox.advertised(ws, len(codec.TOPICS))
        subs = fox.subscribe(ws, [channels[t] for t in VIEWED])
        try:
            for channel, _, payload in fox.frames(ws, subs):
                yield channel["topic"], payload
        except SocketClosed:
            return


@pytest.mark.realtime  # the Zenoh session's and the WebSocket server's threads: scaled time
def test_served_recorded_and_viewed_each_acquisition_is_encoded_once(
    rig: SimulatedBiris,
    server: BirisServer,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    _runtimes: None,
) -> None:
    """The network service, a recorder and a live view of one sensor in one process share one
    feed: every acquisition and every scan is encoded once per message type (counted by
    wrapping the codec), and each sink got every message -- the subscriber on the network
    every point, the file every point's three messages, the viewer every transform and
    profile."""
    from biris_hw.io.liveview import LiveView
    from biris_hw.io.net import connect, serve
    from biris_hw.io.record import Recorder
    from tests.net_helpers import endpoint, free_port

    encoded: collections.Counter[tuple[str, object]] = collections.Counter()
    for name, key in (
        ("encode_point", lambda p: p.t),  # an acquisition's time names it (acq counts per scan)
        ("transforms", lambda p: p.t),
        ("profile_clouds", lambda p: p.t),
        ("encode_scan", lambda s: (s.direction, s.seq)),
        ("scan_cloud", lambda s: (s.direction, s.seq)),
    ):
        original = getattr(codec, name)

        def counted(
            first: Any, *args: Any, _n: str = name, _k: Any = key, _o: Any = original
        ) -> Any:
            for item in first if isinstance(first, list) else [first]:
                encoded[(_n, _k(item))] += 1
            return _o(first, *args)

        monkeypatch.setattr(codec, name, counted)

    where = endpoint(free_port())
    received: list[Point] = []
    arrived = threading.Condition()

    def on_point(point: Point) -> None:
        with arrived:
            received.append(point)
            arrived.notify_all()

    truth = server.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_ACQUISITION, depth=4096)
    scans = server.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_BUFFER, depth=16)
    out = tmp_path / "run.mcap"
    with (
        serve(server, name="feed", listen=[where], multicast=False) as service,
        connect("feed", [where], multicast=False) as remote,
        Recorder(server, out, status_period_s=0.2) as recorder,
        LiveView(server, port=0, status_period_s=0.2) as view,
    ):
        shared = feed.shared_feed(server)
        assert {s.name for s in shared.sinks} == {"service", "recorder", "liveview"}
        subscription = remote.subscribe("point", on_point)
        client = _view_client(view.port)
        assert next(t for t, _ in client if t == "/diagnostics")  # its subscriptions are in
        shown: list[str] = []
        showing = threading.Condition()

        def watch() -> None:  # what the viewer receives, until the view closes
            for topic, _ in client:
                with showing:
                    shown.append(topic)
                    showing.notify_all()

        watcher = spawn(watch)
        until(lambda: service._pub_point.matching_status.matching, what="the subscriber seen")
        with server.open() as conn:
            conn.continuous_scan(-20.0, 20.0)
            swept = [scans.ready_for_data(timeout=WAIT) for _ in range(2)]
            conn.stop_scan()
            conn.wait_idle(timeout=WAIT)
        points: list[Point] = []
        while True:
            try:
                points.append(truth.ready_for_data(timeout=0))
            except TimeoutError:
                break
        while True:  # the sweep the stop ended, if it completed
            try:
                swept.append(scans.ready_for_data(timeout=0))
            except TimeoutError:
                break
        n = len(points)
        assert n >= sum(s.n_acq for s in swept) > 0
        until(lambda: len(received) >= n, wake=arrived, what="every point on the network")
        until(  # before the view closes: what a viewer has not received by then is not shown
            lambda: shown.count(codec.POINTS_TOPIC) >= len(swept),
            wake=showing,
            what="every scan's cloud in the viewer",
        )
        subscription.close()
    summary = recorder.summary
    assert summary is not None
    assert join(watcher)
    viewed = collections.Counter(shown)  # what was sent until it closed
    # the sensor was read once: one pair of connections for three sinks
    readers = [c for c in server.status().connections.values() if c.kind == "DATA"]
    assert len(readers) == 2  # the test's own two; the feed's closed with its last sink
    # each acquisition and scan: one encoding per message type, whatever the sinks
    acquisitions = {p.t for p in points}
    for name in ("encode_point", "transforms", "profile_clouds"):
        assert {encoded[(name, acq)] for acq in acquisitions} == {1}, name
    for scan in swept:
        assert encoded[("encode_scan", (scan.direction, scan.seq))] == 1
        assert encoded[("scan_cloud", (scan.direction, scan.seq))] == 1
    assert max(encoded.values()) == 1
    print(  # the figures, for a reader of -s
        f"{n} acquisitions, {summary.scans} scans: {sum(encoded.values())} encodings, at most "
        f"{max(encoded.values())} per item and message type; "
        f"published {service.published['point']}, recorded {summary.points}, "
        f"viewed {viewed[codec.TF_TOPIC]}"
    )
    # and each sink got every message
    assert [p.t for p in received][:n] == [p.t for p in points]
    assert service.published["point"] >= n and service.dropped_points == 0
    assert summary.points >= n and summary.dropped == 0
    in_file = collections.Counter(m[0] for m in read_decoded(out))
    for topic in (codec.RAW_POINT_TOPIC, codec.TF_TOPIC, codec.PROFILE_TOPIC):
        assert in_file[topic] == summary.points, topic
    assert in_file[codec.RAW_SCAN_TOPIC] == in_file[codec.POINTS_TOPIC] == summary.scans >= 1
    assert viewed[codec.TF_TOPIC] == viewed[codec.PROFILE_TOPIC] == summary.points
    assert viewed[codec.POINTS_TOPIC] == summary.scans
    truth.close()
    scans.close()


def test_a_status_that_cannot_be_read_is_asked_again_after_a_pause_not_in_a_spin() -> None:
    """A sensor whose status fails (a closed one, a stand-in with data only) is asked again
    every STATUS_POLL_S: a status thread that retried at once held the interpreter lock from
    the reader and the sinks (a served stand-in published 200 points a second where it
    published 8000)."""

    class NoStatus(_Sensor):
        asked = 0
        polls = 0

        def open(self, kind: ConnectionKind = ConnectionKind.NORMAL, **options: Any) -> _Conn:
            if kind is ConnectionKind.NORMAL:
                raise ConnectionClosed("data only")
            conn = super().open(kind, **options)
            original = conn.ready_for_data

            def counted(timeout: float | None = None) -> Any:
                NoStatus.polls += 1
                return original(timeout)

            conn.ready_for_data = counted  # type: ignore[method-assign]
            return conn

        def _status(self, newer_than: int | None, timeout: float | None, conn: Any) -> Any:
            NoStatus.asked += 1
            raise ConnectionClosed("no status here")

    sensor = NoStatus()
    sink = feed.attach(sensor, _Collector(), status_period_s=0.01, status_changes=True)
    try:
        until(lambda: NoStatus.polls >= 20, what="twenty asks for data")
    finally:
        sink.detach()
    # the reader asks twice a batch (points, scans): about one status ask per data ask pair
    assert NoStatus.asked <= NoStatus.polls + 5, (NoStatus.asked, NoStatus.polls)

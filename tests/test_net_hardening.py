"""The service against misuse (fast tier): a sensor in memory (:class:`FakeSensor`), the service
and its clients in this process over loopback TCP.

Controllers are served while readers block; connections belong to whoever holds their token;
reset waits for the initialisation; scan counters per direction; passwords only where needed;
no connection outlives its client or its feed; the status thread survives a bad status;
playback is decided from the sensor; the dead-man stops a sweep nobody controls any more.
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Iterator
from typing import Any

import pytest
import zenoh

from biris_hw.data import DeliveryPolicy, Direction
from biris_hw.errors import ConnectionClosed, HardwareFault, Initialising, RequestError
from biris_hw.io.net import RemoteSensor, Service, connect, remote, serve
from biris_hw.io.net.keys import Keys
from biris_hw.io.net.service import MAX_BLOCKING, NEW_CLIENT_BURST, NEW_CLIENT_RATE, _Client
from biris_hw.io.net.zconfig import make_config
from tests.conftest import WAIT, until
from tests.net_helpers import FakeSensor, endpoint, free_port, warm_up_zenoh
from tests.test_record_support import synthetic_scans

CONTROLLERS = {"op": "s3cret"}
KEYS = Keys("h")


@pytest.fixture(scope="module", autouse=True)
def _zenoh_runtime() -> None:
    warm_up_zenoh()


@pytest.fixture
def fake() -> Iterator[FakeSensor]:
    sensor = FakeSensor()
    yield sensor
    sensor.free()


@pytest.fixture
def served(fake: FakeSensor) -> Iterator[tuple[Service, str]]:
    where = endpoint(free_port())
    with serve(
        fake,
        name="h",
        listen=[where],
        controllers=CONTROLLERS,
        multicast=False,
        status_period=0.05,
        stop_when_controllers_leave=True,
    ) as svc:
        yield svc, where


@pytest.fixture
def raw(served: tuple[Service, str]) -> Iterator[zenoh.Session]:
    """A bare Zenoh session: a peer that speaks the protocol as it likes."""
    session = zenoh.open(make_config(connect=[served[1]]))
    try:
        until(
            lambda: list(session.liveliness().get(KEYS.service_token, timeout=1.0)),
            what="raw session sees the service",
        )
        yield session
    finally:
        session.close()  # type: ignore[no-untyped-call]


def _ask(session: zenoh.Session, op: str, **body: Any) -> dict[str, Any]:
    """One request; {"ok": value} or the error reply's body."""
    replies = list(session.get(KEYS.rpc(op), payload=json.dumps(body).encode(), timeout=5.0))
    assert len(replies) == 1
    reply = replies[0]
    if reply.err is not None:
        found: dict[str, Any] = json.loads(reply.err.payload.to_bytes())
        return found
    assert reply.ok is not None
    return {"ok": json.loads(reply.ok.payload.to_bytes())}


def _connect(where: str, **credentials: str) -> RemoteSensor:
    return connect("h", [where], multicast=False, **credentials)


def test_stop_scan_is_answered_while_readers_block(
    fake: FakeSensor, served: tuple[Service, str], raw: zenoh.Session
) -> None:
    """Item: a reader must never delay a controller's stop_scan."""
    svc, where = served
    tokens = []
    for k in range(12):  # 12 clients x 8 in flight: more than any pool of readers
        body = _ask(raw, "open", client=f"reader{k}", kind="DATA", policy="latest")
        tokens.append((f"reader{k}", body["ok"]["conn"]))
    pending = [
        raw.get(
            KEYS.rpc("ready_for_data"),
            payload=json.dumps({"client": ident, "conn": token, "timeout": 5}).encode(),
            timeout=10.0,
        )
        for ident, token in tokens
        for _ in range(8)
    ]
    try:
        until(lambda: fake.blocked >= MAX_BLOCKING, what="readers blocked")
        with _connect(where, user="op", password="s3cret") as controller:
            conn = controller.open()
            started = time.monotonic()
            conn.stop_scan()
            took = time.monotonic() - started
            assert fake.blocked == MAX_BLOCKING  # held all along: not one more than the cap
    finally:
        fake.free()
    replies = [list(h) for h in pending]
    assert took < 1.0, took
    assert "stop_scan" in fake.calls
    assert all(len(r) == 1 for r in replies)  # every read answered, once
    answers = [json.loads(r[0].err.payload.to_bytes()) for r in replies if r[0].err]
    busy = [a for a in answers if a["error"] == "Busy"]
    held = [a for a in answers if a["error"] == "TimeoutError"]  # the fake's answer once freed
    assert len(busy) + len(held) == len(answers)  # refused as Busy, or served: nothing else
    # the cap held (asserted above); a read still queued when the held ones were freed may be
    # served then rather than refused, so the refusals are at most what the cap left out
    assert 0 < len(busy) <= len(pending) - MAX_BLOCKING and svc.refused_busy >= len(busy)


def test_a_connection_is_usable_only_by_its_opener(
    fake: FakeSensor, served: tuple[Service, str], raw: zenoh.Session
) -> None:
    svc, where = served
    with _connect(where) as victim:
        conn = victim.open()
        me = victim.client  # public: it is the key of the victim's liveliness token
        assert _ask(raw, "request_point", client=me, conn=conn.ident)["error"] == "BadRequest"
        guess = "A" * 22
        for op in ("request_point", "close"):
            assert _ask(raw, op, client=me, conn=guess)["error"] == "ConnectionClosed"
        # withdrawing a token of the victim's key does not release the victim: Zenoh says
        # nothing while the victim's own is declared, and the service checks that it is gone
        token = raw.liveliness().declare_token(KEYS.client_token(me))
        token.undeclare()
        # then a client of the raw session's leaves: its release comes after anything the
        # withdrawal above could have caused (one link, one subscriber, one janitor, in order)
        assert "conn" in _ask(raw, "open", client="decoy")["ok"]
        decoy = raw.liveliness().declare_token(KEYS.client_token("decoy"))
        until(lambda: "decoy" in svc.clients(), what="decoy known")
        decoy.undeclare()
        until(lambda: svc.released_clients == 1, what="the decoy released")
        assert svc.clients() == {me: 1}
        assert conn.request_point() is None  # still the victim's, still open
    until(lambda: svc.released_clients == 2, what="the victim released when it leaves")


def test_fresh_client_ids_do_not_dodge_the_limits(
    served: tuple[Service, str], raw: zenoh.Session
) -> None:
    svc, _ = served
    began = time.monotonic()
    handlers = [
        raw.get(KEYS.rpc("status"), payload=json.dumps({"client": f"c{k}"}).encode())
        for k in range(200)
    ]
    errors = [json.loads(r.err.payload.to_bytes()) for h in handlers for r in h if r.err]
    # the bucket refills while the flood runs: by as much as the time it took (a loaded host's
    # flood takes longer), and never more
    admitted = NEW_CLIENT_BURST + NEW_CLIENT_RATE * (time.monotonic() - began) + 1
    assert len(errors) >= 200 - admitted
    assert all(e["error"] == "Busy" for e in errors)
    assert len(svc.clients()) <= admitted


def test_remote_reset_waits_for_the_initialisation(
    fake: FakeSensor, served: tuple[Service, str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A reset outlasting a read's reply margin is waited for, and its fault raised."""
    _, where = served
    monkeypatch.setattr(remote, "REPLY_MARGIN_S", 0.05)
    fake.reset_s = 0.2
    fake.reset_fault = HardwareFault("motor_stall", "homing: the pan axis stalled")
    with _connect(where, user="op", password="s3cret") as controller:
        with pytest.raises(HardwareFault) as caught:
            controller.open().reset()
        assert caught.value.kind == "motor_stall"


def test_scan_counters_per_direction(fake: FakeSensor, served: tuple[Service, str]) -> None:
    svc, where = served
    with _connect(where) as reader:
        got: list[Direction] = []
        subscription = reader.subscribe("scan", lambda scan: got.append(scan.direction))
        until(
            lambda: all(p.matching_status.matching for p in svc._pub_scan.values()),
            what="the service sees the subscriber",
        )
        for scan in synthetic_scans(5, n_acq=2, samples=4):
            fake.feed(scan)
        until(lambda: subscription.received == 5, what="five scans")
        assert subscription.dropped == 0
        assert (svc.published["scan/cw"], svc.published["scan/ccw"]) == (3, 2)
        assert got == [Direction.CW, Direction.CCW] * 2 + [Direction.CW]
        subscription.close()


def test_a_publication_is_counted_received_once_its_callback_has_returned(
    fake: FakeSensor, served: tuple[Service, str]
) -> None:
    """A reader waiting for ``received`` to reach n must have had n callbacks: counted on
    arrival, a loaded host's Zenoh thread could be pre-empted before the callback ran."""
    svc, where = served
    entered, release = threading.Event(), threading.Event()

    def slow(scan: object) -> None:
        entered.set()
        release.wait(WAIT)

    with _connect(where) as reader:
        subscription = reader.subscribe("scan", slow)
        until(
            lambda: all(p.matching_status.matching for p in svc._pub_scan.values()),
            what="the service sees the subscriber",
        )
        fake.feed(next(iter(synthetic_scans(1, n_acq=2, samples=4))))
        try:
            assert entered.wait(WAIT)
            assert subscription.received == 0  # in the callback: not yet counted
        finally:
            release.set()
        until(lambda: subscription.received == 1, what="the scan counted")
        subscription.close()


def test_passwords_go_only_with_control_operations(
    fake: FakeSensor, monkeypatch: pytest.MonkeyPatch
) -> None:
    """What reaches the service's queryable (any peer may declare one that matches)."""
    heard: dict[str, dict[str, Any]] = {}
    on_query = Service._on_query

    def spy(self: Service, query: zenoh.Query) -> None:
        payload = query.payload
        body = json.loads(payload.to_bytes() if payload is not None else b"{}")
        heard[str(query.key_expr).rsplit("/", 1)[-1]] = body
        on_query(self, query)

    monkeypatch.setattr(Service, "_on_query", spy)
    where = endpoint(free_port())
    with (
        serve(fake, name="h", listen=[where], controllers=CONTROLLERS, multicast=False),
        _connect(where, user="op", password="s3cret") as controller,
    ):
        conn = controller.open()
        controller.status()
        conn.request_point()
        conn.stop_scan()
    assert set(heard) >= {"open", "status", "request_point", "stop_scan"}
    assert {op for op, body in heard.items() if "password" in body} == {"stop_scan"}


def test_open_for_a_released_client_closes_the_connection(
    fake: FakeSensor, served: tuple[Service, str]
) -> None:
    svc, _ = served
    client = _Client("gone")
    client.released = True  # its token went while open() was at the server
    with pytest.raises(ConnectionClosed):
        svc._open({"kind": "NORMAL"}, client)
    assert fake.opened[-1].closed and client.connections == {}


def test_a_feed_that_ends_closes_its_connection(
    fake: FakeSensor, served: tuple[Service, str]
) -> None:
    def feed() -> Any:
        return next(c for c in fake.opened if c.policy is DeliveryPolicy.EVERY_BUFFER)

    until(lambda: any(c.policy is DeliveryPolicy.EVERY_BUFFER for c in fake.opened))
    fake.feed(ConnectionClosed("the BIRIS server has stopped"))
    until(lambda: feed().closed, what="the scan feed's connection closed")


def test_a_feed_reads_on_while_the_server_initialises(
    fake: FakeSensor, served: tuple[Service, str]
) -> None:
    """During a reset every read is refused (Initialising, a RequestError); the feed looks again
    on the same connection, whose data come back when the reset is done."""
    until(lambda: any(c.policy is DeliveryPolicy.EVERY_BUFFER for c in fake.opened))
    scans = next(c for c in fake.opened if c.policy is DeliveryPolicy.EVERY_BUFFER)
    for _ in range(3):
        fake.feed(Initialising("the server is initialising"))
    until(lambda: not fake.scans, what="every refusal read by the feed")
    assert not scans.closed


def test_status_thread_survives_an_unexpected_error(
    fake: FakeSensor, served: tuple[Service, str]
) -> None:
    svc, _ = served
    fake.status_error = ValueError("a bug")
    until(lambda: fake.status_error is None, what="the status thread met the error")
    before = svc.published["status"]
    until(lambda: svc.published["status"] > before, what="status published again")


def test_playback_is_decided_from_the_sensor() -> None:
    with pytest.raises(RequestError, match="not a recording"):
        Service(FakeSensor(), "p", playback=True, multicast=False)


def test_dead_man_stops_the_scan_when_the_last_controller_leaves(
    fake: FakeSensor, served: tuple[Service, str]
) -> None:
    svc, where = served
    with _connect(where) as reader:
        reader.open()
        with _connect(where, user="op", password="s3cret") as controller:
            controller.open().continuous_scan(-10.0, 10.0)
        until(lambda: "stop_scan" in fake.calls, what="the dead-man's stop_scan")
        assert svc.dead_man_stops == 1
        assert reader.status()["state"] == "idle"


def test_no_dead_man_unless_asked(fake: FakeSensor) -> None:
    where = endpoint(free_port())
    with serve(fake, name="h", listen=[where], controllers=CONTROLLERS, multicast=False) as svc:
        with _connect(where, user="op", password="s3cret") as controller:
            controller.open().continuous_scan(-10.0, 10.0)
        until(lambda: svc.released_clients == 1, what="the controller released")
        assert "stop_scan" not in fake.calls

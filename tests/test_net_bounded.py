"""Bounded peers (fast tier): a sensor in memory (:class:`FakeSensor`), the service and raw Zenoh
peers in this process over loopback TCP.

A client that never declares its liveliness token holds its connections on a lease its requests
renew, so a reader that opens the service's every connection and goes quiet locks nobody out
for long; a client whose token the service sees keeps them until the token goes. Failed
authentications are limited per client and for the service as a whole, counted and logged,
while a controller already at work goes on. A request of nobody is refused. Requests wait
their turn per client, not behind a flooder's backlog.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any, cast

import pytest
import zenoh

from biris_hw.io.net import Service, serve
from biris_hw.io.net import service as service_module
from biris_hw.io.net.keys import Keys
from biris_hw.io.net.service import _FairPool
from biris_hw.io.net.zconfig import make_config
from tests.conftest import until
from tests.net_helpers import FakeSensor, endpoint, free_port, warm_up_zenoh

if TYPE_CHECKING:
    from biris_hw.sensor import Sensor

CONTROLLERS = {"op": "s3cret"}
KEYS = Keys("b")


@pytest.fixture(scope="module", autouse=True)
def _zenoh_runtime() -> None:
    warm_up_zenoh()


@pytest.fixture
def fake() -> Iterator[FakeSensor]:
    sensor = FakeSensor()
    yield sensor
    sensor.free()


def _serve(fake: FakeSensor) -> Any:
    where = endpoint(free_port())
    sensor = cast("Sensor", fake)  # what the service uses of a sensor, in memory
    return serve(sensor, name="b", listen=[where], controllers=CONTROLLERS, multicast=False), where


@pytest.fixture
def served(fake: FakeSensor) -> Iterator[tuple[Service, str]]:
    context, where = _serve(fake)
    with context as svc:
        yield svc, where


def _session(where: str) -> zenoh.Session:
    session = zenoh.open(make_config(connect=[where]))
    until(
        lambda: list(session.liveliness().get(KEYS.service_token, timeout=1.0)),
        what="the raw session sees the service",
    )
    return session


@pytest.fixture
def raw(served: tuple[Service, str]) -> Iterator[zenoh.Session]:
    """A bare Zenoh session: a peer that speaks the protocol as it likes."""
    session = _session(served[1])
    try:
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
    if reply.ok.encoding == zenoh.Encoding.APPLICATION_JSON:
        return {"ok": json.loads(reply.ok.payload.to_bytes())}
    return {"ok": reply.ok.payload.to_bytes()}


def _open(session: zenoh.Session, client: str, **body: Any) -> str:
    answer = _ask(session, "open", client=client, **body)
    assert "ok" in answer, answer
    token: str = answer["ok"]["conn"]
    return token


def _status_attachment(session: zenoh.Session, **asked: bool) -> dict[str, Any]:
    """A status reply's attachment (what ``asked`` asks for)."""
    payload = json.dumps({"client": "counting", **asked}).encode()
    (reply,) = list(session.get(KEYS.rpc("status"), payload=payload, timeout=5.0))
    assert reply.ok is not None and reply.ok.attachment is not None
    attachment: dict[str, Any] = json.loads(reply.ok.attachment.to_bytes())
    return attachment


def _counters(session: zenoh.Session) -> dict[str, int]:
    """The service's counters, as a status request asks for them."""
    counters: dict[str, int] = _status_attachment(session, counters=True)["service"]
    return counters


# -- leases ------------------------------------------------------------------------------------


@pytest.mark.realtime  # the janitor's own rounds, on the monotonic clock, are the point
def test_a_reader_without_a_token_cannot_lock_everyone_out_for_long(
    fake: FakeSensor, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The review's lock-out, scaled down: a peer opens every connection the service allows
    under ids whose token it never declares and goes quiet; a newcomer is answered Busy, until
    the lease runs out and the janitor closes them, within the stated bound."""
    monkeypatch.setattr(service_module, "MAX_CONNECTIONS", 4)
    monkeypatch.setattr(service_module, "CLIENT_LEASE_S", 0.3)
    monkeypatch.setattr(service_module, "LEASE_CHECK_S", 0.05)
    context, where = _serve(fake)
    with context as svc:
        attacker, newcomer = _session(where), _session(where)
        try:
            tokens = [_open(attacker, f"squatter{k % 2}", kind="DATA") for k in range(3)]
            last_asked = time.monotonic()
            tokens.append(_open(attacker, "squatter1", kind="DATA"))
            assert _ask(newcomer, "open", client="newcomer")["error"] == "Busy"
            until(lambda: svc.expired_clients == 2, what="the squatters let go")
            assert time.monotonic() - last_asked >= 0.3  # not before their lease ran out
            squatted = fake.opened[-4:]
            assert all(conn.closed for conn in squatted)
            assert svc.clients() == {"newcomer": 0} and svc.released_clients == 0
            answer = _ask(attacker, "request_point", client="squatter0", conn=tokens[0])
            assert answer["error"] == "ConnectionClosed"  # what a lapsed client holds is gone
            assert "conn" in _ask(newcomer, "open", client="newcomer")["ok"]
        finally:
            attacker.close()  # type: ignore[no-untyped-call]
            newcomer.close()  # type: ignore[no-untyped-call]


def test_a_client_with_a_token_keeps_its_connections_past_the_lease(
    served: tuple[Service, str], raw: zenoh.Session
) -> None:
    svc, _ = served
    token = raw.liveliness().declare_token(KEYS.client_token("holder"))
    until(lambda: "holder" in svc._live, what="the service sees the holder's token")
    conn = _open(raw, "holder")
    _open(raw, "leaseholder")  # no token: on a lease
    later = time.monotonic() + 2 * service_module.CLIENT_LEASE_S
    assert svc._expire_leases(later) == 1
    assert svc.clients() == {"holder": 1}
    assert _ask(raw, "request_point", client="holder", conn=conn) == {"ok": None}
    token.undeclare()  # type: ignore[no-untyped-call]
    until(lambda: svc.released_clients == 1, what="the holder released when its token goes")
    assert svc.clients() == {}


def test_a_request_in_flight_keeps_the_lease(
    fake: FakeSensor, served: tuple[Service, str], raw: zenoh.Session
) -> None:
    """A reader waiting in READY_FOR_DATA is asking something: its lease does not run out
    under it (the wait is held at most MAX_WAIT_S, shorter than the lease)."""
    svc, _ = served
    conn = _open(raw, "waiter", kind="DATA", policy="latest")
    body = json.dumps({"client": "waiter", "conn": conn, "timeout": 5}).encode()
    waiting = raw.get(KEYS.rpc("ready_for_data"), payload=body, timeout=10.0)
    until(lambda: fake.blocked == 1, what="the read held")
    assert svc._expire_leases(time.monotonic() + 2 * service_module.CLIENT_LEASE_S) == 0
    fake.free()
    (reply,) = list(waiting)
    assert reply.err is not None
    assert json.loads(reply.err.payload.to_bytes())["error"] == "TimeoutError"
    assert svc.clients() == {"waiter": 1}


# -- authentication ----------------------------------------------------------------------------


def test_password_guessing_is_limited_per_client_counted_and_logged(
    fake: FakeSensor, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    monkeypatch.setattr(service_module, "AUTH_RATE_PER_CLIENT", 0.0)  # no refill mid-test
    caplog.set_level(logging.WARNING, logger="biris_hw.io.net.service")
    context, where = _serve(fake)
    with context as svc:
        session = _session(where)
        try:
            conn = _open(session, "guesser")
            errors = [
                _ask(
                    session,
                    "stop_scan",
                    client="guesser",
                    conn=conn,
                    user="op",
                    password=f"guess{k}",
                )
                for k in range(12)
            ]
            allowed = int(service_module.AUTH_FAILURES_PER_CLIENT)
            assert [e["error"] for e in errors] == ["AccessDenied"] * allowed + ["Busy"] * (
                12 - allowed
            )
            assert {e.get("class") for e in errors[allowed:]} == {"AuthLimited"}
            # the right password is not even looked at now: a guesser learns nothing
            right = _ask(session, "stop_scan", client="guesser", conn=conn, **_op())
            assert right.get("class") == "AuthLimited" and "stop_scan" not in fake.calls
            counters = _counters(session)
            assert counters["refused_access"] == allowed
            assert counters["refused_auth_limited"] == 12 - allowed + 1
            assert (svc.refused_access, svc.refused_auth_limited) == (allowed, 12 - allowed + 1)
        finally:
            session.close()  # type: ignore[no-untyped-call]
    said = [r.getMessage() for r in caplog.records if r.name == "biris_hw.io.net.service"]
    assert any(s.startswith("access refused: client guesser (user op)") for s in said)
    assert any(s.startswith("authentication limited: client guesser (user op)") for s in said)
    assert len(said) == 2  # one line per kind and REFUSAL_LOG_S, however many refusals


def _op() -> dict[str, str]:
    return {"user": "op", "password": CONTROLLERS["op"]}


def test_guessers_with_many_ids_are_held_by_the_service_wide_limit(
    fake: FakeSensor, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Fresh ids do not get round the limit: all clients together have a few failures; then
    nobody new is checked, but a controller that authenticated before goes on controlling
    what it opened."""
    monkeypatch.setattr(service_module, "AUTH_RATE", 0.0)
    context, where = _serve(fake)
    with context as svc:
        session = _session(where)
        try:
            working = _open(session, "controller")
            assert _ask(session, "stop_scan", client="controller", conn=working, **_op()) == {
                "ok": None
            }
            budget = int(service_module.AUTH_FAILURES)
            answers = []
            for k in range(budget + 5):
                conn = _open(session, f"guesser{k}")
                guess = {"user": "op", "password": f"x{k}", "cw_deg": -1, "ccw_deg": 1}
                answers.append(
                    _ask(session, "continuous_scan", client=f"guesser{k}", conn=conn, **guess)
                )
            assert [a["error"] for a in answers] == ["AccessDenied"] * budget + ["Busy"] * 5
            latecomer = _open(session, "latecomer")
            refused = _ask(
                session,
                "continuous_scan",
                client="latecomer",
                conn=latecomer,
                cw_deg=-1,
                ccw_deg=1,
                **_op(),
            )
            assert refused.get("class") == "AuthLimited"
            assert _ask(session, "stop_scan", client="controller", conn=working, **_op()) == {
                "ok": None
            }
            assert fake.calls.count("stop_scan") == 2 and "continuous_scan" not in fake.calls
            assert svc.refused_access == budget
        finally:
            session.close()  # type: ignore[no-untyped-call]


def test_reads_need_no_credentials_and_spend_no_allowance(
    served: tuple[Service, str], raw: zenoh.Session
) -> None:
    """On a service that is free to read, a read's credentials (there are none) are never
    checked, so reading costs nothing of the failures allowed."""
    svc, _ = served
    conn = _open(raw, "reader")
    for _ in range(3 * int(service_module.AUTH_FAILURES_PER_CLIENT)):
        assert _ask(raw, "request_point", client="reader", conn=conn, password="x") == {"ok": None}
    assert (svc.refused_access, svc.refused_auth_limited) == (0, 0)


def test_status_tells_clients_controllers_and_counts(
    served: tuple[Service, str], raw: zenoh.Session
) -> None:
    svc, _ = served
    _open(raw, "reader")
    working = _open(raw, "controller")
    assert _ask(raw, "stop_scan", client="controller", conn=working, **_op()) == {"ok": None}
    wrong = _ask(raw, "stop_scan", client="reader", conn=working, user="op", password="no")
    assert wrong["error"] == "AccessDenied"
    info = _status_attachment(raw, info=True)
    assert (info["clients"], info["controllers"]) == (2, 1)
    assert "service" not in info  # only when asked
    counters = _status_attachment(raw, counters=True)["service"]
    assert counters == svc.counters()
    assert counters["connections"] == 2 and counters["clients"] == 3  # "counting" asked too
    assert counters["requests"] == 6 and counters["refused_access"] == 1


# -- who asks ----------------------------------------------------------------------------------


@pytest.mark.parametrize("client", [None, 7, "", ["me"], "a/b", "x" * 65])
def test_a_request_of_nobody_is_refused(
    served: tuple[Service, str], raw: zenoh.Session, client: object
) -> None:
    svc, _ = served
    body: dict[str, Any] = {} if client is None else {"client": client}
    answer = _ask(raw, "status", **body)
    assert answer["error"] == "BadRequest" and "client" in answer["message"]
    assert svc.clients() == {} and svc.refused_bad == 1


# -- fairness ----------------------------------------------------------------------------------


def test_requests_wait_their_turn_per_client() -> None:
    """One worker, held by a flooder's request while it queues four more; a second client's
    one request comes next, not behind the four (as a first-come queue would have it)."""
    pool = _FairPool(1, 16, "test-fair")
    served: list[str] = []
    holding = threading.Event()
    release = threading.Event()

    def hold() -> None:
        holding.set()
        release.wait(10.0)
        served.append("flood0")

    try:
        assert pool.submit("flood", hold)
        assert holding.wait(10.0)
        for k in range(1, 5):
            assert pool.submit("flood", served.append, f"flood{k}")
        assert pool.submit("other", served.append, "other")
        release.set()
    finally:
        pool.shutdown()  # serves what waits, then ends its worker
    assert served == ["flood0", "flood1", "other", "flood2", "flood3", "flood4"]


def test_a_full_pool_says_no_and_a_closed_one_refuses() -> None:
    pool = _FairPool(1, 1, "test-full")
    release = threading.Event()
    try:
        assert pool.submit("a", release.wait, 10.0)
        assert pool.submit("b", release.wait, 10.0)
        assert not pool.submit("c", release.wait, 10.0)  # one running, one waiting: full
    finally:
        release.set()
        pool.shutdown()
    with pytest.raises(RuntimeError):
        pool.submit("a", release.wait, 0.0)

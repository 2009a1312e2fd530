"""The network service in one process (fast tier): every message through Zenoh on loopback TCP,
authorisation, and bad input. Other processes: tests/test_net_processes.py (slow)."""

from __future__ import annotations

import json
import threading
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest
import zenoh

from biris_hw import BirisServer, ConnectionKind, Direction, MotorParams
from biris_hw.data import DeliveryPolicy, Point, Scan
from biris_hw.errors import AccessDenied, BirisError, ConnectionClosed, HardwareFault, RequestError
from biris_hw.io.net import RemoteSensor, Service, connect, serve
from biris_hw.io.net.keys import MAX_REQUEST, Keys
from biris_hw.io.net.zconfig import make_config
from sim import SimulatedBiris
from tests.conftest import until
from tests.net_helpers import endpoint, free_port, warm_up_zenoh

# the Zenoh service's own threads call into the server: scaled real time
pytestmark = pytest.mark.realtime

CONTROLLERS = {"op": "s3cret"}


@pytest.fixture(scope="module", autouse=True)
def _zenoh_runtime() -> None:
    warm_up_zenoh()


@pytest.fixture
def service(server: BirisServer) -> Iterator[tuple[Service, str]]:
    where = endpoint(free_port())
    with serve(server, name="t", listen=[where], controllers=CONTROLLERS, multicast=False) as svc:
        yield svc, where


def _connect(where: str, **credentials: str) -> RemoteSensor:
    return connect("t", [where], multicast=False, **credentials)


def _same_scan(a: Scan | None, b: Scan | None) -> bool:
    assert a is not None and b is not None
    return (a.direction, a.seq, a.dropped, a.acquisition, a.partial) == (
        b.direction,
        b.seq,
        b.dropped,
        b.acquisition,
        b.partial,
    ) and all(
        np.array_equal(getattr(a, k), getattr(b, k))
        for k in ("azimuth", "range_mm", "closest_mm", "intensity", "t")
    )


CUT_SCAN_RETRIES = 3
"""Scans to 45 degrees a test makes before it gives up on one with acquisitions."""


def _scan_with_acquisitions(conn: Any, data: Any) -> Scan:
    """A CCW scan to 45 degrees that holds acquisitions, delivered on ``data`` (every buffer).

    Beside CPU-bound processes a late host can cut a scan down to no acquisition at all: the
    server marks it partial, as it must, and that is no failure here; the head goes back to 0
    and scans again (the way back's scan, whatever it holds, is taken off ``data`` too)."""
    for _ in range(CUT_SCAN_RETRIES):
        assert conn.single_scan(45.0) == 512
        scan = data.ready_for_data(timeout=30)
        assert isinstance(scan, Scan) and scan.direction is Direction.CCW and data.dropped == 0
        if scan.n_acq:
            return scan
        assert scan.partial and scan.partial_reason, "an empty scan not marked partial"
        conn.wait_idle(timeout=30)
        conn.single_scan(0.0)
        assert isinstance(data.ready_for_data(timeout=30), Scan)
        conn.wait_idle(timeout=30)
    pytest.fail(f"{CUT_SCAN_RETRIES} scans to 45 degrees in a row held no acquisition")


def test_every_message_end_to_end(server: BirisServer, service: tuple[Service, str]) -> None:
    svc, where = service
    with _connect(where, user="op", password="s3cret") as remote, _connect(where) as reader:
        points: list[Point] = []
        got_point = threading.Event()

        def on_point(point: Point) -> None:
            points.append(point)
            got_point.set()

        subscription = reader.subscribe("point", on_point)
        conn = remote.open()
        data = remote.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_BUFFER)
        acq = reader.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_ACQUISITION)
        assert remote.status()["state"] == "idle"
        assert conn.request_point() is None and conn.request_scan_data(Direction.CCW) is None
        with pytest.raises(TimeoutError):
            data.ready_for_data(timeout=0)  # a poll: nothing yet

        scan = _scan_with_acquisitions(conn, data)
        first = acq.ready_for_data(timeout=30)
        assert isinstance(first, Point)
        conn.wait_idle(timeout=30)
        with server.open() as local:  # what a local client gets is what a remote one gets
            assert _same_scan(local.request_scan_data(Direction.CCW), scan)
            assert _same_scan(conn.request_scan_data(Direction.CCW), scan)
            here = local.request_point()
            there = conn.request_point()
            assert here is not None and there is not None
            assert (here.acq, here.t, here.azimuth) == (there.acq, there.t, there.azimuth)
            assert np.array_equal(here.profile, there.profile)
        assert got_point.wait(5)
        until(lambda: any(p.scan_seq == scan.seq for p in points), what="the scan's points pushed")

        with pytest.raises(RequestError, match="already"):
            conn.single_scan(45.0)  # the head is there: the server's own refusal, carried back
        assert conn.continuous_scan(-10.0, 10.0) == (-114, 114)
        conn.stop_scan()
        conn.wait_idle(timeout=30)
        conn.start_continuous()
        conn.wait_idle(timeout=30)
        assert remote.status().acquisition == "continuous"
        conn.stop_continuous()
        assert conn.set_elevation(0.0) == 0
        conn.home()
        conn.set_motor_params(MotorParams())
        conn.timeout_disable()
        conn.timeout_enable()
        conn.wait_idle(timeout=30)
        conn.reset()
        conn.wait_idle(timeout=30)
        assert remote.status()["state"] == "idle"

        with pytest.raises(RequestError):
            conn.single_scan(float("nan"))  # refused here, before anything is sent
        with pytest.raises(RequestError):
            conn.request_scan_data(7)
        with pytest.raises(RequestError):
            remote.open(ConnectionKind.DATA, depth=0)
        conn.close()
        with pytest.raises(ConnectionClosed):
            conn.request_point()
        subscription.close()
        assert subscription.received >= 1
    until(lambda: svc.clients() == {}, what="both clients' connections released")


def test_reader_is_refused_control_and_nothing_changes(
    server: BirisServer, service: tuple[Service, str]
) -> None:
    _, where = service
    for credentials in ({}, {"user": "op", "password": "wrong"}, {"user": "x", "password": "y"}):
        with _connect(where, **credentials) as reader:
            conn = reader.open()
            before = reader.status()
            with pytest.raises(AccessDenied):
                conn.single_scan(90.0)
            with pytest.raises(AccessDenied):
                conn.continuous_scan(-5.0, 5.0)
            with pytest.raises(AccessDenied):
                conn.home()
            with pytest.raises(AccessDenied):
                conn.reset()
            with pytest.raises(AccessDenied):
                conn.set_motor_params(MotorParams(gain=0x10))
            assert issubclass(AccessDenied, BirisError)
            after = reader.status()
            assert (after.state, after.azimuth, after.counters["scans"]) == (
                before.state,
                before.azimuth,
                before.counters["scans"],
            )
            conn.wait_idle(timeout=0)  # reading is free


def test_bad_network_input_gets_clear_errors(
    server: BirisServer, service: tuple[Service, str]
) -> None:
    svc, where = service
    keys = Keys("t")
    raw = zenoh.open(make_config(connect=[where]))
    try:
        until(
            lambda: list(raw.liveliness().get(keys.service_token, timeout=1.0)),
            what="raw session sees the service",
        )

        def ask(op: str, payload: bytes) -> dict[str, str]:
            replies = list(raw.get(keys.rpc(op), payload=payload, timeout=5.0))
            assert len(replies) == 1
            err = replies[0].err
            assert err is not None, replies[0].ok
            body: dict[str, str] = json.loads(err.payload.to_bytes())
            return body

        client = {"client": "rawclient"}
        assert ask("launch_missiles", json.dumps(client).encode())["error"] == "BadRequest"
        assert ask("open", b"\xff\xfe not json")["error"] == "BadRequest"
        assert ask("open", b"[1, 2]")["error"] == "BadRequest"
        assert ask("open", b"{" + b" " * (MAX_REQUEST + 1) + b"}")["error"] == "BadRequest"
        assert ask("open", json.dumps({"client": "no/slashes"}).encode())["error"] == "BadRequest"
        body = ask("request_point", json.dumps({**client, "conn": "one"}).encode())
        assert body["error"] == "BadRequest" and "conn" in body["message"]
        body = ask("request_point", json.dumps({**client, "conn": 999}).encode())
        assert body["error"] == "BadRequest"  # a connection is named by its token, not a number
        body = ask("request_point", json.dumps({**client, "conn": "x" * 22}).encode())
        assert body["error"] == "ConnectionClosed"
        body = ask("open", json.dumps({**client, "kind": "SECRET"}).encode())
        assert body["error"] == "RequestError"
        body = ask("single_scan", json.dumps({**client, "conn": "x" * 22, "to_deg": 1}).encode())
        assert body["error"] == "AccessDenied"

        # a flood from one client: the excess is answered Busy at once; others are served
        flood = json.dumps({"client": "flood"}).encode()
        handlers = [raw.get(keys.rpc("status"), payload=flood, timeout=10.0) for _ in range(300)]
        answers = [reply for handler in handlers for reply in handler]
        busy = [r for r in answers if r.err is not None]
        assert len(answers) == 300
        assert busy and all(
            json.loads(r.err.payload.to_bytes())["error"] == "Busy" for r in busy if r.err
        )
        assert svc.refused_busy == len(busy)
        with _connect(where) as other:
            assert other.status()["state"] == "idle"
    finally:
        raw.close()  # type: ignore[no-untyped-call]


def test_the_service_serves_on_through_a_fault(
    rig: SimulatedBiris, server: BirisServer, service: tuple[Service, str]
) -> None:
    """A parity fault mid-sweep: the service keeps answering status (the fault in it), publishes
    the fault and the status that shows it, and once a controller has reset the sensor over
    the network, publishes new acquisitions again: none of its threads ended at the fault."""
    _svc, where = service
    published: dict[str, list[Any]] = {"fault": [], "status": [], "point": []}
    changed = threading.Condition()

    def keeper(what: str) -> Callable[[Any], None]:
        def keep(value: Any) -> None:
            with changed:
                published[what].append(value)
                changed.notify_all()

        return keep

    with _connect(where, user="op", password="s3cret") as remote, _connect(where) as reader:
        subscriptions = [
            reader.subscribe("fault", keeper("fault")),
            reader.subscribe("status", keeper("status")),
            reader.subscribe("point", keeper("point")),
        ]
        conn = remote.open()
        conn.continuous_scan(-10.0, 10.0)
        until(lambda: published["point"], wake=changed, what="an acquisition published")
        rig.faults.parity_error()
        until(lambda: published["fault"], wake=changed, what="the fault published")
        assert [f.kind for f in published["fault"]] == ["parity"]
        until(
            lambda: any(s.state_name == "fault:parity" for s in published["status"]),
            wake=changed,
            what="a status in the fault published",
        )
        for _ in range(3):  # asked again and again, the service answers
            assert reader.status().state_name == "fault:parity"
        with pytest.raises(HardwareFault, match="parity"):
            conn.wait_idle(timeout=0)
        conn.reset()
        reset_at = rig.clock.now()
        assert reader.status().state_name == "idle"
        conn.continuous_scan(-10.0, 10.0)
        until(
            lambda: published["point"][-1].t > reset_at,
            wake=changed,
            what="an acquisition made after the reset published",
        )
        conn.stop_scan()
        conn.wait_idle(timeout=30)
        for subscription in subscriptions:
            subscription.close()
    assert len(published["fault"]) == 1


def test_no_service_is_a_clear_error() -> None:
    with pytest.raises(ConnectionClosed, match="no BIRIS service"):
        connect("nobody", [endpoint(free_port())], multicast=False, timeout=0.3)
    with pytest.raises(RequestError):
        connect("bad/name")

"""Every request is answered (fast tier): hypothesis drives raw Zenoh queries on every rpc key of a
service on a sensor in memory, over loopback TCP, and each gets exactly one reply -- a success
or one of the documented error replies, never none and never the service's InternalError.

The payloads: bytes of any kind, any JSON value, requests whose every field may be of any type
(a real connection token and the real credentials among the choices, so that requests also get
through to the sensor), JSON nested thousands deep, and sizes around the limit. The examples
are derandomised (the same ones every run) and few, so the file runs in a few seconds.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any, cast

import pytest
import zenoh
from hypothesis import given, settings
from hypothesis import strategies as st

from biris_hw.io.net import Service, serve
from biris_hw.io.net import service as service_module
from biris_hw.io.net.keys import MAX_REQUEST, OPS, Keys
from biris_hw.io.net.zconfig import make_config
from tests.conftest import until
from tests.net_helpers import FakeConnection, FakeSensor, endpoint, free_port, warm_up_zenoh

if TYPE_CHECKING:
    from biris_hw.sensor import Sensor

KEYS = Keys("fz")
CONTROLLERS = {"op": "s3cret"}
REPLIES = frozenset(
    {
        "RequestError",
        "HardwareFault",
        "ConnectionClosed",
        "TimeoutError",
        "AccessDenied",
        "BadRequest",
        "Busy",
        "BirisError",
    }
)
"""The error replies docs/wire-format.md lists, but InternalError (a bug in the service)."""

REAL = ("<normal>", "<data>")
"""Stand-ins for the connection tokens the test opened (filled in per example)."""


class _Connection(FakeConnection):
    """A fake connection with every operation: each recorded, none waiting (a read that would
    wait times out at once), a refusal where the server would refuse."""

    def ready_for_data(self, timeout: float | None = None) -> Any:
        self._record("ready_for_data")
        raise TimeoutError("nothing")

    def request_scan_data(self, direction: Any) -> None:
        self._record("request_scan_data")

    def wait_idle(self, timeout: float | None = None) -> None:
        self._record("wait_idle")

    def single_scan(self, to_deg: float) -> int:
        self._record("single_scan")
        return _counts(to_deg)

    def set_elevation(self, deg: float) -> int:
        self._record("set_elevation")
        return _counts(deg)

    def continuous_scan(self, cw: float, ccw: float) -> tuple[int, int]:
        self._record("continuous_scan")
        return _counts(cw), _counts(ccw)

    def set_motor_params(self, params: Any) -> None:
        self._record("set_motor_params")

    def start_continuous(self) -> None:
        self._record("start_continuous")

    def stop_continuous(self) -> None:
        self._record("stop_continuous")

    def home(self) -> None:
        self._record("home")

    def timeout_enable(self) -> None:
        self._record("timeout_enable")

    def timeout_disable(self) -> None:
        self._record("timeout_disable")


def _counts(deg: float) -> int:
    """As the server does: an angle it cannot place is refused, any other clamped."""
    from biris_hw.errors import RequestError

    if not math.isfinite(deg):
        raise RequestError(f"angle {deg!r} is not a finite number of degrees")
    return round(max(-360.0, min(360.0, deg)) * 4096 / 360)


class _Sensor(FakeSensor):
    """A :class:`FakeSensor` whose clients' connections are :class:`_Connection`; the
    service's own feed, opened before :attr:`serving`, keeps the fake's (which wait)."""

    serving = False

    def open(self, kind: Any = None, *, policy: Any = None, depth: int | None = None) -> Any:
        from biris_hw.data import ConnectionKind

        if not self.serving:
            return super().open(kind, policy=policy, depth=depth)
        with self.cond:
            conn = _Connection(self, self._next, kind or ConnectionKind.NORMAL, policy, depth or 8)
            self._next += 1
            self.opened.append(conn)
        return conn


@pytest.fixture(scope="module", autouse=True)
def _zenoh_runtime() -> None:
    warm_up_zenoh()


@pytest.fixture
def served(monkeypatch: pytest.MonkeyPatch) -> Iterator[tuple[Service, zenoh.Session]]:
    """The service (failed authentications not limited, so that requests with the right
    credentials keep getting through) and a raw session on it."""
    monkeypatch.setattr(service_module, "AUTH_FAILURES", 1e9)
    monkeypatch.setattr(service_module, "AUTH_FAILURES_PER_CLIENT", 1e9)
    where = endpoint(free_port())
    sensor = _Sensor()
    with serve(
        cast("Sensor", sensor),
        name="fz",
        listen=[where],
        controllers=CONTROLLERS,
        multicast=False,
    ) as svc:
        sensor.serving = True
        session = zenoh.open(make_config(connect=[where]))
        try:
            until(
                lambda: list(session.liveliness().get(KEYS.service_token, timeout=1.0)),
                what="the raw session sees the service",
            )
            yield svc, session
        finally:
            session.close()  # type: ignore[no-untyped-call]
            sensor.free()


_leaf = (
    st.none()
    | st.booleans()
    | st.integers(min_value=-(2**80), max_value=2**80)
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=24)
)
_json = st.recursive(
    _leaf,
    lambda inner: (
        st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4)
    ),
    max_leaves=12,
)
_ids = st.sampled_from(["fuzz", "fuzz-2", "fuzz_3"])
_client = st.one_of(_ids, _ids, _ids, _leaf)
"""Mostly a client the service knows, so that most requests get past the parser."""
_request = st.fixed_dictionaries(
    {"client": _client},
    optional={
        "conn": st.sampled_from(REAL)
        | st.text(alphabet="AZaz09_-", min_size=16, max_size=30)
        | _leaf,
        "user": st.just("op") | _leaf,
        "password": st.just(CONTROLLERS["op"]) | _leaf,
        "kind": st.sampled_from(["NORMAL", "DATA"]) | _leaf,
        "policy": st.sampled_from(["latest", "every_buffer", "every_acquisition"]) | _leaf,
        "depth": _leaf,
        "timeout": st.sampled_from([0, 0.01, None]) | _leaf,
        "direction": st.sampled_from([0, 1]) | _leaf,
        "to_deg": _leaf,
        "cw_deg": _leaf,
        "ccw_deg": _leaf,
        "deg": _leaf,
        "params": st.dictionaries(
            st.sampled_from(["sample", "zero", "pole", "gain", "max_vel", "max_accel", "x"]),
            _leaf,
        )
        | _json,
        "info": _leaf,
        "counters": _leaf,
        "extra": _json,
    },
)


def _nested(depth: int) -> bytes:
    return b'{"client": "fuzz", "x": ' + b"[" * depth + b"]" * depth + b"}"


_number = st.one_of(st.integers(-400, 400), st.floats(-400.0, 400.0), _leaf)
_wellformed = st.fixed_dictionaries(
    {
        "client": _ids,
        "conn": st.sampled_from(REAL),
        "user": st.just("op"),
        "password": st.just(CONTROLLERS["op"]),
    },
    optional={
        "kind": st.sampled_from(["NORMAL", "DATA"]),
        "policy": st.sampled_from(["latest", "every_buffer", "every_acquisition"]),
        "depth": st.one_of(st.none(), st.integers(-2, 10_000), _leaf),
        "timeout": st.one_of(st.sampled_from([0, 0.01, None, -1]), _leaf),
        "direction": st.one_of(st.sampled_from([0, 1, 2]), _leaf),
        "to_deg": _number,
        "cw_deg": _number,
        "ccw_deg": _number,
        "deg": _number,
        "params": st.dictionaries(
            st.sampled_from(["sample", "zero", "pole", "gain", "max_vel", "max_accel", "x"]),
            st.one_of(st.integers(-10, 70_000), _leaf),
        ),
        "info": st.booleans(),
        "counters": st.booleans(),
    },
)
"""A request as a client would send it (a real connection, the right credentials), its
arguments anything from sensible to nonsense: what gets through to the sensor."""

_payload = st.one_of(
    _wellformed.map(lambda body: ("request", body)),
    _wellformed.map(lambda body: ("request", body)),
    _request.map(lambda body: ("request", body)),
    _json.map(lambda value: ("bytes", json.dumps(value).encode())),
    st.binary(max_size=300).map(lambda raw: ("bytes", raw)),
    st.integers(min_value=1, max_value=5000).map(lambda n: ("bytes", b"[" * n)),
    st.integers(min_value=1, max_value=2000).map(lambda n: ("bytes", _nested(n))),
    st.integers(min_value=MAX_REQUEST - 40, max_value=MAX_REQUEST + 40).map(
        lambda n: ("bytes", b'{"client": "fuzz"}'.ljust(n))
    ),
    st.none().map(lambda _: ("none", b"")),
)


def _live_token(svc: Service, session: zenoh.Session, kind: str, held: dict[str, str]) -> str:
    """A token of an open connection of the kind asked for (opened again if closed)."""
    token = held.get(kind)
    if token is None or token not in svc._conns:
        body = {"client": "fuzz", "kind": "NORMAL" if kind == REAL[0] else "DATA"}
        (reply,) = list(session.get(KEYS.rpc("open"), payload=json.dumps(body).encode()))
        assert reply.ok is not None, reply.err and reply.err.payload.to_bytes()
        token = held[kind] = json.loads(reply.ok.payload.to_bytes())["conn"]
    return token


def test_every_request_on_every_key_is_answered(
    served: tuple[Service, zenoh.Session],
) -> None:
    svc, session = served
    held: dict[str, str] = {}
    asked: dict[str, int] = {}

    @settings(max_examples=300, deadline=None, database=None, derandomize=True)
    @given(op=st.sampled_from(sorted(OPS)), payload=_payload)
    def ask(op: str, payload: tuple[str, Any]) -> None:
        how, value = payload
        if how == "request":
            conn = value.get("conn")
            if conn in REAL:
                value = {**value, "conn": _live_token(svc, session, conn, held)}
            raw = json.dumps(value).encode()
        else:
            raw = value
        options: dict[str, Any] = {} if how == "none" else {"payload": raw}
        replies = list(session.get(KEYS.rpc(op), timeout=10.0, **options))
        assert len(replies) == 1, (op, raw[:200])
        reply = replies[0]
        if reply.err is not None:
            body = json.loads(reply.err.payload.to_bytes())
            assert body["error"] in REPLIES, (op, raw[:200], body)
            kind = str(body["error"])
        else:
            assert reply.ok is not None
            kind = "ok"
        asked[kind] = asked.get(kind, 0) + 1

    ask()
    assert svc.internal_errors == 0
    # the examples reached the sensor, not only the parser
    assert asked.get("ok", 0) > 10 and asked.get("BadRequest", 0) > 10, asked

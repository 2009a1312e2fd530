"""Refused means unchanged (issue 11; docs/api.md, "Numbers, refusals and polls").

Every numeric argument of the client API takes any real number type (numpy's scalars, Fraction),
clamps huge finite values exactly as documented and refuses everything else with a
RequestError that names the argument. After a refusal the server's status (state, axes, counters,
connections) and the true head are exactly as before, and a normal scan is still accepted.
``timeout=0`` polls: answered at once, whatever the server is doing.

One simulated server serves the whole module: it takes longer to start than these tests take to
run. Every test leaves it idle, at rest, with its DATA connection drained and its audit clean.
"""

from __future__ import annotations

import dataclasses
import math
import threading
from collections.abc import Callable, Iterator
from decimal import Decimal
from fractions import Fraction
from typing import Any, cast

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from biris_hw import BirisInitRecord, BirisServer, ConnectionKind, DeliveryPolicy, MotorParams
from biris_hw import protocol as p
from biris_hw.angles import counts_to_deg, deg_to_counts, destination_counts
from biris_hw.client import Connection
from biris_hw.data import Point
from biris_hw.errors import HardwareFault, RequestError
from biris_hw.ipc import Mailbox
from biris_hw.server.connections import Connections
from biris_hw.server.counters import Counters
from regs.hctl1000 import MOTION_LIMIT_COUNTS
from sim import Scene, SimulatedBiris
from tests.conftest import until

WAIT = 5.0
"""Timeout for what should happen almost at once; only reached when a test fails."""

TIME_SCALE = 50.0
"""Fast enough that a 3-degree scan takes under 10 ms, slow enough for a loaded machine."""

SETTLE_S = 0.25
"""Hardware seconds after idle by which the head has rung down inside a count of its
destination."""

SETTLED = 1.0
"""Counts the true head may differ between two readings while it stands still (it does not move
at all in practice: the margin only keeps a float reading's noise from failing the test)."""

WITH_SERVER = settings(
    max_examples=12,
    derandomize=True,  # one run per seed: the shared bench's path is the same every time
    database=None,
    deadline=None,  # real threads and a simulator: a slow example is not a failure
    suppress_health_check=[HealthCheck.function_scoped_fixture],  # the bench is reset per example
)

# -- values no request may take -------------------------------------------------------------------

NOT_FINITE: list[object] = [
    math.nan,
    math.inf,
    -math.inf,
    np.float32("nan"),
    np.float64("-inf"),
    np.float16("inf"),
    np.longdouble("nan"),
]
NOT_NUMBERS: list[object] = [
    None,
    "10",
    b"10",
    True,  # an int to Python; never an angle, a timeout or a depth
    False,
    np.bool_(True),
    10j,
    [10.0],
    (10,),
    np.array(10.0),  # a 0-d array is an array, not a scalar
    np.array([10.0]),
    object(),
    Decimal("10"),  # not a numbers.Real: Decimal("1e999999999") has no exact value in memory
    Decimal("NaN"),
    Decimal("sNaN"),  # compares by raising: must not escape as InvalidOperation
]
HUGE = [10**400, 1e308, np.float64(1e308), np.longdouble("1e4000"), Fraction(10**400, 7)]
"""Finite, and far beyond +-360 degrees: clamped, never an OverflowError."""


# -- one server for the module --------------------------------------------------------------------


@dataclasses.dataclass
class Bench:
    """The module's simulator and server, a NORMAL and a DATA (LATEST) connection."""

    rig: SimulatedBiris
    server: BirisServer
    conn: Connection
    data: Connection

    def snapshot(self) -> tuple[object, ...]:
        """What a refused request must leave exactly as it was."""
        s = self.server.status()
        return (
            s.state,
            s.fault,
            s.azimuth,
            s.elevation,
            s.calibration,
            s.continuous,
            dict(s.counters),
            {ident: (c.queued, c.delivered, c.dropped) for ident, c in s.connections.items()},
        )

    def head(self) -> tuple[float, float]:
        """Where the head truly stands (the simulator's backdoor)."""
        return self.rig.azimuth_counts, self.rig.elevation_counts

    def settled(self) -> tuple[float, float]:
        """Where the head stands once it has settled: idle is the servo's settle band (the
        head within a count or two, still ringing down), so a quarter second of hardware time
        later (virtual time: nothing else moves meanwhile)."""
        self.rig.timebase.sleep(SETTLE_S, what="the head to settle")
        return self.head()

    def drain(self) -> None:
        """Empty the DATA connection's queue, by polling."""
        for _ in range(10):
            try:
                self.data.ready_for_data(timeout=0)
            except TimeoutError:
                return
        pytest.fail("the DATA connection never ran dry")

    def normal_scan(self) -> None:
        """A 3-degree scan towards 0 from where the head is: accepted, done, and delivered."""
        here = self.server.status().azimuth
        dest = here - 34 if here > 0 else here + 34
        assert self.conn.single_scan(counts_to_deg(dest)) == dest
        self.conn.wait_idle(timeout=WAIT)
        assert self.server.status().azimuth == dest
        self.drain()

    def refused(self, request: Callable[[], object], match: str) -> RequestError:
        """``request`` is a RequestError matching ``match``, and nothing changes; a scan still
        works afterwards. Returns the error, for a test to read."""
        before, head = self.snapshot(), self.head()
        with pytest.raises(RequestError, match=match) as info:
            request()
        assert self.snapshot() == before
        assert all(abs(a - b) < SETTLED for a, b in zip(self.head(), head, strict=True))
        self.normal_scan()
        return info.value


def naming(argument: str) -> str:
    """The pattern of a refusal that names ``argument`` (its message starts with the name)."""
    return rf"^{argument}: "


@pytest.fixture(scope="module")
def shared() -> Iterator[Bench]:
    with (
        SimulatedBiris(
            scene=Scene.circle(2.0), time_scale=TIME_SCALE, seed=7, clock="virtual"
        ) as rig,
        BirisServer(rig.hardware, BirisInitRecord()) as server,
    ):
        bench = Bench(rig, server, server.open(), server.open(ConnectionKind.DATA))
        yield bench
        bench.conn.close()
        bench.data.close()


def _recover(shared: Bench) -> str | None:
    """Reset the shared server if it is in a fault; the fault's message, or None. A fault is
    one test's failure: reset here, it is not carried into the rest of the module."""
    fault = shared.server.status().fault
    if fault is None:
        return None
    try:
        shared.conn.wait_idle(timeout=0)  # raises the fault, with the server's own message
    except HardwareFault as exc:
        said = str(exc)
    else:  # pragma: no cover - a fault state always refuses
        said = str(fault)
    shared.conn.reset()
    shared.conn.wait_idle(timeout=WAIT)
    shared.drain()
    return said


@pytest.fixture
def bench(shared: Bench) -> Iterator[Bench]:
    """The shared bench, idle and drained before the test; idle and clean after it. A test
    that leaves the server in a fault fails with it, and the server is reset for the next."""
    _recover(shared)  # a test that errored before its teardown could check
    shared.conn.wait_idle(timeout=WAIT)
    shared.drain()
    yield shared
    left = _recover(shared)
    assert left is None, f"the test left the shared server in a fault: {left}"
    shared.conn.stop_scan()
    shared.conn.wait_idle(timeout=WAIT)
    shared.drain()
    assert shared.rig.audit.violations == []


# -- refused: bad numbers and non-numbers, every call ---------------------------------------------

ANGLE_CALLS: dict[str, Callable[[Bench, Any], object]] = {
    "to_deg": lambda b, v: b.conn.single_scan(v),
    "cw_deg": lambda b, v: b.conn.continuous_scan(v, 20.0),
    "ccw_deg": lambda b, v: b.conn.continuous_scan(-20.0, v),
    "deg": lambda b, v: b.conn.set_elevation(v),
}
TIMEOUT_CALLS: dict[str, Callable[[Bench, Any], object]] = {
    "wait_idle": lambda b, v: b.conn.wait_idle(timeout=v),
    "ready_for_data": lambda b, v: b.data.ready_for_data(timeout=v),
}


@pytest.mark.parametrize("named", ANGLE_CALLS)
def test_an_angle_that_is_not_a_finite_real_number_changes_nothing(
    bench: Bench, named: str
) -> None:
    call = ANGLE_CALLS[named]
    for value in NOT_FINITE + NOT_NUMBERS:
        bench.refused(lambda: call(bench, value), naming(named))  # noqa: B023  (called at once)


@pytest.mark.parametrize("call", TIMEOUT_CALLS)
def test_a_timeout_that_is_not_a_number_changes_nothing(bench: Bench, call: str) -> None:
    request = TIMEOUT_CALLS[call]

    def no_deadline(v: object) -> bool:  # valid: None and +inf wait as long as it takes
        return v is None or (isinstance(v, (float, np.floating)) and bool(v == math.inf))

    bad = [v for v in NOT_FINITE + NOT_NUMBERS if not no_deadline(v)]
    for value in bad:
        bench.refused(lambda: request(bench, value), naming("timeout"))  # noqa: B023


def _negative_numbers() -> st.SearchStrategy[object]:
    floats = st.floats(max_value=-1e-300, allow_nan=False)  # -inf included
    return st.one_of(
        floats,
        # float32 rounds tiny negatives to -0.0, which is a poll, not a negative timeout
        floats.filter(lambda x: x >= -3e38).map(np.float32).filter(lambda v: bool(v < 0)),
        floats.map(np.float64),
        st.integers(max_value=-1),
        st.sampled_from([-(10**400), np.int64(-1), np.int8(-128), Fraction(-1, 10**400)]),
        st.fractions(max_value=Fraction(-1, 10**9)),
    )


@WITH_SERVER
@given(call=st.sampled_from(sorted(TIMEOUT_CALLS)), value=_negative_numbers())
def test_a_negative_timeout_of_any_type_is_refused_and_changes_nothing(
    bench: Bench, call: str, value: object
) -> None:
    error = bench.refused(lambda: TIMEOUT_CALLS[call](bench, value), naming("timeout"))
    assert "0 (poll)" in str(error)  # it says what is allowed instead


@pytest.mark.parametrize(
    "depth", [0, -1, 2**16 + 1, 10**400, 1.5, np.float64(2.0), "2", True, Fraction(2), [2]]
)
def test_a_bad_depth_opens_nothing(bench: Bench, depth: object) -> None:
    def request() -> object:
        bad: Any = depth
        return bench.server.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_BUFFER, depth=bad)

    bench.refused(request, naming("depth"))


@pytest.mark.parametrize("params", [None, {"gain": 0x3F}, (0xAF, 0x7F), MotorParams().to_dict()])
def test_motor_params_that_are_not_motor_params_change_nothing(
    bench: Bench, params: object
) -> None:
    bench.refused(lambda: bench.conn.set_motor_params(params), naming("params"))  # type: ignore[arg-type]


# -- parameters that can never move the head ------------------------------------------------------


@pytest.mark.parametrize(
    ("field", "why"),
    [("gain", "no torque"), ("max_vel", "never leaves its start"), ("max_accel", "never speeds")],
)
def test_a_motor_that_can_never_move_the_head_is_refused_before_anything_is_sent(
    bench: Bench, field: str, why: str
) -> None:
    for zero in (0, np.int64(0), np.uint8(0)):
        error = bench.refused(lambda: MotorParams(**{field: zero}), naming(field))  # noqa: B023
        assert why in str(error) and "can never move" in str(error)
    with pytest.raises(RequestError, match=naming(field) + "0 "):
        dataclasses.replace(MotorParams(), **{field: 0})  # replace() validates again
    with pytest.raises(RequestError, match=naming(f"motor.{field}") + "0 "):
        BirisInitRecord.from_toml(f"[motor]\n{field} = 0\n")
    with pytest.raises(RequestError, match=naming(f"elevation_motor.{field}") + "0 "):
        BirisInitRecord.from_dict({"elevation_motor": {field: 0}})


def test_the_slowest_motor_that_moves_is_accepted(bench: Bench) -> None:
    bench.conn.set_motor_params(MotorParams(max_vel=1))
    bench.conn.wait_idle(timeout=WAIT)
    bench.normal_scan()
    bench.conn.set_motor_params(MotorParams())
    bench.conn.wait_idle(timeout=WAIT)


def test_the_protocol_refuses_a_malformed_message_in_the_senders_thread() -> None:
    for bad in (2.5, np.float64(3.0), "7", None, True):
        with pytest.raises(RequestError, match=naming("destination")):
            p.SingleScanRqst(1, bad)  # type: ignore[arg-type]
        with pytest.raises(RequestError, match=naming("destination")):
            p.SetElevation(1, bad)  # type: ignore[arg-type]
        with pytest.raises(RequestError, match=naming("ccw_limit")):
            p.ContScanRqst(1, -10, bad)  # type: ignore[arg-type]
    message = p.SingleScanRqst(1, np.int64(10**6))
    assert message.destination == 10**6 and type(message.destination) is int  # clamped later
    for flag in (1, 0, None, "yes", np.bool_(True)):
        with pytest.raises(RequestError, match=naming("poll")):
            p.WaitIdle(1, poll=flag)  # type: ignore[arg-type]
        with pytest.raises(RequestError, match=naming("poll")):
            p.ReadyForData(1, poll=flag)  # type: ignore[arg-type]
    with pytest.raises(RequestError, match=naming("params")):
        p.BirisMotorParams(1, {"gain": 1})  # type: ignore[arg-type]


# -- accepted: any real number type, and huge values clamp ----------------------------------------


def _exact(value: object) -> Fraction:
    """The test's own exact value of a number: what the API must round, whatever its type."""
    if isinstance(value, (int, np.integer)):
        return Fraction(int(value))
    numerator, denominator = value.as_integer_ratio()  # type: ignore[attr-defined]
    return Fraction(numerator, denominator)


INT_TYPES: list[Callable[[int], object]] = [int, np.int8, np.int16, np.int64, np.uint16]
REAL_TYPES: list[Callable[[float], object]] = [
    float,
    np.float16,
    np.float32,
    np.float64,
    np.longdouble,
    Fraction,
]


@st.composite
def typed_angles(draw: st.DrawFn, lo: int, hi: int) -> object:
    """An angle in lo..hi degrees as any of the numeric types a caller might have."""
    if draw(st.booleans()):
        make_int = draw(st.sampled_from(INT_TYPES))
        return make_int(draw(st.integers(max(lo, 0) if make_int is np.uint16 else lo, hi)))
    make_real = draw(st.sampled_from(REAL_TYPES))
    return make_real(draw(st.floats(lo, hi)))


@WITH_SERVER
@given(to_deg=typed_angles(-40, 40))
def test_a_scan_destination_of_any_real_type_is_used_exactly(bench: Bench, to_deg: object) -> None:
    expected = round(_exact(to_deg) * 4096 / 360)
    here = bench.server.status().azimuth
    assume(expected != here)  # else "already there", rightly
    assert bench.conn.single_scan(to_deg) == expected  # type: ignore[arg-type]
    bench.conn.wait_idle(timeout=WAIT)
    assert bench.server.status().azimuth == expected
    assert abs(bench.settled()[0] - expected) < 2  # the true head followed
    scan = bench.data.ready_for_data(timeout=0)  # the scan waits: a poll hands it over
    assert scan.direction.sign == (1 if expected > here else -1)


@WITH_SERVER
@given(deg=typed_angles(-40, 40))
def test_an_elevation_of_any_real_type_is_used_exactly(bench: Bench, deg: object) -> None:
    expected = round(_exact(deg) * 4096 / 360)  # within the record's +-512 counts
    assert bench.conn.set_elevation(deg) == expected  # type: ignore[arg-type]
    bench.conn.wait_idle(timeout=WAIT)
    assert bench.server.status().elevation == expected
    assert abs(bench.settled()[1] - expected) < 2


def test_continuous_limits_of_numpy_types(bench: Bench) -> None:
    used = bench.conn.continuous_scan(np.float32(-10.5), np.int64(10))
    assert used == (deg_to_counts(-10.5), deg_to_counts(10)) == (-119, 114)
    assert all(type(limit) is int for limit in used)
    with pytest.raises(TimeoutError, match="not idle"):  # scanning: a poll says so at once
        bench.conn.wait_idle(timeout=np.float64(0))
    bench.conn.stop_scan()
    bench.conn.wait_idle(timeout=np.float32(WAIT))


def test_huge_angles_clamp_to_one_revolution_and_move_nothing_further(bench: Bench) -> None:
    for sign in (1, -1):
        limit = sign * MOTION_LIMIT_COUNTS
        first, *rest = (sign * v for v in HUGE)
        assert bench.conn.single_scan(first) == limit
        bench.conn.wait_idle(timeout=WAIT)
        assert abs(bench.rig.azimuth_counts - limit) < 4  # within the filter's overshoot
        bench.drain()
        for value in rest:  # the same clamped destination: "already there", nothing moves
            already = rf"already at {limit} counts"
            bench.refused(lambda: bench.conn.single_scan(value), already)  # noqa: B023
            assert bench.conn.single_scan(value) == limit  # back from the 3-degree scan
            bench.conn.wait_idle(timeout=WAIT)
            bench.drain()
    bench.conn.home()
    bench.conn.wait_idle(timeout=WAIT)


def test_huge_scan_limits_clamp_and_the_wrong_way_round_is_refused(bench: Bench) -> None:
    wrong_way = rf"CW limit \({MOTION_LIMIT_COUNTS} counts\).*\({-MOTION_LIMIT_COUNTS}\)"
    bench.refused(lambda: bench.conn.continuous_scan(1e12, -(10**400)), wrong_way)
    limits = bench.conn.continuous_scan(-(10**400), np.longdouble("1e4000"))
    assert limits == (-MOTION_LIMIT_COUNTS, MOTION_LIMIT_COUNTS)
    bench.conn.stop_scan()  # after the first sweep, to the CW limit
    bench.conn.wait_idle(timeout=WAIT)
    assert bench.server.status().azimuth == -MOTION_LIMIT_COUNTS
    bench.conn.home()
    bench.conn.wait_idle(timeout=WAIT)


def test_huge_elevations_clamp_to_the_records_limits(bench: Bench) -> None:
    lo, hi = BirisInitRecord().elevation_limits_counts
    for value, expected in ((10**400, hi), (-1e308, lo), (np.longdouble("-1e4000"), lo)):
        assert bench.conn.set_elevation(value) == expected
        bench.conn.wait_idle(timeout=WAIT)
        assert abs(bench.settled()[1] - expected) < 2
    bench.conn.set_elevation(0)


@pytest.mark.parametrize("timeout", [math.inf, 10**400, 1e308, np.longdouble("1e4000"), 1e10])
def test_a_timeout_beyond_any_lock_waits_as_long_as_it_takes(bench: Bench, timeout: object) -> None:
    bench.conn.wait_idle(timeout=timeout)  # type: ignore[arg-type]  # idle: at once, no Overflow
    bench.conn.single_scan(-3.0 if bench.server.status().azimuth > 0 else 3.0)
    bench.conn.wait_idle(timeout=timeout)  # type: ignore[arg-type]
    assert bench.data.ready_for_data(timeout=timeout) is not None  # type: ignore[arg-type]


def test_an_open_depth_of_any_integer_type(bench: Bench) -> None:
    for depth in (np.int64(4), np.uint8(4), 4):
        size: Any = depth  # the annotation says int; any integer type is accepted
        with bench.server.open(
            ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_BUFFER, depth=size
        ) as queue:
            assert queue.depth == 4 and type(queue.depth) is int


@settings(max_examples=300)
@given(
    deg=st.one_of(
        st.floats(allow_nan=False, allow_infinity=False),
        st.integers(),
        st.sampled_from(HUGE),
        st.sampled_from(HUGE).map(lambda v: -v),
        st.fractions(),
        st.floats(-1e4, 1e4).map(np.float32),
        st.floats(-1e300, 1e300).map(np.longdouble),
    )
)
def test_every_finite_angle_converts_exactly_and_clamps(deg: object) -> None:
    exact = _exact(deg)
    unclamped = round(exact * 4096 / 360)
    assert deg_to_counts(deg) == unclamped  # type: ignore[arg-type]  # never an OverflowError
    clamped = destination_counts(deg, "to_deg")
    assert clamped == max(-MOTION_LIMIT_COUNTS, min(MOTION_LIMIT_COUNTS, unclamped))
    assert type(clamped) is int


@given(a=st.floats(-1e300, 1e300), b=st.floats(-1e300, 1e300))
def test_the_conversion_keeps_the_order_of_angles(a: float, b: float) -> None:
    lo, hi = sorted((a, b))
    assert deg_to_counts(lo) <= deg_to_counts(hi)
    assert destination_counts(lo, "x") <= destination_counts(hi, "x")


@given(
    value=st.one_of(
        st.floats(0.001, 1e6).map(np.float32),
        st.floats(0.001, 1e6),
        st.integers(1, 10**6).map(np.int64),
        st.fractions(Fraction(1, 1000), 10**6),
    )
)
def test_record_numbers_of_any_real_type_become_plain_floats(value: object) -> None:
    record = BirisInitRecord(timeout_s=value, head_height_m=value)  # type: ignore[arg-type]
    assert record.timeout_s == float(_exact(value)) and type(record.timeout_s) is float
    assert record.head_height_m == record.timeout_s
    assert BirisInitRecord.from_dict(record.to_dict()) == record


# -- timeout=0 polls ------------------------------------------------------------------------------


@pytest.mark.parametrize("zero", [0, 0.0, -0.0, np.float32(0), np.int64(0), Fraction(0)])
def test_polls_answer_at_once(bench: Bench, zero: object) -> None:
    bench.conn.wait_idle(timeout=zero)  # type: ignore[arg-type]  # idle
    with pytest.raises(TimeoutError, match="no data waiting"):
        bench.data.ready_for_data(timeout=zero)  # type: ignore[arg-type]  # drained
    bench.conn.single_scan(-3.0 if bench.server.status().azimuth > 0 else 3.0)
    bench.conn.wait_idle(timeout=WAIT)
    scan = bench.data.ready_for_data(timeout=zero)  # type: ignore[arg-type]  # one waits
    assert scan.t_delivered is not None
    with pytest.raises(TimeoutError):
        bench.data.ready_for_data(timeout=zero)  # type: ignore[arg-type]  # and is gone
    bench.conn.continuous_scan(-5.0, 5.0)
    with pytest.raises(TimeoutError, match="the server is not idle"):
        bench.conn.wait_idle(timeout=zero)  # type: ignore[arg-type]


def _point(acq: int) -> Point:
    profile = np.zeros(4, np.int16)
    return Point(0, 1000, profile, profile, float(acq), acq, 1)


def test_a_poll_hands_over_what_waits_and_never_parks() -> None:
    clients = Connections(lambda: 1.0, Counters())
    inbox = Mailbox("admin")
    owner = threading.current_thread()
    conn = clients.open(ConnectionKind.DATA, DeliveryPolicy.EVERY_ACQUISITION, None, owner)

    def ready(poll: bool) -> Any:
        ticket = inbox.post(p.ReadyForData(conn.ident, poll=poll))
        clients.ready(inbox.receive(timeout=0), conn, poll=poll)
        return ticket

    polled = ready(poll=True)
    assert polled.done and conn.waiting is None  # answered, not parked
    with pytest.raises(TimeoutError, match=f"no data waiting for connection {conn.ident}"):
        polled.wait(0)
    clients.deliver_points([_point(0), _point(1)], lost=0)
    first, _ = ready(poll=True).wait(0)
    assert first.acq == 0 and first.t_delivered == 1.0
    assert conn.delivered == 1 and len(conn.queue) == 1


def test_a_poll_that_finds_nothing_leaves_a_parked_request_alone() -> None:
    clients = Connections(lambda: 1.0, Counters())
    inbox = Mailbox("admin")
    conn = clients.open(
        ConnectionKind.DATA, DeliveryPolicy.EVERY_ACQUISITION, None, threading.current_thread()
    )
    parked = inbox.post(p.ReadyForData(conn.ident))
    clients.ready(inbox.receive(timeout=0), conn)
    assert not parked.done
    polled = inbox.post(p.ReadyForData(conn.ident, poll=True))
    clients.ready(inbox.receive(timeout=0), conn, poll=True)
    with pytest.raises(TimeoutError):
        polled.wait(0)
    assert not parked.done  # not superseded: the poll asked for nothing to change
    clients.deliver_points([_point(7)], lost=0)
    point, dropped = cast(tuple[Point, int], parked.wait(0))
    assert point.acq == 7 and dropped == 0


def test_a_fault_on_the_shared_server_is_reset_not_carried_on(shared: Bench) -> None:
    """The module's tests share one server: a fault one of them leaves is reported in that
    test (the bench's teardown) and reset there, so the next test starts from an idle server
    instead of failing on the same fault."""
    shared.conn.wait_idle(timeout=WAIT)
    shared.rig.faults.parity_error()
    until(lambda: shared.server.status().fault is not None, WAIT)
    said = _recover(shared)
    assert said is not None and "parity" in said
    assert shared.server.status().fault is None
    assert _recover(shared) is None  # nothing to do on a healthy server
    shared.rig.faults.clear_all()
    shared.normal_scan()

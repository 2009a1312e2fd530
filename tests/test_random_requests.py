"""Random request sequences (issue 11): a hypothesis state machine drives one server with every
client request and injected faults, and checks after every step that nothing unsafe or
self-contradictory happened.

Requests: single_scan, continuous_scan, stop_scan, home, set_motor_params (sane, and wild but
valid), set_elevation, wait_idle, reset, and fault injections (parity, bus, locked shaft, dead
amplifier, hung BIRIS) each followed by ``clear_all()`` + ``reset()``. Angles include the
extremes (+-1e6 degrees, +-360, +-720, fractions of a count) and numpy number types.

Invariants, after every step:

* the TRUE head never leaves +-0x1000 counts (plus the filter's overshoot allowance the audit
  uses) and never touches a mechanical stop; the simulator's HEAD_BEYOND_LIMIT audit watches it
  between steps too;
* the audit stays clean;
* status never contradicts itself: idle iff ``wait_idle(timeout=0)`` returns, a fault state
  iff requests raise HardwareFault (of that kind), the accounts' second identity holds, and an
  idle head stands where status says, counted from true zero;
* after stop_scan + wait_idle a scan is always accepted.

Runs are derandomized (a fixed hypothesis seed, no database), every simulator is seeded and runs
on virtual time (issue 22), so a run is the same run on any host under any load: the same
sequences, each step at the same hardware instant. The whole machine is slow, with a tiny fast
variant.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, Phase, settings
from hypothesis import strategies as st
from hypothesis.errors import Flaky
from hypothesis.stateful import (
    RuleBasedStateMachine,
    initialize,
    invariant,
    rule,
    run_state_machine_as_test,
)

from biris_hw import BirisInitRecord, MotorParams
from biris_hw.errors import HardwareFault, RequestError
from biris_hw.server import BirisServer
from biris_hw.server.motion import ARRIVAL_TOLERANCE_COUNTS
from regs.hctl1000 import COUNTS_PER_REV
from sim.audit import Rule
from sim.hctl1000 import HEAD_OVERSHOOT_COUNTS
from sim.rig import SimulatedBiris
from sim.scene import Scene
from tests.conftest import until

TIME_SCALE = 30.0
LONG = 5.0
"""A caller's timeout for a wait that should end (read at the rig's nominal x30: 150 s of
hardware time). The slowest profile the rules can draw (sample timer FFH, max_vel 1: 490
counts/s) crosses the whole +-4096 range in 17 s; the longest such wait seen takes 6 s. On
virtual time no host is late, so that margin is enough, and a wait that cannot end (wait_idle
during a continuous scan) costs the CPU 150 simulated seconds, not 900."""

HEAD_LIMIT = COUNTS_PER_REV + HEAD_OVERSHOOT_COUNTS
"""How far from true zero the true head may ever stand (counts)."""

ANGLES = st.one_of(
    st.floats(-400.0, 400.0, allow_nan=False),
    st.sampled_from([1e6, -1e6, 360.0, -360.0, 360.01, -359.99, 720.0, -720.0, 0.0, 90.0, -90.0]),
    st.floats(-0.2, 0.2, allow_nan=False),
    st.integers(-1000, 1000),
    st.builds(np.float32, st.floats(-400.0, 400.0, width=32)),
    st.builds(np.int64, st.integers(-720, 720)),
)

SANE_PARAMS = st.builds(
    MotorParams,
    sample=st.sampled_from([0xAF, 0x7F, 0xFF]),
    gain=st.sampled_from([0x3F, 0x30, 0x50]),
    max_vel=st.sampled_from([1, 2, 3, 4]),
    max_accel=st.sampled_from([0x3322, 0x1000, 0x6000]),
)
WILD_PARAMS = st.builds(
    MotorParams,
    sample=st.integers(0, 0xFF),
    zero=st.integers(0, 0xFF),
    pole=st.integers(0, 0xFF),
    gain=st.integers(1, 0xFF),
    max_vel=st.integers(1, 0x7F),
    max_accel=st.integers(1, 0x7FFF),
)
"""Valid, however odd: every field within its register and none that can never move the head
(those are a RequestError up front, tested in test_request_validation.py)."""

FAULTS = ("parity", "bus", "stall", "dead_amplifier", "hang")
SPONTANEOUS = ("parity", "bus")
"""Faults the coupler reports on its own; the others show only when the broken part is used."""


class RandomRequests(RuleBasedStateMachine):
    """One simulator and one server per example, driven by one client."""

    def __init__(self) -> None:
        super().__init__()
        self.rig: SimulatedBiris | None = None
        self.server: BirisServer | None = None
        self.faulted: str | None = None
        """The fault kind a request raised (the server must say so) until recovered."""
        self.trace: list[str] = []
        """Every step so far and what it got: the report of a failure."""
        self.injected: str | None = None
        """The fault injected and not yet cleared."""
        self.own_params = False
        """Motor parameters of the client's own are loaded (since the last reset): a filter or
        a profile the head cannot follow is then a motor_stall of its own making."""

    # -- set-up and tear-down -----------------------------------------------------------------
    @initialize(
        seed=st.integers(0, 2**16),
        start=st.one_of(st.sampled_from([-2000.0, 0.0, 2000.0]), st.floats(-2000.0, 2000.0)),
        ring=st.booleans(),
    )
    def start(self, seed: int, start: float, ring: bool) -> None:
        """A freshly powered head, anywhere the operator's precondition allows (within +-180
        degrees of true zero; a head left wound round is found by the pan journal, tested in
        test_position_integrity.py and test_process_kill.py)."""
        self.rig = SimulatedBiris(
            scene=Scene.circle(2.0),
            time_scale=TIME_SCALE,
            clock="virtual",
            seed=seed,
            initial_azimuth_counts=start,
        ).start()
        try:
            self.server = BirisServer(
                self.rig.hardware, BirisInitRecord(continuous_acquisition=ring)
            )
        except BaseException:
            self.rig.close()
            raise
        self.conn = self.server.open()
        self.trace.append(f"start(seed={seed}, head at {start!r} counts, ring={ring})")

    def teardown(self) -> None:
        if self.server is not None:
            self.server.close()
        if self.rig is not None:
            self.rig.close()

    @property
    def s(self) -> BirisServer:
        assert self.server is not None
        return self.server

    @property
    def r(self) -> SimulatedBiris:
        assert self.rig is not None
        return self.rig

    # -- one request ----------------------------------------------------------------------------
    def _do(self, call: Callable[[], Any], what: str) -> Any:
        """Make a request; a refusal is fine, a fault is noted, anything else fails the test."""
        self._recover()
        try:
            got = call()
        except (RequestError, TimeoutError) as refused:
            self.trace.append(f"{what}: {type(refused).__name__}: {refused}")
            return None
        except HardwareFault as fault:
            self.trace.append(f"{what}: HardwareFault({fault.kind}: {fault.message})")
            self._note_fault(fault.kind)
            return None
        self.trace.append(f"{what}: {got!r}")
        return got

    def _note_fault(self, kind: str) -> None:
        """A fault is reported: it must have a cause (an injection, or parameters of the
        client's own for a motor stall); the next step recovers from it."""
        self.faulted = kind
        with self._checking("a fault with a cause"):
            explained = self.injected is not None or (kind == "motor_stall" and self.own_params)
            assert explained, f"HardwareFault({kind}) with no fault injected"

    @contextlib.contextmanager
    def _checking(self, what: str) -> Iterator[None]:
        """Record a failing check with the steps that led to it (a run that hypothesis cannot
        replay -- threads -- is reported as flaky, and this is then the failure shown)."""
        try:
            yield
        except BaseException as exc:
            FAILURES.append(
                f"{what} failed: {type(exc).__name__}: {exc}\nafter:\n  " + "\n  ".join(self.trace)
            )
            raise

    def _recover(self) -> None:
        """After the invariants have seen a fault: clear the panel and reset."""
        if self.faulted is None:
            return
        self.r.faults.clear_all()
        self.injected = None
        with self._checking("recovery: clear_all + reset"):
            self.conn.reset()  # the documented way back: it must work at the first attempt
            self.trace.append("clear_all + reset: ok")
        self.faulted = None
        self.own_params = False  # a reset loads the record's

    # -- rules ------------------------------------------------------------------------------------
    @rule(to=ANGLES)
    def single_scan(self, to: Any) -> None:
        self._do(lambda: self.conn.single_scan(to), f"single_scan({to!r})")

    @rule(a=ANGLES, b=ANGLES)
    def continuous_scan(self, a: Any, b: Any) -> None:
        cw, ccw = min(a, b), max(a, b)
        self._do(lambda: self.conn.continuous_scan(cw, ccw), f"continuous_scan({cw!r}, {ccw!r})")

    @rule()
    def stop_scan(self) -> None:
        self._do(self.conn.stop_scan, "stop_scan()")

    @rule()
    def home(self) -> None:
        self._do(self.conn.home, "home()")

    @rule(params=st.one_of(SANE_PARAMS, WILD_PARAMS))
    def set_motor_params(self, params: MotorParams) -> None:
        self._recover()  # first: the recovery's reset loads the record's parameters
        self.own_params = True  # (a refused set changes nothing, but the flag only excuses)
        self._do(lambda: self.conn.set_motor_params(params), f"set_motor_params({params})")

    @rule(deg=st.one_of(st.floats(-60.0, 60.0), st.sampled_from([1e6, -1e6, 0.01])))
    def set_elevation(self, deg: float) -> None:
        self._do(lambda: self.conn.set_elevation(deg), f"set_elevation({deg!r})")

    @rule(timeout=st.sampled_from([0, 0.05, 0.5, LONG]))
    def wait_idle(self, timeout: float) -> None:
        self._do(lambda: self.conn.wait_idle(timeout=timeout), f"wait_idle({timeout})")

    @rule()
    def reset(self) -> None:
        self._do(self.conn.reset, "reset()")
        if self.faulted is None:
            self.own_params = False  # a reset loads the record's

    @rule(to=st.sampled_from([-360.0, -90.0, -10.0, 10.0, 90.0, 360.0]))
    def stop_wait_then_scan(self, to: float) -> None:
        """After STOP and wait_idle a scan is always accepted (unless a fault intervened)."""
        self._do(self.conn.stop_scan, "stop_scan()")
        self._do(lambda: self.conn.wait_idle(timeout=LONG), f"wait_idle({LONG})")
        if self.faulted is not None:
            return
        with self._checking("a scan after stop + wait_idle"):
            here = self.s.status().azimuth
            if abs(here - round(to / 360.0 * COUNTS_PER_REV)) < 2:
                to = -to  # "already there" is a refusal of its own; ask for somewhere else
            try:
                got = self.conn.single_scan(to)
                self.trace.append(f"single_scan({to}) after stop + wait_idle: {got}")
            except HardwareFault as fault:
                self.trace.append(f"single_scan({to}): HardwareFault({fault.kind})")
                self._note_fault(fault.kind)
            except RequestError as refused:
                pytest.fail(f"a scan was refused after stop + wait_idle: {refused}")

    @rule(fault=st.sampled_from(FAULTS), to=st.sampled_from([-45.0, 45.0, 120.0]))
    def inject_fault(self, fault: str, to: float) -> None:
        """Break something; make the server notice (a request that needs the broken part);
        the next step (after the invariants) clears the panel and resets."""
        self._recover()
        panel = self.r.faults
        self.trace.append(f"inject {fault}")
        self.injected = fault
        {
            "parity": panel.parity_error,
            "bus": panel.bus_error,
            "stall": panel.stall_motor,
            "dead_amplifier": panel.dead_amplifier,
            "hang": panel.hang_supervisor,
        }[fault]()
        if fault in SPONTANEOUS:  # the coupler interrupts: the server notices on its own
            until(lambda: self.s.status().fault is not None, what=f"{fault} to be noticed")
        else:
            self._do(lambda: self.conn.single_scan(to), f"single_scan({to})")
        self._do(lambda: self.conn.wait_idle(timeout=LONG), f"wait_idle({LONG})")
        with self._checking(f"{fault} noticed"):
            if self.faulted is None and fault not in SPONTANEOUS:
                # the scan was refused (one in progress), and the one in progress may have
                # needed nothing more of the broken part (BIRIS done, the head settling): a
                # scan of its own now uses it
                self._do(self.conn.stop_scan, "stop_scan()")
                self._do(lambda: self.conn.wait_idle(timeout=LONG), f"wait_idle({LONG})")
                if self.faulted is None:
                    here = self.s.status().azimuth
                    if abs(here - round(to / 360.0 * COUNTS_PER_REV)) < 2:
                        to = -to  # "already there" is a refusal of its own
                    self._do(lambda: self.conn.single_scan(to), f"single_scan({to})")
                    self._do(lambda: self.conn.wait_idle(timeout=LONG), f"wait_idle({LONG})")
            assert self.faulted is not None, f"{fault} went unnoticed"

    @rule()
    def status(self) -> None:
        st = self.s.status()
        self.trace.append(f"status(): {st} {st.accounts()}")

    # -- invariants -------------------------------------------------------------------------------
    @invariant()
    def the_true_head_stays_within_the_envelope(self) -> None:
        if self.rig is None:
            return
        with self._checking("the head's envelope"):
            assert abs(self.r.azimuth_counts) <= HEAD_LIMIT, self.r.azimuth_counts
            assert self.r.board.plants[0].stop_hits == 0, "the head struck a mechanical stop"
            beyond = [v for v in self.r.audit.violations if v.rule is Rule.HEAD_BEYOND_LIMIT]
            assert beyond == [], beyond

    @invariant()
    def the_audit_stays_clean(self) -> None:
        if self.rig is None:
            return
        with self._checking("the audit"):
            assert self.r.audit.violations == []

    @invariant()
    def status_never_contradicts_itself(self) -> None:
        if self.server is None:
            return
        with self._checking("status"):
            self._check_status()

    def _check_status(self) -> None:
        before = self.s.status()
        try:
            self.conn.wait_idle(timeout=0)
            polled: str | None = "idle"
        except TimeoutError:
            polled = "busy"
        except HardwareFault as fault:
            polled = f"fault:{fault.kind}"
        except RequestError:
            polled = None  # initialising: a reset under way cannot be polled
        after = self.s.status()
        # nothing starts by itself: idle stays idle, a fault stays until a reset
        if before["state"] == "idle":
            assert polled == "idle", (before, polled)
        if polled == "idle":
            assert after["state"] == "idle", (polled, after)
        if polled == "busy":
            assert not before["state"].startswith("fault") and before["state"] != "idle", before
        if before["state"].startswith("fault"):
            assert polled == before["state"], (before, polled)
        if polled is not None and polled.startswith("fault"):
            assert after["state"] == polled, (polled, after)
            assert self.faulted in (None, polled.removeprefix("fault:"))
            with pytest.raises(HardwareFault) as again:
                self.conn.request_point()
            assert f"fault:{again.value.kind}" == polled
            if self.faulted is None:  # a fault no request has raised yet: recover next step
                self.trace.append(f"status: HardwareFault({again.value.kind})")
                self._note_fault(again.value.kind)
        if self.faulted is not None:
            assert after["state"] == f"fault:{self.faulted}", (self.faulted, after)
        accounts = after.accounts()
        assert accounts.adds_up, f"{after}: {accounts}"
        if after["state"] == "idle":
            # an idle head stands where the server last sent it, counted from TRUE zero
            true = self.r.azimuth_counts
            assert abs(true - after.azimuth) <= ARRIVAL_TOLERANCE_COUNTS, (true, after)


FAILURES: list[str] = []
"""The first failing check of a run, with its steps (see RandomRequests._checking)."""


def _run(max_examples: int, steps: int) -> None:
    FAILURES.clear()
    try:
        _run_machine(max_examples, steps)
    except Flaky as flaky:
        # threads make a run impossible to replay exactly; the failure that made it flaky is
        # the one to report
        if FAILURES:
            pytest.fail(FAILURES[0] + f"\n(hypothesis then: {type(flaky).__name__})")
        raise


def _run_machine(max_examples: int, steps: int) -> None:
    with _no_local_constants():
        run_state_machine_as_test(
            RandomRequests,
            settings=settings(
                max_examples=max_examples,
                stateful_step_count=steps,
                derandomize=True,
                database=None,
                deadline=None,
                phases=[Phase.explicit, Phase.generate],  # no shrinking: threads make it flaky
                suppress_health_check=list(HealthCheck),
                print_blob=False,
            ),
        )


@contextlib.contextmanager
def _no_local_constants() -> Iterator[None]:
    """Draw no "local constants": hypothesis (6.131 on) mixes in literals it harvests from every
    module of this checkout loaded so far, so a derandomized run draws other sequences when
    other test modules are collected with this one (its slow tier drew sequences ten times
    longer to run than this file alone did). Without them the sequences are a function of this
    file alone, and on virtual time a run is one run."""
    try:
        from hypothesis.internal.conjecture import providers
        from hypothesis.internal.constants_ast import Constants
    except ImportError:  # a hypothesis before local constants: nothing to turn off
        yield
        return
    if not hasattr(providers, "_get_local_constants"):
        yield
        return
    original = providers._get_local_constants
    providers._get_local_constants = Constants  # an empty set of constants
    providers.CONSTANTS_CACHE.cache.clear()  # pools built from the harvest so far
    try:
        yield
    finally:
        providers._get_local_constants = original
        providers.CONSTANTS_CACHE.cache.clear()


@pytest.mark.slow
@pytest.mark.timeout(600)  # 15 sequences of 40 steps: about 60 s on an idle host on virtual time
# (CPU-bound: a loaded host takes longer, and a run is still the same run)
@pytest.mark.audit_violations_expected  # asserted by the machine's own invariant instead
def test_random_request_sequences_are_safe_and_consistent() -> None:
    _run(max_examples=15, steps=40)


def test_a_short_request_sequence_keeps_every_invariant() -> None:
    """The fast tier's variant: one fixed sequence through the same rules and invariants
    (hypothesis's first derandomized examples are the trivial ones)."""
    machine = RandomRequests()
    steps: list[Callable[[], None]] = [
        lambda: machine.single_scan(90.0),
        lambda: machine.continuous_scan(np.float32(-45.0), 45),
        lambda: machine.set_motor_params(MotorParams(sample=0x7F, gain=0x50, max_vel=3)),
        lambda: machine.stop_wait_then_scan(-90.0),
        lambda: machine.set_elevation(10.0),
        lambda: machine.inject_fault("parity", 45.0),
        lambda: machine.single_scan(np.int64(400)),
        lambda: machine.reset(),
        lambda: machine.home(),
        lambda: machine.wait_idle(LONG),
    ]
    try:
        machine.start(seed=5, start=700.0, ring=False)
        for step in steps:
            step()
            machine.the_true_head_stays_within_the_envelope()
            machine.the_audit_stays_clean()
            machine.status_never_contradicts_itself()
    finally:
        machine.teardown()

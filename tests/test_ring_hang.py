"""Continuous acquisition through a hung BIRIS: the hang is seen while the head stands idle, and
the accounts book no frame BIRIS did not make (issue 24, item 7).

In Appendix D's continuous acquisition BIRIS fills its ring of 1,024 frames whether or not a
sweep reads it; with the head idle its data interrupts are off, so nothing else looks. The
server therefore owes the ring's progress to the BIRIS timeout: each time the timeout runs out
the level-2 routine looks at ACQ_LINE, and a ring that has not moved since the previous look is
a hung BIRIS, the ``timeout`` fault (``biris_hw.server.acquisition``, "The ring must
progress"). Frames passed between two looks are the slot advance plus laps that only the clock
can tell, and only while BIRIS is known to have acquired all the while ("Laps, on evidence").

Everything runs on virtual time with seeded simulators: a hang of 80 hardware seconds costs a
fraction of a second, and every run is the same run. The accounts are compared with the
simulator's own count once the ring has stopped (``rig.supervisor.acquisitions_made`` against
``status().accounts().accounted``, which the status module documents as exact then).
"""

from __future__ import annotations

import random
from collections.abc import Callable

import pytest

from biris_hw import BirisInitRecord, ConnectionKind, DeliveryPolicy, HardwareFault
from biris_hw.errors import RequestError
from biris_hw.server import BirisServer
from regs.layout import FIELD_PERIOD_S
from sim import SimulatedBiris
from tests.conftest import join, spawn, until

WAIT = 10.0
"""A caller's patience, read at the rig's nominal x30 (300 s of hardware time)."""
RING_RECORD = BirisInitRecord(continuous_acquisition=True)
TIMEOUT_S = RING_RECORD.timeout_s
PERIOD_S = 2 * FIELD_PERIOD_S
"""An acquisition at 64 samples: two video fields."""
LAP_S = 1024 * PERIOD_S
"""One lap of the ring: 34 hardware seconds."""


def _made_equals_accounted(rig: SimulatedBiris, server: BirisServer) -> tuple[int, int]:
    """Stop the ring and wait for idle: (made, accounted), which must then agree."""
    conn = server.open()
    conn.stop_continuous()
    conn.wait_idle(timeout=WAIT)
    assert not rig.supervisor.continuous
    accounts = server.status().accounts()
    assert accounts.adds_up, accounts
    return rig.supervisor.acquisitions_made, accounts.accounted


def _blocked_reader(server: BirisServer, told: list[BaseException]) -> None:
    """A DATA client waiting for points the idle head never makes: what ends its wait."""
    data = server.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_ACQUISITION)
    try:
        data.ready_for_data(timeout=WAIT)
    except BaseException as exc:  # the test looks at what it was
        told.append(exc)
    finally:
        data.close()


def test_a_hang_while_idle_is_a_timeout_fault_within_two_biris_timeouts(
    rig: SimulatedBiris,
) -> None:
    with BirisServer(rig.hardware, RING_RECORD) as server:
        conn = server.open()
        conn.wait_idle(timeout=WAIT)
        # a healthy ring idling through a lap is watched (a look every timeout), never faulted,
        # and its laps are booked (the accounts are checked at the end)
        rig.timebase.sleep(LAP_S + TIMEOUT_S)
        status = server.status()
        assert (status["state"], status["ring"]) == ("idle", "live")
        told: list[BaseException] = []
        reader = spawn(_blocked_reader, server, told)
        until(lambda: len(server.status()["connections"]) == 2, what="the reader's connection")
        hung_at = rig.clock.now()
        rig.faults.hang_supervisor()
        until(lambda: server.status()["fault"] is not None, what="the fault")
        detected = rig.clock.now() - hung_at
        # BIRIS began its last frame within a period before the hang; the looks come a timeout
        # apart, and the first that finds no frame begun since the one before is the fault
        assert TIMEOUT_S - PERIOD_S <= detected <= 2 * TIMEOUT_S + 0.02, detected
        assert server.status()["fault"] == "timeout"
        assert join(reader)
        assert len(told) == 1 and isinstance(told[0], HardwareFault), told
        assert told[0].kind == "timeout" and "ring did not advance" in told[0].message
        with pytest.raises(HardwareFault) as later:
            conn.single_scan(10.0)
        assert later.value.kind == "timeout"
        rig.faults.clear_hang()
        conn.reset()
        conn.wait_idle(timeout=WAIT)
        made, accounted = _made_equals_accounted(rig, server)
        assert made == accounted


def test_with_the_timeout_disabled_a_hang_while_idle_is_not_a_fault(rig: SimulatedBiris) -> None:
    with BirisServer(rig.hardware, RING_RECORD) as server:
        conn = server.open()
        conn.wait_idle(timeout=WAIT)
        conn.timeout_disable()
        rig.faults.hang_supervisor()
        rig.timebase.sleep(3 * TIMEOUT_S)
        assert server.status()["state"] == "idle"  # by configuration, as for commands
        rig.faults.clear_hang()
        made, accounted = _made_equals_accounted(rig, server)
        assert made == accounted


@pytest.mark.parametrize("timeout_on", [True, False], ids=["timeout_on", "timeout_off"])
def test_after_80_s_of_hang_the_accounts_equal_what_biris_made(
    rig: SimulatedBiris, timeout_on: bool
) -> None:
    """The review's repro: +2,048 phantom frames after 80 hardware seconds of hang (two laps
    of the clock's count), whether the hang was seen (timeout on) or not (off). BIRIS resumes
    for a few seconds before the reset stops its ring: those frames are its own and count."""
    with BirisServer(rig.hardware, RING_RECORD) as server:
        conn = server.open()
        conn.wait_idle(timeout=WAIT)
        if not timeout_on:
            conn.timeout_disable()
        rig.timebase.sleep(1.0)
        rig.faults.hang_supervisor()
        before = rig.supervisor.acquisitions_made
        rig.timebase.sleep(80.0)
        assert rig.supervisor.acquisitions_made == before  # hung: nothing made
        assert server.status()["fault"] == ("timeout" if timeout_on else None)
        rig.faults.clear_hang()
        rig.timebase.sleep(3.0)
        resumed = rig.supervisor.acquisitions_made - before
        assert resumed > 60  # it made these after the hang
        conn.reset()
        conn.wait_idle(timeout=WAIT)
        made, accounted = _made_equals_accounted(rig, server)
        assert made == accounted


def test_an_unwatched_healthy_ring_idle_for_a_lap_is_booked_in_full(rig: SimulatedBiris) -> None:
    """Laps are still booked from the clock where BIRIS did acquire all the while, even with
    no look for over a lap (the timeout disabled: the ring is not watched). The watched case is
    the first test's, before its hang."""
    with BirisServer(rig.hardware, RING_RECORD) as server:
        conn = server.open()
        conn.wait_idle(timeout=WAIT)
        conn.timeout_disable()
        rig.timebase.sleep(1.2 * LAP_S)
        assert server.status()["state"] == "idle"
        made, accounted = _made_equals_accounted(rig, server)
        assert made > 1024  # more than a lap went by unread
        assert made == accounted


# -- a seeded random sequence, the ring switched on and off ---------------------------------------


def _random_run(rig: SimulatedBiris, server: BirisServer, seed: int, steps: int) -> list[str]:
    """Requests, hangs and waits drawn from ``seed``: the ring switched on and off, scans,
    resets (some during the ring's start-up), the timeout toggled, hangs while idle and while
    scanning, idle stretches up to a lap. Each fault is answered as an operator would:
    ``clear_all()`` + ``reset()``. Returns what was done, for a failure's message. Checks at
    every quiet moment (ring off, idle) that made = accounted."""
    draw = random.Random(seed)
    conn = server.open()
    trace: list[str] = []
    tb = rig.timebase

    def check(where: str) -> None:
        status = server.status()
        if status["state"] != "idle" or status["ring"] != "off" or rig.supervisor.continuous:
            return
        accounts = status.accounts()
        made = rig.supervisor.acquisitions_made
        assert accounts.adds_up, (where, accounts)
        assert accounts.accounted == made, f"{where}: made {made}, {accounts}\n" + "\n".join(trace)

    def hang_a_while() -> None:
        rig.faults.hang_supervisor()
        tb.sleep(draw.uniform(0.5, 1.5 * LAP_S))
        rig.faults.clear_hang()

    steps_by_name: list[tuple[str, Callable[[], object]]] = [
        ("start_continuous", conn.start_continuous),
        ("stop_continuous", conn.stop_continuous),
        ("single_scan", lambda: conn.single_scan(draw.uniform(-40.0, 40.0))),
        ("continuous_scan", lambda: conn.continuous_scan(-20.0, 20.0)),
        ("stop_scan", conn.stop_scan),
        ("set_elevation", lambda: conn.set_elevation(draw.choice([0.0, 5.0, -5.0]))),
        ("reset", conn.reset),
        ("timeout_disable", conn.timeout_disable),
        ("timeout_enable", conn.timeout_enable),
        ("hang", hang_a_while),
        ("wait", lambda: tb.sleep(draw.choice([0.05, 0.3, 2.0, 0.6 * LAP_S]))),
        ("wait_idle", lambda: conn.wait_idle(timeout=draw.choice([0.05, 0.3]))),
    ]
    weights = [3, 3, 2, 1, 2, 1, 2, 1, 1, 2, 4, 2]
    for i in range(steps):
        ((name, step),) = draw.choices(steps_by_name, weights)
        try:
            step()
            outcome = "ok"
        except (RequestError, TimeoutError) as refused:
            outcome = type(refused).__name__
        except HardwareFault as fault:
            outcome = f"HardwareFault({fault.kind})"
        status = server.status()
        trace.append(
            f"#{i} {name}: {outcome}; {status['state']}, ring {status['ring']}, "
            f"t={rig.clock.now():.2f}, made {rig.supervisor.acquisitions_made}, "
            f"accounted {status.accounts().accounted}"
        )
        if status["fault"] is not None:
            rig.faults.clear_all()
            conn.reset()
            trace.append(f"   clear_all + reset: {server.status()['state']}")
        check(f"after #{i} {name}")
    rig.faults.clear_all()
    conn.stop_scan()
    conn.wait_idle(timeout=WAIT)
    made, accounted = _made_equals_accounted(rig, server)
    assert made == accounted, f"made {made}, accounted {accounted}\n" + "\n".join(trace)
    return trace


@pytest.mark.parametrize(
    ("seed", "ring"), [(7, True), pytest.param(10, False, marks=pytest.mark.slow)]
)
def test_a_seeded_random_sequence_ends_with_made_equal_to_accounted(
    rig: SimulatedBiris, seed: int, ring: bool
) -> None:
    with BirisServer(rig.hardware, BirisInitRecord(continuous_acquisition=ring)) as server:
        trace = _random_run(rig, server, seed, steps=30)
    names = {line.split(":")[0].split(" ", 1)[1] for line in trace if line.startswith("#")}
    assert {"start_continuous", "stop_continuous", "hang", "reset"} <= names

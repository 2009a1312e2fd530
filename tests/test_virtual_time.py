"""The simulator and the server on virtual time (issue 22, docs/simulator.md).

On virtual time hardware time moves only when every thread of the rig and of its server waits,
so a run depends on the seed and the requests, never on the host: the same seed gives the same
scans, bit for bit and to the last timestamp, on a quiet machine and beside three CPU-bound
processes. A wait that nothing will ever end fails at once, naming who waits on what.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from typing import Any

import numpy as np
import pytest

import sim.rig as sim_rig
import sim.supervisor.supervisor as supervisor_module
from biris_hw.data import ConnectionKind, Direction, Scan
from biris_hw.ipc import Mailbox
from biris_hw.server import BirisServer
from biris_hw.timebase import VirtualTime, VirtualTimeDeadlock
from sim.hostload import busy_processes
from sim.rig import SimulatedBiris
from sim.scene import Scene


def _session(seed: int) -> list[Any]:
    """A fixed sequence of requests on a fresh virtual rig: two single scans, two sweeps of a
    continuous scan read by a DATA connection, a point; everything the client was handed."""
    got: list[Any] = []
    rig = SimulatedBiris(scene=Scene.room(), time_scale=30.0, seed=seed, clock="virtual")
    with rig.start(), BirisServer(rig.hardware) as server:
        conn = server.open()
        data = server.open(ConnectionKind.DATA)
        for destination, direction in ((120.0, Direction.CCW), (-60.0, Direction.CW)):
            conn.single_scan(destination)
            conn.wait_idle()
            got.append(conn.request_scan_data(direction))
        conn.continuous_scan(-15.0, 15.0)
        got.extend(data.ready_for_data() for _ in range(2))
        conn.stop_scan()
        conn.wait_idle()
        got.append(conn.request_point())
        got.append(rig.clock.now())
        assert isinstance(rig.timebase, VirtualTime)
        assert rig.timebase.deadlock is None
    return got


def _fields(item: object) -> dict[str, object]:
    if dataclasses.is_dataclass(item) and not isinstance(item, type):
        return {f.name: getattr(item, f.name) for f in dataclasses.fields(item)}
    return {"value": item}


def _differences(first: list[Any], second: list[Any]) -> list[str]:
    found: list[str] = []
    if len(first) != len(second):
        return [f"{len(first)} items against {len(second)}"]
    for k, (a, b) in enumerate(zip(first, second, strict=True)):
        fa, fb = _fields(a), _fields(b)
        if fa.keys() != fb.keys():
            found.append(f"item {k}: {type(a).__name__} against {type(b).__name__}")
            continue
        for name, va in fa.items():
            vb = fb[name]
            same = (
                np.array_equal(va, vb) and va.dtype == vb.dtype
                if isinstance(va, np.ndarray) and isinstance(vb, np.ndarray)
                else va == vb
            )
            if not same:
                found.append(f"item {k} ({type(a).__name__}).{name}: {va!r} against {vb!r}")
    return found


@pytest.fixture(scope="module")
def seed5() -> list[Any]:
    """One run of seed 5, for the two tests that compare another run with it."""
    return _session(seed=5)


def test_a_seed_is_one_run(seed5: list[Any]) -> None:
    """Two runs of one seed in this worker (beside the fast tier's other workers, and beside
    three CPU-bound processes under ``make test-under-load``)."""
    first = seed5
    second = _session(seed=5)
    scans = [item for item in first if isinstance(item, Scan)]
    assert len(scans) == 4 and all(len(scan.azimuth) > 5 for scan in scans)
    assert _differences(first, second) == []


@pytest.mark.slow  # its three processes take two cores from the fast tier's other workers
def test_a_seed_is_one_run_on_a_quiet_host_and_beside_three_busy_processes() -> None:
    quiet = _session(seed=5)
    with busy_processes(3):
        loaded = _session(seed=5)
    scans = [item for item in quiet if isinstance(item, Scan)]
    assert len(scans) == 4 and all(len(scan.azimuth) > 5 for scan in scans)
    assert _differences(quiet, loaded) == []


def test_an_idle_biris_sleeping_through_its_fields_changes_nothing(
    seed5: list[Any], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The same run with a supervisor that wakes at every field (as BIRIS polls COMMAND)
    instead of sleeping through idle ones: every Scan, point and time the same."""
    monkeypatch.setattr(supervisor_module, "IDLE_CHECK_FIELDS", 1)
    assert _differences(seed5, _session(seed=5)) == []


def test_another_seed_is_another_run(seed5: list[Any]) -> None:
    """The comparison above can fail: a different seed changes the noise in every row."""
    assert _differences(seed5[:1], _session(seed=6)[:1]) != []


def test_a_wait_nothing_will_end_fails_at_once_naming_the_waits(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The video fields are always due, so "nothing is due" never comes; a driver waiting with
    no deadline for what will never happen is a deadlock after the rig's runaway limit, which
    takes seconds of CPU, not for ever (here a limit of 60 hardware seconds, not the rig's 600:
    the same rule, a tenth of the CPU)."""
    monkeypatch.setattr(sim_rig, "RUNAWAY_HW_S", 60.0)
    rig = SimulatedBiris(scene=Scene.circle(2.0), time_scale=30.0, seed=3, clock="virtual")
    with rig.start():
        nobody = Mailbox("nobody", timebase=rig.timebase)
        began = time.monotonic()
        with pytest.raises(VirtualTimeDeadlock) as caught:
            nobody.send("hello")
        took = time.monotonic() - began
        assert isinstance(rig.timebase, VirtualTime)
        assert rig.timebase.deadlock is not None
        waits = {info.what: info.thread for info in caught.value.waits}
        assert waits["reply from 'nobody'"] == threading.current_thread().name
        assert "next field" in waits  # the simulator's supervisor, listed too
        assert took < 60.0  # pytest's own timeout would otherwise be what ended it
    rig.timebase._deadlock = None  # seen and checked: not a failure of this test's teardown


def test_virtual_time_needs_a_rig_the_time_base_can_see() -> None:
    for options in ({"transport": "vmusb"}, {"axes": "canopen"}, {"crate": True}):
        with pytest.raises(ValueError, match="virtual"):
            SimulatedBiris(clock="virtual", **options)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="clock"):
        SimulatedBiris(clock="wall")


def test_biris_scan_on_virtual_time_and_watch_refuses_it(biris: Any) -> None:
    """``biris scan --sim --clock virtual`` returns its scan; a command that serves or shows the
    sensor as time passes keeps scaled time and says so."""
    sim = ["--sim", "--scene", "circle:2", "--seed", "3", "--clock", "virtual"]
    code, out, err = biris("scan", "--to", "30", *sim)
    assert code == 0, err
    assert "acquisitions over" in out and "dropped 0" in out
    code, _, err = biris("watch", "--duration", "0.1", *sim)
    assert code != 0
    assert "--clock virtual does not apply to biris watch" in err

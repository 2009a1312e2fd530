"""CPU affinity: the init record's ``cpus`` keeps every server thread there, and nothing else."""

from __future__ import annotations

import os
import threading

import pytest

from biris_hw import BirisInitRecord, Direction, RequestError
from biris_hw.affinity import available_cpus, check_cpus, pin_current_thread, pinned
from biris_hw.server import BirisServer
from sim import SimulatedBiris
from tests.conftest import affinity_allowed

pytestmark = pytest.mark.skipif(
    not affinity_allowed(), reason="this platform does not let a thread choose its CPUs"
)

WAIT = 30.0


def _affinity(thread: threading.Thread) -> frozenset[int]:
    assert thread.native_id is not None
    return frozenset(os.sched_getaffinity(thread.native_id))


@pytest.mark.parametrize(
    ("cpus", "named"),
    [
        ((-1,), "cpus: must be in 0..1023"),
        ((0, 0), "cpus: names a CPU twice"),
        ("0", "cpus: must be a sequence"),
        ((True,), "cpus: must be an integer, not a bool"),
        ((1.0,), "cpus: must be an integer"),
    ],
)
def test_the_record_refuses_what_is_no_cpu_set(cpus: object, named: str) -> None:
    with pytest.raises(RequestError, match=named):
        BirisInitRecord(cpus=cpus)  # type: ignore[arg-type]


def test_the_record_reads_a_toml_list_and_writes_it_back() -> None:
    record = BirisInitRecord.from_toml("cpus = [1, 0]\n")
    assert record.cpus == (1, 0)
    assert BirisInitRecord.from_toml(record.to_toml()) == record
    assert BirisInitRecord().cpus == ()


def test_cpus_the_process_cannot_use_are_refused() -> None:
    outside = max(available_cpus()) + 1
    with pytest.raises(RequestError, match=rf"cpus: \[{outside}\] not available"):
        check_cpus({outside})
    with pytest.raises(RequestError, match="names no CPU"):
        check_cpus(())


def test_pinned_is_for_the_block_and_the_threads_it_starts() -> None:
    me = threading.current_thread()
    before = _affinity(me)
    one = min(available_cpus())
    seen: list[frozenset[int]] = []
    with pinned({one}):
        assert _affinity(me) == {one}
        child = threading.Thread(target=lambda: seen.append(frozenset(os.sched_getaffinity(0))))
        child.start()
        child.join()
    assert seen == [{one}] and _affinity(me) == before
    previous = pin_current_thread({one})
    try:
        assert previous == before and _affinity(me) == {one}
    finally:
        os.sched_setaffinity(0, previous)


def test_a_server_keeps_every_thread_on_its_cpus(no_leaks: None) -> None:
    one = min(available_cpus())
    me = threading.current_thread()
    mine = _affinity(me)
    existing = set(threading.enumerate())
    with SimulatedBiris(time_scale=20.0, clock="virtual") as rig:
        simulator = set(threading.enumerate()) - existing
        with BirisServer(rig.hardware, BirisInitRecord(cpus=(one,))) as server:
            assert _affinity(me) == mine  # the caller's thread is given back as it was
            ours = set(threading.enumerate()) - existing - simulator
            assert {"level2_isr", "biris_server"} <= {t.name for t in ours}
            assert all(_affinity(t) == {one} for t in ours), {t.name: _affinity(t) for t in ours}
            assert all(_affinity(t) == mine for t in simulator)  # not the server's to move
            conn = server.open()
            conn.single_scan(20.0)
            conn.wait_idle(timeout=WAIT)
            assert conn.request_scan_data(Direction.CCW) is not None


def test_a_server_asked_for_cpus_it_cannot_have_starts_nothing(no_leaks: None) -> None:
    outside = max(available_cpus()) + 1
    with SimulatedBiris(time_scale=20.0, clock="virtual") as rig:
        before = set(threading.enumerate())
        with pytest.raises(RequestError, match="not available"):
            BirisServer(rig.hardware, BirisInitRecord(cpus=(outside,)))
        assert set(threading.enumerate()) == before
        assert not rig.supervisor.booted  # BIRIS was not touched either


def test_a_platform_that_forbids_affinity_is_a_request_error(
    monkeypatch: pytest.MonkeyPatch, no_leaks: None
) -> None:
    def forbidden(pid: int, cpus: object) -> None:
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "sched_setaffinity", forbidden)
    one = min(available_cpus())
    with pytest.raises(RequestError, match="cannot keep this thread on"):
        pin_current_thread({one})
    with SimulatedBiris(time_scale=20.0, clock="virtual") as rig:
        before = set(threading.enumerate())
        with pytest.raises(RequestError, match="cannot keep this thread on"):
            BirisServer(rig.hardware, BirisInitRecord(cpus=(one,)))
        assert set(threading.enumerate()) == before

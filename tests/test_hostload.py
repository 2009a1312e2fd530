"""sim.hostload: the load processes spin, and none outlives its block, its deadline or its parent.

What matters for its users (tests, ``make test-under-load``, the ``_contended`` benchmarks) is that
the load is really there while the block runs and really gone after it: a load process left
behind would slow every later test and benchmark on the machine without anyone knowing why.
"""

from __future__ import annotations

import os
import select
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from sim import hostload
from sim.hostload import HostLoad, busy_processes
from tests.conftest import until


def state(pid: int) -> str | None:
    """The process's state letter from /proc (R running, S sleeping, Z ended, not reaped), or
    None once it is gone."""
    try:
        with open(f"/proc/{pid}/stat", encoding="ascii") as f:
            return f.read().rsplit(")", 1)[1].split()[0]
    except (FileNotFoundError, ProcessLookupError):
        return None


def cpu_ticks(pid: int) -> int:
    """User plus system CPU time the process has used, in clock ticks (0 once it is gone)."""
    try:
        with open(f"/proc/{pid}/stat", encoding="ascii") as f:
            fields = f.read().rsplit(")", 1)[1].split()
    except (FileNotFoundError, ProcessLookupError):
        return 0
    return int(fields[11]) + int(fields[12])  # utime, stime: fields 14 and 15 of stat(5)


def gone(pid: int) -> bool:
    """Not running any more: reaped, or ended and waiting for a parent that is not ours."""
    return state(pid) in (None, "Z")


pytestmark = pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads /proc")


def test_the_processes_spin_beside_the_block_and_are_reaped_after_it(no_leaks: None) -> None:
    with busy_processes(2) as load:
        assert isinstance(load, HostLoad)
        assert load.count == 2 and len(set(load.pids)) == 2
        assert os.getpid() not in load.pids
        assert load.max_s == hostload.DEFAULT_MAX_S
        if os.getpriority(os.PRIO_PROCESS, 0) == 0:
            assert load.nice == (0, 0)
        # CPU-bound: each one uses CPU time while the test only waits
        until(lambda: all(cpu_ticks(pid) >= 5 for pid in load.pids), what="the load to spin")
        assert all(state(pid) in ("R", "S") for pid in load.pids)
    assert all(state(pid) is None for pid in load.pids), "a load process outlived its block"


def test_the_processes_are_reaped_when_the_block_raises(no_leaks: None) -> None:
    with pytest.raises(KeyError), busy_processes(1) as load:
        raise KeyError("the test under load failed")
    assert state(load.pids[0]) is None


def test_a_process_stops_by_itself_after_max_s(no_leaks: None) -> None:
    with busy_processes(1, max_s=0.2) as load:
        # it ends on its own; its parent (this process) reaps it only on leaving the block
        until(lambda: gone(load.pids[0]), what="the load process to stop by itself")
    assert state(load.pids[0]) is None


def test_the_processes_keep_none_of_the_parents_descriptors_open(no_leaks: None) -> None:
    """Forked children inherit every descriptor; they close them, or a pipe, socket or eventfd
    the code under test closes would stay open in them (no EOF for its peer) while they spin."""
    read_end, write_end = os.pipe()
    try:
        with busy_processes(2):
            os.close(write_end)
            write_end = -1
            readable, _, _ = select.select([read_end], [], [], 5.0)
            assert readable, "a load process holds the pipe's write end open"
            assert os.read(read_end, 1) == b""
    finally:
        os.close(read_end)
        if write_end >= 0:
            os.close(write_end)


def test_no_processes_is_a_load_of_nothing() -> None:
    with busy_processes(0) as load:
        assert load.count == 0 and load.pids == () and load.nice == ()


@pytest.mark.parametrize(("n", "max_s"), [(-1, 1.0), (1, 0.0), (1, -5.0), (1, float("nan"))])
def test_bad_arguments_are_refused_before_anything_starts(n: int, max_s: float) -> None:
    with pytest.raises(ValueError), busy_processes(n, max_s=max_s):
        pass


# The parent is killed outright (no block exit, no atexit): its load processes must notice that
# they were orphaned and stop at once, long before max_s. hostload.py is loaded from its file, so
# the parent does not import the whole simulator package first.
_PARENT = """
import importlib.util, os, signal, sys
spec = importlib.util.spec_from_file_location("hostload", sys.argv[1])
hostload = sys.modules["hostload"] = importlib.util.module_from_spec(spec)
spec.loader.exec_module(hostload)
with hostload.busy_processes(2, max_s=60.0) as load:
    print(*load.pids, flush=True)
    os.kill(os.getpid(), signal.SIGKILL)
"""


def test_orphaned_processes_stop_when_their_parent_is_killed() -> None:
    parent = subprocess.Popen(
        [sys.executable, "-c", _PARENT, hostload.__file__],
        stdout=subprocess.PIPE,
        text=True,
    )
    assert parent.stdout is not None
    with parent.stdout:
        pids = [int(pid) for pid in parent.stdout.readline().split()]
    assert parent.wait(timeout=30) == -signal.SIGKILL
    assert len(pids) == 2
    until(lambda: all(gone(pid) for pid in pids), what="the orphaned load processes to stop")

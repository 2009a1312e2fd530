"""A busy host on demand: CPU-bound processes beside the code under test.

A figure or a test that passes on a quiet machine says little about a robot's computer, where a
planner or a compiler shares the cores with the driver. :func:`busy_processes` makes that load
the same way for tests, benchmarks (the ``_contended`` figures) and ``make test-under-load``: ``n``
processes, each spinning a tight pure-Python loop at the default priority (nice 0), as a
neighbour's job would.

*Processes*, not threads: a thread would compete for this interpreter's lock, which is another
(and much harsher) load than a busy neighbour; a process competes for the CPUs only.

Nothing is left behind. The context manager terminates, kills if need be, and joins every process
on exit, whatever ends the block. A process the context manager could not stop (its parent was
killed with SIGKILL, say) stops by itself: it checks every millisecond or so whether its parent
is still the one that started it (``os.getppid``), and it never runs longer than ``max_s``.

The processes are forked (multiprocessing's ``fork`` start method; POSIX only). ``spawn``
would cost a Python start-up per process, run the parent's main script again in each, and start
multiprocessing's resource tracker, a process of its own whose pipe a test's leak check then
finds open. Forking a parent whose threads run (a server, a simulator) is safe only for a child
that touches nothing those threads might have held at that instant, so the child is written for
it: it closes every descriptor it inherited but its own pipe (it keeps no socket or eventfd of
the parent's open), restores the default SIGTERM and ignores SIGINT, runs a loop that takes no
lock, and leaves with ``os._exit``, skipping the interpreter's shutdown (which flushes standard
streams a parent thread may have been writing to).
"""

from __future__ import annotations

import multiprocessing
import os
import signal
import time
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess

__all__ = ["DEFAULT_MAX_S", "HostLoad", "busy_processes"]

DEFAULT_MAX_S = 600.0
"""Longest a load process runs, in seconds, if nobody stops it: longer than any test run or
benchmark section that uses it, short enough that a forgotten one is not a day's load."""

_START_TIMEOUT_S = 30.0
"""How long the processes may take to start spinning (on a host that is perhaps very busy
already) before :func:`busy_processes` gives up."""

_STOP_GRACE_S = 5.0
"""How long a terminated process may take to end before it is killed."""

_SPIN_CHUNK = 20_000
"""Loop turns between two checks of the deadline and the parent: about a millisecond of CPU."""


@dataclass(frozen=True)
class HostLoad:
    """The load processes of one :func:`busy_processes` block, all spinning when it is given."""

    count: int
    """How many processes there are."""
    pids: tuple[int, ...]
    """Their process ids, to check on them (``/proc/PID``) or name them in a report."""
    nice: tuple[int, ...]
    """The niceness each one runs at: 0, unless this process was niced above 0 and may not
    lower its children's (then the children keep the inherited one, as a neighbour would)."""
    max_s: float
    """Seconds after which each stops by itself."""


@contextmanager
def busy_processes(n: int = 3, *, max_s: float = DEFAULT_MAX_S) -> Iterator[HostLoad]:
    """``n`` CPU-bound processes for the duration of the block; every one stopped and reaped on
    exit.

    The block begins once every process has started spinning, so the load is present from its
    first line; ``n`` may be 0 (no load: a baseline run through the same code). Raises
    ValueError for a negative ``n`` or a ``max_s`` that is not positive, and RuntimeError when a
    process fails to start (the others are stopped first).
    """
    if n < 0:
        raise ValueError(f"the number of load processes must be 0 or more, not {n}")
    if not max_s > 0.0:
        raise ValueError(f"max_s must be positive, not {max_s}")
    fork = multiprocessing.get_context("fork")
    processes: list[BaseProcess] = []
    ready: list[Connection] = []
    try:
        for i in range(n):
            receiver, sender = fork.Pipe(duplex=False)
            ready.append(receiver)
            process = fork.Process(
                target=_child,
                args=(sender, os.getpid(), max_s),
                name=f"hostload-{i}",
                daemon=True,  # multiprocessing's exit handler stops it too, should all else fail
            )
            try:
                with warnings.catch_warnings():
                    # Python 3.12+ warns of forking with threads running: the child is written
                    # for it (module notes)
                    warnings.simplefilter("ignore", DeprecationWarning)
                    process.start()
            finally:
                sender.close()  # the child has its own copy; EOF here then means it died
            processes.append(process)
        nice = _await_spinning(processes, ready)
        pids = tuple(p.pid for p in processes if p.pid is not None)
        yield HostLoad(count=n, pids=pids, nice=nice, max_s=max_s)
    finally:
        for conn in ready:
            conn.close()
        _stop(processes)


def _await_spinning(processes: list[BaseProcess], ready: list[Connection]) -> tuple[int, ...]:
    """Each process's niceness, once each has said it is about to spin."""
    deadline = time.monotonic() + _START_TIMEOUT_S
    nice: list[int] = []
    for process, conn in zip(processes, ready, strict=True):
        if not conn.poll(max(0.0, deadline - time.monotonic())):
            raise RuntimeError(
                f"load process {process.pid} did not start within {_START_TIMEOUT_S:g} s"
            )
        try:
            nice.append(int(conn.recv()))
        except EOFError:
            process.join(_STOP_GRACE_S)
            raise RuntimeError(
                f"load process {process.pid} ended on start (exit code {process.exitcode})"
            ) from None
    return tuple(nice)


def _stop(processes: list[BaseProcess]) -> None:
    """Terminate all at once (so they end together), kill any that linger, reap every one."""
    for process in processes:
        if process.exitcode is None:
            process.terminate()
    deadline = time.monotonic() + _STOP_GRACE_S
    for process in processes:
        process.join(max(0.0, deadline - time.monotonic()))
        if process.exitcode is None:
            process.kill()
            process.join()
        process.close()


# -- the child -----------------------------------------------------------------------------------


def _child(ready: Connection, parent: int, max_s: float) -> None:
    """A load process: fork hygiene, nice 0, say so, spin until stopped, orphaned or ``max_s``
    is up, and leave without the interpreter's shutdown (module notes)."""
    code = 1
    try:
        keep = ready.fileno()
        os.closerange(3, keep)
        os.closerange(keep + 1, _max_fd())
        signal.signal(signal.SIGTERM, signal.SIG_DFL)  # terminate() ends it, whatever the parent
        # Ctrl-C in a terminal reaches the whole process group; the parent decides when load ends
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        try:
            os.setpriority(os.PRIO_PROCESS, 0, 0)
        except OSError:
            pass  # lowering an inherited niceness needs privileges: keep it (HostLoad.nice says)
        deadline = time.monotonic() + max_s
        ready.send(os.getpriority(os.PRIO_PROCESS, 0))
        ready.close()
        _spin(parent, deadline)
        code = 0
    finally:
        os._exit(code)


def _max_fd() -> int:
    """One past the highest descriptor a process may have open."""
    try:
        return int(os.sysconf("SC_OPEN_MAX"))
    except (OSError, ValueError):
        return 65536


def _spin(parent: int, deadline: float) -> None:
    """Pure-Python work, checked about every millisecond against the deadline and the parent.

    A parent that dies leaves its children to another process (``getppid`` changes), which is
    how an orphan notices within a millisecond instead of spinning on to ``max_s``.
    """
    x = 0
    while time.monotonic() < deadline and os.getppid() == parent:
        for i in range(_SPIN_CHUNK):
            x ^= i

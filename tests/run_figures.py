"""What a run of the suite cost, and how busy the machine was meanwhile: one line at its end.

A run's wall time alone cannot tell a slower suite from a slower machine. On a shared virtual
machine one commit's quiet fast tier took 73 s with 124 s of CPU and, a quarter of an hour
later, 81 s with 136 s: the same work cost more CPU seconds on a machine gone slower. So every
run says, beside its wall time, the CPU seconds its processes used (the controller, each xdist
worker, and the child processes they waited for), that CPU as a share of the usable cores' time,
and what the whole machine did meanwhile (``/proc/stat``): the share it stood idle (no runnable
work: the suite waiting on the wall clock with nothing beside it) and the share the hypervisor
stole (ran another guest while this one had work). ``make test-under-load`` shows the load
beside the suite as a machine seldom idle while the suite's own share drops.

This plugin only reports; nothing in it passes or fails a test.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from biris_hw.affinity import available_cpus
from biris_hw.errors import RequestError

PROC_STAT = Path("/proc/stat")


@dataclass(frozen=True)
class MachineTicks:
    """The machine-wide CPU time counters of ``/proc/stat``'s ``cpu`` line, in clock ticks."""

    total: int
    idle: int
    """idle and iowait: no runnable work on a core"""
    steal: int
    """time the hypervisor ran something else while this guest had work"""


def parse_stat(text: str) -> MachineTicks | None:
    """The counters of the aggregate ``cpu`` line of a ``/proc/stat`` text (user nice system
    idle iowait irq softirq steal ...); None if there is no such line or it is short."""
    for line in text.splitlines():
        fields = line.split()
        if fields[:1] != ["cpu"]:
            continue
        try:
            values = [int(v) for v in fields[1:9]]
        except ValueError:
            return None
        if len(values) < 8:
            return None
        # guest time (fields 9-10) is already counted in user and nice
        return MachineTicks(total=sum(values), idle=values[3] + values[4], steal=values[7])
    return None


def read_ticks(path: Path = PROC_STAT) -> MachineTicks | None:
    """The machine's counters now; None where there is no ``/proc/stat`` (not Linux)."""
    try:
        return parse_stat(path.read_text())
    except OSError:
        return None


def usable_cores() -> int:
    """The cores this process may run on (its affinity where the platform says)."""
    try:
        return len(available_cpus()) or 1
    except RequestError:  # no CPU affinity on this platform
        return os.cpu_count() or 1


def process_cpu_s(children: bool) -> float:
    """This process's user and system CPU seconds, and its waited-for children's if asked."""
    t = os.times()
    own = t.user + t.system
    return own + (t.children_user + t.children_system) if children else own


def describe(
    wall_s: float,
    cpu_s: float,
    cores: int,
    before: MachineTicks | None,
    after: MachineTicks | None,
) -> str:
    """The summary line: the run's wall and CPU seconds, its share of the cores' time, and
    (where both counters were read) the machine's idle and stolen shares meanwhile."""
    share = cpu_s / (wall_s * cores) if wall_s > 0 else 0.0
    line = (
        f"the run: {wall_s:.1f} s, {cpu_s:.1f} s of CPU in its processes "
        f"({share:.0%} of {cores} core{'s' if cores != 1 else ''})"
    )
    if before is not None and after is not None and after.total > before.total:
        ticks = after.total - before.total
        idle = (after.idle - before.idle) / ticks
        steal = (after.steal - before.steal) / ticks
        line += f"; the machine meanwhile: {idle:.0%} idle, {steal:.0%} stolen by its host"
    return line


_start: dict[str, Any] = {}
"""The controller's (or a plain run's) figures at the session's start."""

_workers_cpu_s: list[float] = []
"""The CPU seconds each finished xdist worker reported (the controller's list)."""


def _is_worker(config: pytest.Config) -> bool:
    return hasattr(config, "workerinput")


def _distributed(config: pytest.Config) -> bool:
    """Whether this process is an xdist controller (its children are the workers, whose CPU
    they report themselves) rather than a plain run (its children are the tests')."""
    return config.pluginmanager.has_plugin("dsession")


def pytest_sessionstart(session: pytest.Session) -> None:
    config = session.config
    if _is_worker(config):
        return
    _start.update(
        wall=time.monotonic(),
        cpu=process_cpu_s(children=not _distributed(config)),
        ticks=read_ticks(),
    )


def pytest_sessionfinish(session: pytest.Session) -> None:
    """A worker hands the controller its CPU seconds: its own and its tests' child processes'
    (the worker is the controller's child too, but reaped only after the summary)."""
    workeroutput = getattr(session.config, "workeroutput", None)
    if workeroutput is not None:
        workeroutput["cpu_s"] = process_cpu_s(children=True)


@pytest.hookimpl(optionalhook=True)
def pytest_testnodedown(node: Any, error: object) -> None:
    """(xdist controller) a finished worker's CPU seconds."""
    cpu = getattr(node, "workeroutput", {}).get("cpu_s")
    if isinstance(cpu, float):
        _workers_cpu_s.append(cpu)


def pytest_terminal_summary(terminalreporter: Any, config: pytest.Config) -> None:
    if _is_worker(config) or not _start:
        return
    own = process_cpu_s(children=not _distributed(config)) - _start["cpu"]
    terminalreporter.write_line(
        describe(
            time.monotonic() - _start["wall"],
            own + sum(_workers_cpu_s),
            usable_cores(),
            _start["ticks"],
            read_ticks(),
        )
    )

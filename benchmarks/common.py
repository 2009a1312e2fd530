"""Shared machinery of the server benchmarks: a rig with a server on it, interrupt timestamps
and CPU accounting.

This module registers no benchmark (it holds no ``@benchmark``), so discovery imports it
harmlessly. Everything here is about measuring *honestly* in one process:

* the simulator and the server share the process and its GIL, so whatever the simulator spends
  is load on the server; :class:`CpuMeter` therefore splits CPU time between the server's
  threads, the simulator's and the rest (clients), per thread from ``/proc``;
* latencies start at the moment the simulated hardware raised its interrupt
  (:class:`IrqRecorder`, through :attr:`sim.irqgate.InterruptGate.on_raise`), not at some point
  inside the driver, so the whole driver path is inside the figure;
* a ``_contended`` figure repeats a measurement with CPU-bound processes beside the server
  (:func:`contended`, :mod:`sim.hostload`) and says how busy the machine was, because a robot's
  computer is rarely idle and a quiet figure alone cannot tell how the driver shares it.

Only the public API is used (``biris_hw``, ``sim``, ``regs``), so the server's internals can
change under the benchmarks.
"""

from __future__ import annotations

import bisect
import gc
import math
import os
import queue
import threading
import time
from collections.abc import Iterable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field

from benchmarks.harness import Figure, Target
from biris_hw import BirisInitRecord, BirisServer
from regs.biexec import ACQ_LINE_END, OFF_ACQ_LINE
from sim import Scene, SimulatedBiris
from sim.clock import FIELD_PERIOD
from sim.hostload import busy_processes

__all__ = [
    "CONTENDING_PROCESSES",
    "HOME_NEAR_COUNTS",
    "Bench",
    "Contention",
    "CpuMeter",
    "DataRaise",
    "IrqRecorder",
    "acquisition_period_s",
    "against_quiet",
    "contended",
    "load_average",
    "not_measured",
    "running_server",
    "snap_to",
]

CONTENDING_PROCESSES = 2
"""CPU-bound processes beside the server in a ``_contended`` figure: one per core of the 2-core
machines the figures are taken on, so the server's threads must take turns with a neighbour on
every CPU, as they would beside a planner or a build on a robot's computer."""

HOME_NEAR_COUNTS = -200.0
"""Where the head stands at power-up in the benchmarks: near the zero index, so homing takes
about a second at time_scale 1 instead of five. Initialisation is not what is measured."""

_NANO = 1_000_000_000


def not_measured(key: str, unit: str, target: Target | None, reason: str) -> Figure:
    """The figure that stands in for one this machine cannot measure: n = 0 and the reason.

    A section keeps the figures it could measure; this row says, in the report, what the other
    one needs (CPU affinity, say), so the gap is visible rather than an absent row.
    """
    return Figure(
        key=key,
        values={"n": 0.0},
        unit=unit,
        target=target,
        method=f"NOT MEASURED: {reason}.",
    )


def acquisition_period_s(samples: int) -> float:
    """Hardware seconds per acquisition: 2 video fields at 64 samples, 3 at 128."""
    return (2 if samples <= 64 else 3) * FIELD_PERIOD


# -- rig and server ------------------------------------------------------------------------------


@dataclass
class Bench:
    """A rig, the server on it, and which threads are whose (for :class:`CpuMeter`)."""

    rig: SimulatedBiris
    server: BirisServer
    server_threads: list[threading.Thread]
    sim_threads: list[threading.Thread]

    def cpu(self, **extra: list[threading.Thread]) -> CpuMeter:
        """A CPU meter over the server's and the simulator's threads, plus ``extra`` groups."""
        return CpuMeter({"server": self.server_threads, "sim": self.sim_threads, **extra})


@contextmanager
def running_server(
    *,
    samples: int = 64,
    time_scale: float = 1.0,
    seed: int = 1,
    record: BirisInitRecord | None = None,
) -> Iterator[Bench]:
    """A simulated BIRIS with an initialised server on it; both closed on exit.

    The scene is a 2 m circle (the cheapest optics: benchmarks time the server, not the scene)
    and the head starts near the index (:data:`HOME_NEAR_COUNTS`) so set-up stays short.
    """
    before = set(threading.enumerate())
    with SimulatedBiris(
        scene=Scene.circle(2.0),
        samples=samples,
        time_scale=time_scale,
        seed=seed,
        initial_azimuth_counts=HOME_NEAR_COUNTS,
    ) as rig:
        sim_threads = [t for t in threading.enumerate() if t not in before]
        known = before | set(sim_threads)
        with BirisServer(rig.hardware, record if record is not None else BirisInitRecord()) as srv:
            srv_threads = [t for t in threading.enumerate() if t not in known]
            gc.collect()  # as every `biris` command does once its server is up: what is
            gc.freeze()  # alive now is out of the collector's reach (40-180 ms full collections)
            yield Bench(rig, srv, srv_threads, sim_threads)


# -- interrupt timestamps ------------------------------------------------------------------------


@dataclass(frozen=True)
class DataRaise:
    """One BIRIS data interrupt as the simulator raised it.

    ``announces`` is the acquisition it tells the driver is complete: ACQ_LINE - 1, or the last
    one of the sequence when ACQ_LINE reads -128; -1 for the interrupt that starts acquisition
    0 (it announces nothing). ``line`` is ACQ_LINE as written just before the raise.
    """

    t_ns: int
    t_hw: float
    line: int
    announces: int


class IrqRecorder:
    """Timestamps of every data, command and motor interrupt the simulator raises.

    Installed on the rig's level-2 and level-3 gates for the duration of a ``with`` block. The
    hook runs in the simulator's thread right after the interrupt was handed to the line: it
    reads ACQ_LINE (to know which acquisition the interrupt announces), appends to a list and,
    with ``listen``, puts the raise on :attr:`events` for a client thread to react to; a few
    microseconds, and inside the figures.
    """

    def __init__(self, rig: SimulatedBiris, *, listen: bool = False) -> None:
        self.rig = rig
        self.listen = listen
        self.data: list[DataRaise] = []
        self.cmd: list[tuple[int, float]] = []
        """(perf_counter_ns, hardware time) of each command-completion interrupt."""
        self.motor: list[tuple[int, float]] = []
        """(perf_counter_ns, hardware time) of each end-of-profile interrupt."""
        self.events: queue.SimpleQueue[DataRaise] = queue.SimpleQueue()
        self._window = rig.hardware.biris
        self._line_at = rig.memory_map.biexec_offset + OFF_ACQ_LINE
        self._now = rig.clock.now
        self._prev_line = ACQ_LINE_END

    def __enter__(self) -> IrqRecorder:
        self.rig.level2_gate.on_raise = self._on_level2
        self.rig.level3_gate.on_raise = self._on_level3
        return self

    def __exit__(self, *exc: object) -> None:
        self.rig.level2_gate.on_raise = None
        self.rig.level3_gate.on_raise = None

    def clear(self) -> None:
        """Forget what was recorded (the next phase of a benchmark starts afresh)."""
        self.data.clear()
        self.cmd.clear()
        self.motor.clear()

    def _on_level2(self, source: str, t_ns: int) -> None:
        if source == "data":
            raw = self._window.read16(self._line_at)
            line = raw - 0x10000 if raw & 0x8000 else raw
            if line == ACQ_LINE_END:
                announces = self._prev_line if self._prev_line >= 0 else -1
            else:
                announces = line - 1 if line > 0 else -1
            self._prev_line = line
            event = DataRaise(t_ns, self._now(), line, announces)
            self.data.append(event)
            if self.listen and announces >= 0:
                self.events.put(event)
        elif source == "cmd":
            self.cmd.append((t_ns, self._now()))

    def _on_level3(self, source: str, t_ns: int) -> None:
        if source == "motor":
            self.motor.append((t_ns, self._now()))

    def announcing(self) -> dict[int, list[int]]:
        """Raise times (ns, ascending) of the data interrupts announcing each acquisition index."""
        out: dict[int, list[int]] = {}
        for event in self.data:
            if event.announces >= 0:
                out.setdefault(event.announces, []).append(event.t_ns)
        return out

    def sequence_spans(self) -> list[tuple[int, int]]:
        """(acquisitions, wall ns) of each complete sequence, start-up excluded.

        From the data interrupt that starts acquisition 0 to the one that announces the last, n
        acquisitions pass: the rate BIRIS (the simulator) actually ran at, which differs from
        nominal when the process cannot keep up (slower, or faster while catching up).
        """
        spans: list[tuple[int, int]] = []
        start: DataRaise | None = None
        for event in self.data:
            if event.line == 0:
                start = event
            elif event.line == ACQ_LINE_END and start is not None:
                n = event.announces + 1
                if n > 1 and event.t_ns > start.t_ns:
                    spans.append((n, event.t_ns - start.t_ns))
                start = None
        return spans

    def lags_hw(self, acquisition_times: Sequence[float], period: float) -> list[float]:
        """How late (hardware seconds) the simulator raised each announcing data interrupt.

        The interrupt announcing acquisition j is due at the end of its exposure: its
        mid-exposure time (``acquisition_times[j]``, the simulator's schedule, exact) plus half
        a period. Raises and acquisitions pair in order, both counted from when this recorder
        was installed, so pass the acquisition times made since then.
        """
        raises = [e for e in self.data if e.announces >= 0]
        return [
            e.t_hw - (t + period / 2.0) for e, t in zip(raises, acquisition_times, strict=False)
        ]


def snap_to(times: Sequence[float], t: float, tolerance: float) -> float | None:
    """The entry of sorted ``times`` nearest ``t``, if within ``tolerance``; else None.

    The server stamps acquisitions with an *estimate* of their mid-exposure time made when it
    reads them, so any delay in reading shifts the estimate by the same amount and would hide
    itself in an age. Snapping to the simulator's exact times removes that.
    """
    i = bisect.bisect_left(times, t)
    best: float | None = None
    for j in (i - 1, i):
        if 0 <= j < len(times) and (best is None or abs(times[j] - t) < abs(best - t)):
            best = times[j]
    return best if best is not None and abs(best - t) <= tolerance else None


# -- CPU -----------------------------------------------------------------------------------------


def _thread_cpu_ns(threads: Iterable[threading.Thread]) -> int:
    """CPU time of these threads, from /proc (0 where unavailable: not Linux, thread gone)."""
    total = 0
    for thread in threads:
        tid = thread.native_id
        if tid is None:
            continue
        try:
            with open(f"/proc/self/task/{tid}/schedstat", encoding="ascii") as f:
                total += int(f.read().split()[0])
        except (OSError, ValueError, IndexError):
            continue
    return total


class CpuMeter:
    """Process CPU over wall time, with the share of named thread groups.

    100 % is one core. ``cpu_percent`` is the whole process (simulator, server and client
    threads: they cannot be run apart in one process); ``<group>_cpu_percent`` comes from the
    per-thread run time the kernel keeps (``/proc/self/task/*/schedstat``) and is absent where
    that is not available. A thread that ends inside the window takes its time with it.
    """

    def __init__(self, groups: dict[str, list[threading.Thread]]) -> None:
        self.groups = groups
        self.values: dict[str, float] = {}

    def __enter__(self) -> CpuMeter:
        self._wall0 = time.perf_counter()
        self._cpu0 = time.process_time()
        self._thread0 = {name: _thread_cpu_ns(ts) for name, ts in self.groups.items()}
        return self

    def __exit__(self, *exc: object) -> None:
        wall = time.perf_counter() - self._wall0
        cpu = time.process_time() - self._cpu0
        self.values = {"cpu_percent": 100.0 * cpu / wall if wall > 0 else float("nan")}
        if os.path.exists("/proc/self/task"):
            for name, threads in self.groups.items():
                used = (_thread_cpu_ns(threads) - self._thread0[name]) / _NANO
                self.values[f"{name}_cpu_percent"] = 100.0 * used / wall if wall > 0 else 0.0
        self.values["wall_s"] = wall


# -- contention ----------------------------------------------------------------------------------


def load_average() -> float:
    """The machine's 1-minute load average (NaN where the platform has none).

    Written beside quiet and contended figures alike: other people's work on a shared machine
    moves every figure, and without the load a quiet figure cannot be told from a contended one.
    """
    try:
        return os.getloadavg()[0]
    except OSError:
        return math.nan


def _process_cpu_s(pid: int) -> float:
    """User + system CPU seconds a process has used, from /proc (0 where unavailable)."""
    try:
        with open(f"/proc/{pid}/stat", encoding="ascii") as f:
            fields = f.read().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


@dataclass
class Contention:
    """What ran beside a contended measurement, for its figure: filled in by :func:`contended`."""

    processes: int
    load_cpu_percent: float = math.nan
    """CPU the load processes got together, % of one core, over the block (from /proc)."""
    loadavg_before: float = math.nan
    loadavg_after: float = math.nan
    values: dict[str, float] = field(default_factory=dict)
    """The above as a figure's values (``load_processes``, ``load_cpu_percent``, ...)."""

    def describe(self) -> str:
        """One sentence for a figure's method."""
        return (
            f"{self.processes} CPU-bound processes (sim.hostload.busy_processes: a pure-Python "
            "loop each, nice 0) ran beside the server for the whole measurement; together they "
            f"got {self.load_cpu_percent:.0f} % of one core, and the 1-minute load average went "
            f"from {self.loadavg_before:.2f} to {self.loadavg_after:.2f}."
        )


@contextmanager
def contended(processes: int = CONTENDING_PROCESSES) -> Iterator[Contention]:
    """CPU-bound processes beside the block (spinning from its first line, reaped after it),
    and how much CPU they got: the load that makes a figure ``_contended``."""
    contention = Contention(processes)
    with busy_processes(processes) as load:
        contention.loadavg_before = load_average()
        cpu0 = sum(_process_cpu_s(pid) for pid in load.pids)
        wall0 = time.perf_counter()
        yield contention
        wall = time.perf_counter() - wall0
        cpu = sum(_process_cpu_s(pid) for pid in load.pids) - cpu0
        contention.loadavg_after = load_average()
    contention.load_cpu_percent = 100.0 * cpu / wall if wall > 0 else math.nan
    contention.values = {
        "load_processes": float(processes),
        "load_cpu_percent": contention.load_cpu_percent,
        "loadavg_before": contention.loadavg_before,
        "loadavg_after": contention.loadavg_after,
    }


def against_quiet(
    contended_values: Mapping[str, float], quiet_values: Mapping[str, float]
) -> dict[str, float]:
    """The quiet figure's p50 and p99 beside the contended one's, and contended / quiet."""
    out: dict[str, float] = {}
    for key in ("p50", "p99"):
        quiet = quiet_values[key]
        out[f"quiet_{key}"] = quiet
        out[f"ratio_{key}"] = contended_values[key] / quiet if quiet > 0 else math.nan
    return out

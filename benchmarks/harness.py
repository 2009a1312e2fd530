"""The benchmark harness: figures, targets, the registry, the runner and the command line.

Benchmarks are not tests. A figure that misses its target, or a benchmark that raises, is written
into the report and the suite carries on, so one slow or broken benchmark never hides the others
and never fails the build. Only a harness error (bad options, a report that cannot be written)
gives a non-zero exit status.
"""

from __future__ import annotations

import argparse
import gc
import importlib
import math
import operator
import pkgutil
import sys
import tempfile
import time
import traceback
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, TypeAlias

__all__ = [
    "SECTIONS",
    "BenchContext",
    "BenchSkipped",
    "Benchmark",
    "Figure",
    "Outcome",
    "Registry",
    "Target",
    "benchmark",
    "interleaved_rounds",
    "main",
    "percentile",
    "registry",
    "run_suite",
    "summarise",
]

SECTIONS: tuple[str, ...] = (
    "latency_us",
    "presentation_ms",
    "throughput",
    "virtual_time",
    "fanout",
    "registers",
    "sweep_gap_ms",
    "soak",
    "transport_vmusb",
    "transport_can",
    "net",
    "record",
    "idle",
    "cli_startup_ms",
    "moving",
    "grid",
)
"""The report's sections, in report order; each is present in report.json whether it ran or not."""

Op = Literal[">=", ">", "<=", "<", "=="]

_OPS: dict[str, Callable[[float, float], bool]] = {
    ">=": operator.ge,
    ">": operator.gt,
    "<=": operator.le,
    "<": operator.lt,
    "==": operator.eq,
}

# Modules of this package that hold machinery rather than benchmarks.
_NOT_BENCHMARKS = frozenset({"harness", "report", "__main__"})


@dataclass(frozen=True)
class Target:
    """What a figure should reach: ``Target(">=", 10.0, on="ratio")`` reads "ratio >= 10".

    A target names the one value it judges, so a figure can carry supporting numbers (the two
    contenders' rates, percentiles) beside the one the issue sets a goal for.
    """

    op: Op
    value: float
    on: str

    def __post_init__(self) -> None:
        if self.op not in _OPS:
            raise ValueError(f"unknown target operator {self.op!r} (use one of {list(_OPS)})")

    def check(self, values: Mapping[str, float]) -> bool | None:
        """Met or not; ``None`` when the judged value is missing or not a finite number."""
        got = values.get(self.on)
        if got is None or not math.isfinite(got):
            return None
        return _OPS[self.op](got, self.value)

    def __str__(self) -> str:
        return f"{self.on} {self.op} {self.value:g}"


@dataclass(frozen=True)
class Figure:
    """One measured result, as the report shows it.

    ``key`` is a dotted path whose first part is the section (``registers.read16``); ``method``
    says in a sentence or two how the numbers were obtained, because a figure without its method
    cannot be compared with anything. ``note``, when given, is one sentence that report.md shows
    above the section's table: the conclusion a reader should not have to work out.
    """

    key: str
    values: Mapping[str, float]
    unit: str
    method: str
    target: Target | None = None
    note: str = ""

    @property
    def section(self) -> str:
        return self.key.partition(".")[0]

    @property
    def name(self) -> str:
        """The key without its section: the figure's name inside the section."""
        return self.key.partition(".")[2] or self.key

    @property
    def met(self) -> bool | None:
        """Whether the target is reached; ``None`` when there is no target to judge."""
        return None if self.target is None else self.target.check(self.values)


class BenchSkipped(Exception):
    """Raised by a benchmark that cannot run here (a peer library is missing, no hardware).

    The section is reported as skipped with the reason, which is not the same as failed: nothing
    went wrong, there was just nothing to measure.
    """


@dataclass(frozen=True)
class BenchContext:
    """What a benchmark gets from the harness: how hard to try and where it may write."""

    quick: bool
    work_dir: Path
    log: Callable[[str], None] = field(default=lambda _msg: None)

    def pick(self, full: int, quick: int) -> int:
        """A repetition count: ``full`` for a report, ``quick`` for a smoke run."""
        return quick if self.quick else full


Result: TypeAlias = Figure | Iterable[Figure]
BenchFn: TypeAlias = Callable[[BenchContext], Result]


@dataclass(frozen=True)
class Benchmark:
    """A registered benchmark: its section name and the function that measures it."""

    name: str
    fn: BenchFn
    doc: str = ""


class Registry:
    """Benchmarks by section name; the default one discovers this package's modules lazily."""

    def __init__(self, *, discover: bool = False) -> None:
        self._benchmarks: dict[str, Benchmark] = {}
        self._discover = discover
        self._discovered = False
        self.load_errors: dict[str, str] = {}

    def register(self, name: str, fn: BenchFn) -> BenchFn:
        """Add ``fn`` as the benchmark of section ``name``; a second, different one is refused."""
        if not name.isidentifier():
            raise ValueError(f"benchmark name {name!r} must be an identifier (it is a JSON key)")
        known = self._benchmarks.get(name)
        if known is not None and _qualname(known.fn) != _qualname(fn):
            raise ValueError(f"benchmark {name!r} is already registered by {_qualname(known.fn)}")
        doc = (fn.__doc__ or "").strip().splitlines()
        self._benchmarks[name] = Benchmark(name, fn, doc[0] if doc else "")
        return fn

    def benchmarks(self) -> dict[str, Benchmark]:
        """Every benchmark, after importing this package's benchmark modules if not done yet."""
        if self._discover and not self._discovered:
            self._discovered = True
            self._import_package_modules()
        return dict(self._benchmarks)

    def _import_package_modules(self) -> None:
        # Discovery rather than a list, so that engineers adding sections side by side never
        # edit the same line; a module that fails to import is reported, not fatal.
        package = importlib.import_module(__package__ or "benchmarks")
        for info in pkgutil.iter_modules(package.__path__):
            if info.name in _NOT_BENCHMARKS or info.name.startswith("_"):
                continue
            module = f"{package.__name__}.{info.name}"
            try:
                importlib.import_module(module)
            except Exception as exc:
                self.load_errors[module] = _describe(exc)


registry = Registry(discover=True)
"""The suite's registry: every module of ``benchmarks`` registers into it on import."""


def benchmark(name: str, *, into: Registry | None = None) -> Callable[[BenchFn], BenchFn]:
    """Decorator: ``@benchmark("latency_us")`` makes the function that section's benchmark."""

    def decorate(fn: BenchFn) -> BenchFn:
        return (into or registry).register(name, fn)

    return decorate


# -- measuring -----------------------------------------------------------------------------------


def percentile(samples: Sequence[float], q: float) -> float:
    """The ``q``-th percentile (0..100) with linear interpolation, as numpy's default does."""
    if not samples:
        raise ValueError("percentile of no samples")
    ordered = sorted(samples)
    rank = (len(ordered) - 1) * q / 100.0
    low = math.floor(rank)
    high = min(low + 1, len(ordered) - 1)
    return ordered[low] + (ordered[high] - ordered[low]) * (rank - low)


def summarise(samples: Sequence[float], prefix: str = "") -> dict[str, float]:
    """Median, tail percentiles, extremes and count: the shape every figure's spread takes."""
    return {
        f"{prefix}p50": percentile(samples, 50),
        f"{prefix}p90": percentile(samples, 90),
        f"{prefix}p99": percentile(samples, 99),
        f"{prefix}min": min(samples),
        f"{prefix}max": max(samples),
        f"{prefix}n": float(len(samples)),
    }


@contextmanager
def _gc_paused() -> Iterator[None]:
    """No collector pauses inside timed code, as timeit does; restored even on error."""
    was_enabled = gc.isenabled()
    gc.collect()
    gc.disable()
    try:
        yield
    finally:
        if was_enabled:
            gc.enable()


def interleaved_rounds(
    contenders: Mapping[str, Callable[[], float]], rounds: int
) -> dict[str, list[float]]:
    """Run every contender once per round, rotating who goes first; one sample each per round.

    Comparisons are made within one run so that machine load, frequency scaling and cache state
    hit all contenders alike; rotating the order keeps whoever runs first (or last) from always
    getting the warm or the cold slot. A contender returns its own measurement (elapsed
    nanoseconds, say), so the timed region is exactly what it chooses.
    """
    names = list(contenders)
    samples: dict[str, list[float]] = {name: [] for name in names}
    with _gc_paused():
        for i in range(rounds):
            k = i % len(names)
            for name in names[k:] + names[:k]:
                samples[name].append(contenders[name]())
    return samples


# -- running -------------------------------------------------------------------------------------


@dataclass
class Outcome:
    """What became of one section: its figures, or why there are none."""

    section: str
    status: Literal["ok", "failed", "skipped", "not run", "not implemented"]
    figures: list[Figure] = field(default_factory=list)
    seconds: float = 0.0
    error: str = ""
    traceback: str = ""
    reason: str = ""


def run_one(bench: Benchmark, ctx: BenchContext) -> Outcome:
    """Run a benchmark and catch whatever it raises, so the suite always goes on."""
    started = time.perf_counter()
    try:
        result = bench.fn(ctx)
        figures = [result] if isinstance(result, Figure) else list(result)
        for fig in figures:
            if not isinstance(fig, Figure):
                raise TypeError(f"benchmark returned {type(fig).__name__}, not Figure")
            if fig.section != bench.name:
                raise ValueError(f"figure {fig.key!r} is outside section {bench.name!r}")
    except BenchSkipped as exc:
        return Outcome(
            bench.name, "skipped", seconds=time.perf_counter() - started, reason=str(exc)
        )
    except Exception as exc:
        return Outcome(
            bench.name,
            "failed",
            seconds=time.perf_counter() - started,
            error=_describe(exc),
            traceback="".join(traceback.format_exception(type(exc), exc, exc.__traceback__)),
        )
    return Outcome(bench.name, "ok", figures, seconds=time.perf_counter() - started)


def run_suite(
    reg: Registry, only: Sequence[str] | None, quick: bool, log: Callable[[str], None]
) -> list[Outcome]:
    """An outcome for every section (the six, then any extra ones), running those selected."""
    benches = reg.benchmarks()
    order = list(SECTIONS) + sorted(set(benches) - set(SECTIONS))
    outcomes: list[Outcome] = []
    for name in order:
        bench = benches.get(name)
        if bench is None:
            outcomes.append(Outcome(name, "not implemented"))
        elif only is not None and name not in only:
            outcomes.append(Outcome(name, "not run", reason="not selected by --only"))
        else:
            log(f"bench: {name} ...")
            with tempfile.TemporaryDirectory(prefix=f"biris-bench-{name}-") as work:
                outcome = run_one(bench, BenchContext(quick=quick, work_dir=Path(work), log=log))
            log(f"bench: {name} {outcome.status} in {outcome.seconds:.1f} s")
            outcomes.append(outcome)
    return outcomes


def _parse_args(argv: Sequence[str] | None, names: Iterable[str]) -> argparse.Namespace:
    known = sorted(names)
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks",
        description="Run the biris-hw benchmark suite and write report.json and report.md.",
        epilog="Benchmarks never fail the build: exit status 0 unless the options are wrong (2) "
        "or the report cannot be written (1).",
    )
    parser.add_argument(
        "--only",
        metavar="NAME[,NAME]",
        help=f"run only these benchmarks (known: {', '.join(known) or 'none'})",
    )
    parser.add_argument(
        "--quick", action="store_true", help="fewer repetitions: a smoke run, not a report"
    )
    parser.add_argument(
        "--out", type=Path, default=Path("build/bench"), help="report directory (build/bench)"
    )
    parser.add_argument("--list", action="store_true", help="list the benchmarks and exit")
    args = parser.parse_args(argv)
    if args.only is not None:
        wanted = [n.strip() for n in args.only.split(",") if n.strip()]
        unknown = [n for n in wanted if n not in known]
        if not wanted or unknown:
            missing = ", ".join(unknown) if unknown else "(empty list)"
            parser.error(f"--only: no such benchmark: {missing} (known: {', '.join(known)})")
        args.only = wanted
    return args


def main(argv: Sequence[str] | None = None, *, reg: Registry | None = None) -> int:
    """The command line: run, write both reports, say where they are."""
    from benchmarks import report  # the report module imports this one

    def log(msg: str) -> None:
        print(msg, file=sys.stderr, flush=True)

    reg = registry if reg is None else reg
    benches = reg.benchmarks()
    # Said before the options are checked: a section that failed to load is otherwise "unknown".
    for module, error in reg.load_errors.items():
        log(f"bench: could not load {module}: {error}")
    args = _parse_args(argv, benches)
    if args.list:
        for name, bench in sorted(benches.items()):
            print(f"{name:16} {bench.doc}")
        return 0

    started = time.perf_counter()
    outcomes = run_suite(reg, args.only, args.quick, log)
    meta = report.collect_meta(
        seconds=time.perf_counter() - started,
        quick=args.quick,
        only=args.only,
        load_errors=reg.load_errors,
    )
    try:
        paths = report.write_reports(args.out, meta, outcomes)
    except OSError as exc:
        log(f"bench: cannot write the report to {args.out}: {exc}")
        return 1
    for path in paths:
        print(path)
    return 0


def _qualname(fn: Callable[..., object]) -> str:
    """Where a function was defined: the same after a module reload, distinct for two lambdas."""
    code = getattr(fn, "__code__", None)
    line = f":{code.co_firstlineno}" if code is not None else ""
    return f"{getattr(fn, '__module__', '?')}.{getattr(fn, '__qualname__', repr(fn))}{line}"


def _describe(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {exc}"

"""The benchmark suite behind ``make bench`` (``python -m benchmarks`` from the checkout's root).

This folder is not part of the installed distribution: it imports the simulator freely, which
``biris_hw`` may not, and uses only the public API of ``biris_hw`` and ``sim``.

Benchmarks are not tests: they never fail the build. Each section of the report is measured by
one registered function and every figure is written beside its target, met or not, with the
method that produced it, into ``build/bench/report.json`` and ``build/bench/report.md``.

Adding a section (say ``latency_us``) takes one new module in this package, e.g.
``benchmarks/latency.py``; nothing else is edited, because the harness imports every module
of ``benchmarks`` (except ``harness`` and ``report``; helpers such as ``common`` and ``floor``
register nothing and are imported harmlessly) when the suite starts::

    from benchmarks.harness import BenchContext, Figure, Target, benchmark, summarise

    @benchmark("latency_us")          # the section's JSON key; one benchmark per section
    def latency(ctx: BenchContext) -> list[Figure]:
        '''First line: shown by ``--list``.'''
        samples = [...]               # ctx.pick(full=500, quick=20) repetitions; ctx.work_dir
        return [Figure(key="latency_us.data_interrupt", values=summarise(samples), unit="us",
                       target=Target("<=", 500.0, on="p99"),
                       method="One or two sentences on how it was measured.")]

Figures are medians and percentiles over repeated runs (``summarise``); a comparison is a ratio
of two contenders timed in the same run (``interleaved_rounds``). Raise ``BenchSkipped`` when
the section cannot run here; anything else a benchmark raises is recorded as a failure and the
suite goes on. Run one section with ``python -m benchmarks --only latency_us --quick``.
"""

from benchmarks.harness import (
    SECTIONS,
    BenchContext,
    BenchSkipped,
    Figure,
    Registry,
    Target,
    benchmark,
    interleaved_rounds,
    main,
    percentile,
    registry,
    summarise,
)

__all__ = [
    "SECTIONS",
    "BenchContext",
    "BenchSkipped",
    "Figure",
    "Registry",
    "Target",
    "benchmark",
    "interleaved_rounds",
    "main",
    "percentile",
    "registry",
    "summarise",
]

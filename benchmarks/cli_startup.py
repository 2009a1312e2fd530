"""How long ``biris`` takes to start: ``biris --help``, ``biris --version``, a command's help.

A command-line tool that takes half a second to print its help feels broken, and ``biris --help``
used to load the whole server (23 of its modules, numpy and the hardware layers: 0.4 to 2.5 s on a
2-core machine). The dispatcher now imports a command's module only when that command runs, and
what it imports to run any command (how to fail, what to tell a person) loads nothing of the
server. The target is 0.3 s on 2 cores for ``--help`` and ``--version``; the bare interpreter's
start is measured in the same rounds, so that a slow machine's share of the figure shows.

Each figure is wall-clock time of a fresh process, spawn to exit, over interleaved rounds
(every contender once per round, the order rotated). ``tests/test_cli_startup.py`` holds what is
imported; this module only measures how long it takes.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from time import perf_counter_ns

from benchmarks.harness import (
    BenchContext,
    Figure,
    Target,
    benchmark,
    interleaved_rounds,
    summarise,
)

__all__ = ["START_TARGET_MS", "biris_command", "cli_startup"]

START_TARGET_MS = 300.0
"""``biris --help`` and ``biris --version`` start and end within this, median, on 2 cores."""


def biris_command() -> list[str]:
    """How to run ``biris``: the installed console script beside this interpreter (what a
    person types), or the dispatcher through this interpreter when there is none."""
    script = Path(sys.executable).with_name("biris")
    if script.is_file():
        return [str(script)]
    found = shutil.which("biris")
    if found is not None:
        return [found]
    return [sys.executable, "-c", "import sys; from biris_hw.cli import main; sys.exit(main())"]


def _timed(argv: Sequence[str]) -> Callable[[], float]:
    """Runs ``argv`` to its end; returns the nanoseconds from spawn to exit."""

    def run() -> float:
        started = perf_counter_ns()
        done = subprocess.run(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, check=False)
        elapsed = perf_counter_ns() - started
        if done.returncode != 0:
            raise RuntimeError(f"{' '.join(argv)} exited {done.returncode}: {done.stderr!r}")
        return float(elapsed)

    return run


@benchmark("cli_startup_ms")
def cli_startup(ctx: BenchContext) -> list[Figure]:
    """Wall-clock start of biris --help, --version and scan --help, beside a bare interpreter."""
    biris = biris_command()
    rounds = ctx.pick(full=21, quick=5)
    contenders = {
        "help": _timed([*biris, "--help"]),
        "version": _timed([*biris, "--version"]),
        "scan_help": _timed([*biris, "scan", "--help"]),
        "interpreter": _timed([sys.executable, "-c", "pass"]),
    }
    for run in contenders.values():  # warm the page cache and the bytecode files once
        run()
    ns = interleaved_rounds(contenders, rounds)
    ms = {name: [sample / 1e6 for sample in samples] for name, samples in ns.items()}
    how = (
        f"{rounds} interleaved rounds of a fresh process, spawn to exit (wall clock), run as "
        f"`{Path(biris[0]).name}`; p50 is the median."
    )
    return [
        Figure(
            key="cli_startup_ms.help",
            values=summarise(ms["help"]),
            unit="ms",
            target=Target("<=", START_TARGET_MS, on="p50"),
            method=f"`biris --help`: {how}",
            note="biris --help and --version load no server module, no numpy and no command "
            "module; the interpreter's own start is the floor under every figure.",
        ),
        Figure(
            key="cli_startup_ms.version",
            values=summarise(ms["version"]),
            unit="ms",
            target=Target("<=", START_TARGET_MS, on="p50"),
            method=f"`biris --version`: {how}",
        ),
        Figure(
            key="cli_startup_ms.scan_help",
            values=summarise(ms["scan_help"]),
            unit="ms",
            method=f"`biris scan --help` (imports the scan command and its flags, not the "
            f"server; numpy comes with the register layout's sample counts): {how}",
        ),
        Figure(
            key="cli_startup_ms.interpreter",
            values=summarise(ms["interpreter"]),
            unit="ms",
            method=f"`python -c pass` with the same interpreter: the floor. {how}",
        ),
    ]

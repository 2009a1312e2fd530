"""The benchmark harness: both reports, every section, failures recorded, targets judged."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import benchmarks.harness as harness_module
from benchmarks import SECTIONS, BenchContext, BenchSkipped, Figure, Registry, Target, main
from benchmarks.harness import interleaved_rounds, percentile, registry, run_one, summarise

ROOT = Path(__file__).resolve().parent.parent


def figure(key: str, target: Target | None = None, **values: float) -> Figure:
    return Figure(key=key, values=values, unit="x", method="counted", target=target)


def run(reg: Registry, out: Path, *args: str) -> dict[str, Any]:
    assert main(["--out", str(out), *args], reg=reg) == 0
    doc: dict[str, Any] = json.loads((out / "report.json").read_text())
    return doc


@pytest.fixture
def reg() -> Registry:
    """Three benchmarks: one that raises (and runs first), one that works, one that skips."""
    reg = Registry()

    def throughput(ctx: BenchContext) -> Figure:
        raise RuntimeError("boom in throughput")

    def fanout(ctx: BenchContext) -> list[Figure]:
        assert ctx.quick and ctx.work_dir.is_dir()
        return [
            figure("fanout.good", Target(">=", 2.0, on="ratio"), ratio=3.0, n=5),
            figure("fanout.bad", Target("<=", 1.0, on="p99"), p99=4.0),
            figure("fanout.plain", None, p50=1.5),
        ]

    def latency_us(ctx: BenchContext) -> Figure:
        raise BenchSkipped("no hardware here")

    reg.register("throughput", throughput)
    reg.register("fanout", fanout)
    reg.register("latency_us", latency_us)
    return reg


# -- reports -------------------------------------------------------------------------------------


def test_both_reports_have_meta_and_all_six_sections(reg: Registry, tmp_path: Path) -> None:
    doc = run(reg, tmp_path, "--quick")
    assert list(doc) == ["meta", *SECTIONS]
    for key in ("python", "platform", "cpu_count", "date", "git_commit", "seconds"):
        assert key in doc["meta"]
    assert doc["presentation_ms"] == {"status": "not implemented"}
    assert doc["sweep_gap_ms"] == {"status": "not implemented"}
    md = (tmp_path / "report.md").read_text()
    for section in SECTIONS:
        assert f"## {section}" in md
    assert "| figure | value | target | met | method |" in md


def test_a_raising_benchmark_is_recorded_and_the_suite_goes_on(
    reg: Registry, tmp_path: Path
) -> None:
    doc = run(reg, tmp_path, "--quick")
    failed = doc["throughput"]
    assert failed["status"] == "failed"
    assert failed["error"] == "RuntimeError: boom in throughput"
    assert "Traceback" in failed["traceback"]
    assert doc["fanout"]["status"] == "ok"  # ran after the failure
    assert doc["latency_us"] == {
        "status": "skipped",
        "seconds": pytest.approx(0, abs=1),
        "reason": "no hardware here",
    }
    md = (tmp_path / "report.md").read_text()
    assert "**Failed**" in md and "boom in throughput" in md
    assert "Skipped: no hardware here" in md


def test_met_and_not_met_come_from_the_targets(reg: Registry, tmp_path: Path) -> None:
    doc = run(reg, tmp_path, "--quick")
    figures = doc["fanout"]["figures"]
    assert figures["good"]["met"] is True
    assert figures["good"]["target"] == {
        "op": ">=",
        "value": 2.0,
        "on": "ratio",
        "text": "ratio >= 2",
    }
    assert figures["bad"]["met"] is False
    assert figures["plain"]["met"] is None and figures["plain"]["target"] is None
    assert doc["meta"]["summary"] == {"met": 1, "not_met": 1, "no_target": 1}
    md = (tmp_path / "report.md").read_text()
    assert "| good (x) | **ratio 3**; n 5 | ratio >= 2 | met | counted |" in md
    assert "| bad (x) | **p99 4** | p99 <= 1 | **not met** | counted |" in md


def test_only_runs_the_named_benchmarks(reg: Registry, tmp_path: Path) -> None:
    doc = run(reg, tmp_path, "--only", "fanout", "--quick")
    assert doc["fanout"]["status"] == "ok"
    assert doc["throughput"] == {"status": "not run", "reason": "not selected by --only"}
    assert doc["meta"]["only"] == ["fanout"]


def test_target_judges_its_own_value() -> None:
    assert Target(">=", 1.0, on="ratio").check({"ratio": 1.0}) is True
    assert Target(">", 1.0, on="ratio").check({"ratio": 1.0}) is False
    assert Target("<", 5.0, on="p99").check({"p99": 4.9, "ratio": 99.0}) is True
    assert Target(">=", 1.0, on="ratio").check({"p50": 3.0}) is None
    assert Target(">=", 1.0, on="ratio").check({"ratio": math.nan}) is None
    assert figure("s.f", None, ratio=3.0).met is None
    assert figure("s.f", Target("==", 3.0, on="ratio"), ratio=3.0).met is True
    with pytest.raises(ValueError, match="operator"):
        Target("=>", 1.0, on="ratio")  # type: ignore[arg-type]


def test_a_figure_outside_its_section_or_not_a_figure_is_a_failure() -> None:
    reg = Registry()
    reg.register("fanout", lambda ctx: figure("throughput.x", None, n=1))
    reg.register("throughput", lambda ctx: [42])  # type: ignore[list-item]
    ctx = BenchContext(quick=True, work_dir=Path("."))
    benches = reg.benchmarks()
    assert "outside section" in run_one(benches["fanout"], ctx).error
    assert run_one(benches["throughput"], ctx).error.startswith("TypeError")


def test_registering_a_second_function_for_a_section_is_refused() -> None:
    reg = Registry()
    reg.register("fanout", lambda ctx: [])
    with pytest.raises(ValueError, match="already registered"):
        reg.register("fanout", lambda ctx: [])
    with pytest.raises(ValueError, match="identifier"):
        reg.register("not-a-key", lambda ctx: [])


# -- statistics ----------------------------------------------------------------------------------


def test_percentiles_agree_with_numpy() -> None:
    samples = [5.0, 1.0, 9.0, 3.0, 7.0, 2.0]
    for q in (0, 10, 50, 90, 99, 100):
        assert percentile(samples, q) == pytest.approx(float(np.percentile(samples, q)))
    summary = summarise(samples, prefix="t_")
    assert summary["t_p50"] == pytest.approx(4.0)
    assert (summary["t_min"], summary["t_max"], summary["t_n"]) == (1.0, 9.0, 6.0)


@pytest.fixture
def no_full_collections(monkeypatch: pytest.MonkeyPatch) -> None:
    """The timed blocks skip their opening full collection (``_gc_paused``): a test checks what
    the rounds hand back, not their timing, and in a test process's large heap a collection
    takes a quarter of a second."""
    monkeypatch.setattr(harness_module.gc, "collect", lambda *generation: 0)


def test_interleaved_rounds_rotate_who_goes_first(no_full_collections: None) -> None:
    calls: list[str] = []

    def contender(name: str) -> Callable[[], float]:
        def measure() -> float:
            calls.append(name)
            return float(len(calls))

        return measure

    samples = interleaved_rounds({n: contender(n) for n in "abc"}, rounds=3)
    assert calls == list("abcbcacab")
    assert [len(s) for s in samples.values()] == [3, 3, 3]


# -- the registers benchmark ---------------------------------------------------------------------


@pytest.mark.slow
def test_registers_quick_run_gives_positive_figures(tmp_path: Path) -> None:
    pytest.importorskip("periphery")
    doc = run(registry, tmp_path, "--only", "registers", "--quick")
    section = doc["registers"]
    assert section["status"] == "ok", section.get("error")
    figures = section["figures"]
    assert set(figures) == {"read8", "read16", "write16", "frame129"}
    for fig in figures.values():
        assert fig["met"] in (True, False)
        assert fig["method"]
        for name, value in fig["values"].items():
            assert value is not None and value > 0, name
    assert figures["read16"]["target"]["text"] == "ratio >= 1"
    assert figures["frame129"]["target"]["text"] == "ratio >= 10"
    assert "ratio_vs_bulk" in figures["frame129"]["values"]


def test_registers_is_skipped_without_periphery(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.setitem(sys.modules, "periphery", None)  # import now raises ImportError
    bench = registry.benchmarks()["registers"]
    outcome = run_one(bench, BenchContext(quick=True, work_dir=tmp_path))
    assert outcome.status == "skipped"
    assert "python-periphery is not installed" in outcome.reason


# -- the command line ----------------------------------------------------------------------------


@pytest.mark.parametrize("args", [["--only", "nosuch"], ["--only", ","], ["--bogus"]])
def test_bad_options_exit_2(reg: Registry, tmp_path: Path, args: list[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main([*args, "--out", str(tmp_path)], reg=reg)
    assert exc.value.code == 2
    assert not (tmp_path / "report.json").exists()


def test_an_unwritable_report_exits_1(reg: Registry, tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("")
    assert main(["--quick", "--only", "fanout", "--out", str(blocker)], reg=reg) == 1


@pytest.mark.slow  # fast-tier budget (issue 13 added the transports); make test-slow
def test_the_module_and_the_tools_script_run_from_a_checkout(tmp_path: Path) -> None:
    bad = subprocess.run(
        [sys.executable, "-m", "benchmarks", "--only", "nosuch"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert bad.returncode == 2 and "no such benchmark: nosuch" in bad.stderr
    listed = subprocess.run(
        [sys.executable, str(ROOT / "tools" / "bench.py"), "--list"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert listed.returncode == 0 and "registers" in listed.stdout.split()


# -- the transport_vmusb benchmark ---------------------------------------------------------------


def test_transport_vmusb_is_a_section_and_counts_the_transfers_of_one_access(
    no_full_collections: None,
) -> None:
    """The register-access part alone (the rest needs a rig and most of a minute): one round
    each, and the transfer counts the section's targets judge."""
    from benchmarks.transport_vmusb import register_costs

    assert "transport_vmusb" in SECTIONS and "transport_vmusb" in registry.benchmarks()
    figures = {f.name: f for f in register_costs(rounds=1, batch_ms=1)}
    assert set(figures) == {
        f"register_{op}{armed}"
        for op in ("read8", "read16", "frame129")
        for armed in ("", "_irq_armed")
    }
    for name, fig in figures.items():
        assert fig.met is True, (name, fig.values)
        assert fig.values["vmusb_us"] > fig.values["memory_us"] > 0
        assert fig.values["modelled_hw_us"] >= (625.0 if "armed" in name else 250.0)

"""The line at the end of every run: its CPU, and the machine's idle and stolen time
(tests/run_figures.py)."""

from __future__ import annotations

from pathlib import Path

from tests.run_figures import MachineTicks, describe, parse_stat, read_ticks

STAT = """cpu  100 5 20 300 10 1 2 40 7 0
cpu0 50 2 10 150 5 0 1 20 7 0
cpu1 50 3 10 150 5 1 1 20 0 0
intr 12345
"""


def test_the_aggregate_cpu_line_is_read_and_guest_time_not_counted_twice() -> None:
    # user nice system idle iowait irq softirq steal | guest guest_nice (in user already)
    assert parse_stat(STAT) == MachineTicks(total=478, idle=310, steal=40)


def test_a_text_without_a_whole_cpu_line_gives_nothing() -> None:
    assert parse_stat("intr 1\nctxt 2\n") is None
    assert parse_stat("cpu 1 2 3\n") is None
    assert parse_stat("cpu 1 2 x 4 5 6 7 8\n") is None


def test_no_proc_stat_gives_nothing(tmp_path: Path) -> None:
    assert read_ticks(tmp_path / "absent") is None


def test_the_line_says_cpu_share_idle_and_steal() -> None:
    before = MachineTicks(total=1000, idle=400, steal=0)
    after = MachineTicks(total=1000 + 2 * 7000, idle=400 + 1400, steal=700)
    assert describe(70.0, 119.0, 2, before, after) == (
        "the run: 70.0 s, 119.0 s of CPU in its processes (85% of 2 cores); "
        "the machine meanwhile: 10% idle, 5% stolen by its host"
    )


def test_without_the_machine_counters_only_the_run_is_said() -> None:
    assert describe(10.0, 5.0, 1, None, None) == (
        "the run: 10.0 s, 5.0 s of CPU in its processes (50% of 1 core)"
    )
    same = MachineTicks(total=5, idle=1, steal=0)
    assert describe(10.0, 5.0, 1, same, same).endswith("(50% of 1 core)")

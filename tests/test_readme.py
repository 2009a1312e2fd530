"""Every complete Python example in the README and in docs/*.md runs exactly as written."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from tests.conftest import affinity_allowed

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
DOCS = sorted((ROOT / "docs").glob("*.md"))


def _python_blocks(page: Path) -> list[str]:
    text = page.read_text(encoding="utf-8")
    return re.findall(r"```python\n(.*?)```", text, flags=re.DOTALL)


def _complete_examples(page: Path) -> list[str]:
    """Blocks that stand alone (they import what they use and build a rig); fragments that
    continue an earlier example are left out."""
    return [
        block
        for block in _python_blocks(page)
        if block.startswith(("from ", "import ")) and "with SimulatedBiris(" in block
    ]


def _all_examples() -> list[tuple[Path, str]]:
    return [(page, block) for page in [README, *DOCS] for block in _complete_examples(page)]


def _example_id(example: tuple[Path, str]) -> str:
    page, block = example
    return f"{page.relative_to(ROOT)}:{block.splitlines()[-1].strip()[:40]}"


def test_the_readme_has_its_examples() -> None:
    assert _complete_examples(README), "README.md lost its runnable Python session"
    assert len(_all_examples()) >= 8, "README.md and docs/*.md lost runnable Python examples"


def _tiered(example: tuple[Path, str]) -> object:
    """The README's examples run in the fast tier; the longer pages' in ``make test-slow``
    (fast-tier budget, issues 13-15)."""
    marks = [] if example[0] == README else [pytest.mark.slow]
    return pytest.param(example, id=_example_id(example), marks=marks)


@pytest.mark.parametrize("example", [_tiered(e) for e in _all_examples()])
def test_example_runs_as_written(
    example: tuple[Path, str],
    no_leaks: None,
    capsys: pytest.CaptureFixture[str],
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    page, block = example
    monkeypatch.chdir(tmp_path)  # an example that writes a file ("run.mcap") writes it there
    if "biris_hw.affinity" in block and not affinity_allowed():
        pytest.skip("this platform does not let a thread choose its CPUs")
    exec(compile(block, str(page), "exec"), {"__name__": "__readme__"})
    out = capsys.readouterr().out
    assert out.strip(), "the example printed nothing"
    assert "Traceback" not in out


@pytest.mark.slow  # fast-tier budget (issue 13 added the transports); make test-slow
def test_the_first_example_shows_the_whole_session(capsys: pytest.CaptureFixture[str]) -> None:
    exec(compile(_complete_examples(README)[0], str(README), "exec"), {"__name__": "__readme__"})
    out = capsys.readouterr().out
    assert "acquisitions of 64 samples" in out
    assert "fault: parity" in out

"""Every complete Python example in the README runs exactly as written."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from tests.conftest import affinity_allowed

README = Path(__file__).resolve().parent.parent / "README.md"


def _python_blocks() -> list[str]:
    text = README.read_text(encoding="utf-8")
    return re.findall(r"```python\n(.*?)```", text, flags=re.DOTALL)


def _complete_examples() -> list[str]:
    """Blocks that stand alone (they import what they use and build a rig); fragments that
    continue an earlier example are left out."""
    return [
        block
        for block in _python_blocks()
        if block.startswith(("from ", "import ")) and "with SimulatedBiris(" in block
    ]


def test_the_readme_has_its_examples() -> None:
    assert len(_complete_examples()) >= 7, "README.md lost runnable Python examples"


@pytest.mark.parametrize(
    "block", _complete_examples(), ids=lambda b: b.splitlines()[-1].strip()[:40]
)
def test_readme_example_runs_as_written(
    block: str, no_leaks: None, capsys: pytest.CaptureFixture[str]
) -> None:
    if "biris_hw.affinity" in block and not affinity_allowed():
        pytest.skip("this platform does not let a thread choose its CPUs")
    exec(compile(block, str(README), "exec"), {"__name__": "__readme__"})
    out = capsys.readouterr().out
    assert out.strip(), "the example printed nothing"
    assert "Traceback" not in out


def test_the_first_example_shows_the_whole_session(capsys: pytest.CaptureFixture[str]) -> None:
    exec(compile(_complete_examples()[0], str(README), "exec"), {"__name__": "__readme__"})
    out = capsys.readouterr().out
    assert "acquisitions of 64 samples" in out
    assert "fault: parity" in out

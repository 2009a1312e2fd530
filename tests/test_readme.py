"""The README's Python example runs exactly as written."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

README = Path(__file__).resolve().parent.parent / "README.md"


def _python_blocks() -> list[str]:
    text = README.read_text(encoding="utf-8")
    return re.findall(r"```python\n(.*?)```", text, flags=re.DOTALL)


def _complete_examples() -> list[str]:
    """Blocks that stand alone (they import what they use); fragments are left out."""
    return [block for block in _python_blocks() if block.startswith("from ") and "with " in block]


def test_the_readme_has_a_complete_example() -> None:
    assert _complete_examples(), "README.md lost its runnable Python example"


@pytest.mark.parametrize("block", _complete_examples())
def test_readme_example_runs_as_written(
    block: str, no_leaks: None, capsys: pytest.CaptureFixture[str]
) -> None:
    exec(compile(block, str(README), "exec"), {"__name__": "__readme__"})
    out = capsys.readouterr().out
    assert "acquisitions" in out
    assert "fault: parity" in out

"""The packages import and the console script answers."""

import ctypes

import pytest

from biris_hw.cli import main
from regs.biexec import BiexecCom


def test_biexec_com_is_80_bytes() -> None:
    assert ctypes.sizeof(BiexecCom) == 80


def test_the_demo_command_answers_help(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["demo", "--help"]) == 0  # main returns the exit status, it never exits
    assert "--duration" in capsys.readouterr().out

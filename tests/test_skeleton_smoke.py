"""The packages import and the console script answers."""

import ctypes

from biris_hw.cli import main
from regs.biexec import BiexecCom


def test_biexec_com_is_80_bytes() -> None:
    assert ctypes.sizeof(BiexecCom) == 80


def test_demo_placeholder_runs() -> None:
    assert main(["demo"]) == 0

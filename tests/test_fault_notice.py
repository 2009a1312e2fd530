"""FaultNotice: what ``biris watch`` / ``biris view`` say on stderr as faults come and go,
judged on statuses alone (no server: the fault's own message comes from a stand-in)."""

from __future__ import annotations

import argparse
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import pytest

from biris_hw.commands.faults import FaultNotice
from biris_hw.errors import HardwareFault
from biris_hw.status import ServerState
from tests.conftest import idle_status


class _Conn:
    def __init__(self, fault: HardwareFault | None) -> None:
        self._fault = fault

    def wait_idle(self, timeout: float | None = None) -> None:
        if self._fault is not None:
            raise self._fault


class _Server:
    """Answers the notice's poll with the fault it is told it is in."""

    def __init__(self) -> None:
        self.fault: HardwareFault | None = None

    @contextmanager
    def open(self) -> Iterator[_Conn]:
        yield _Conn(self.fault)


def _notice(server: _Server) -> FaultNotice:
    args = argparse.Namespace(command="watch")
    return FaultNotice(server, args, "watch goes on")  # type: ignore[arg-type]


def _status(faults: int, fault: str | None = None, **changes: Any) -> Any:
    state = ServerState.FAULT if fault else ServerState.IDLE
    return idle_status(state=state, fault=fault, counters={"faults": faults}, **changes)


def _said(capsys: pytest.CaptureFixture[str]) -> list[str]:
    return capsys.readouterr().err.splitlines()


def test_a_fault_is_said_once_with_its_message_and_its_end(
    capsys: pytest.CaptureFixture[str],
) -> None:
    server = _Server()
    notice = _notice(server)
    assert not notice.observe(_status(0))
    server.fault = HardwareFault("parity", "parity error on the coupler")
    assert notice.observe(_status(1, "parity"))
    assert notice.observe(_status(1, "parity"))
    assert notice.exit_status() == 1
    assert not notice.observe(_status(1))
    assert notice.exit_status() == 0
    said = _said(capsys)
    assert len(said) == 3, said
    assert "parity error on the coupler" in said[0]
    assert said[1] == "biris watch: ended with the server still in the fault (parity)"
    assert said[2] == "biris watch: the server has left the fault (state idle)"


def test_a_fault_met_first_hand_is_said_though_a_reset_cleared_it(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """A request of the command's own failed with the fault; by the time it reads the status a
    reset elsewhere cleared it: the fault is still said, with its message, then its end."""
    notice = _notice(_Server())
    notice.observe(_status(0))
    notice.met(HardwareFault("motor_stall", "the pan motor stalled"))
    notice.met(HardwareFault("motor_stall", "the pan motor stalled"))  # the same: said once
    assert not notice.observe(_status(1))
    said = _said(capsys)
    assert len(said) == 2, said
    assert "the pan motor stalled" in said[0]
    assert said[1] == "biris watch: the server has left the fault (state idle)"


def test_a_fault_between_two_looks_is_not_silent(capsys: pytest.CaptureFixture[str]) -> None:
    """Neither look saw the fault state, but the server counted a fault between them."""
    notice = _notice(_Server())
    notice.observe(_status(3))
    notice.observe(_status(3))
    assert _said(capsys) == []
    notice.observe(_status(4))
    said = _said(capsys)
    assert said == [
        "biris watch: the server met a hardware fault and was reset between two looks "
        "(faults counted: 4); its state is idle"
    ]
    notice.observe(_status(4))
    assert _said(capsys) == []

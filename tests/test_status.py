"""``ServerStatus``: typed attributes, and the mapping reading that callers of the old dict use."""

from __future__ import annotations

import dataclasses

import pytest

from biris_hw.data import ConnectionKind
from biris_hw.server import messages as m
from biris_hw.status import ConnectionStatus, ServerState, ServerStatus
from tests.core import Core


def test_status_is_typed_and_reads_as_the_old_mapping() -> None:
    core = Core()
    core.initialise()
    data = core.open(ConnectionKind.DATA)
    status = core.admin.status()
    assert isinstance(status, ServerStatus)
    assert status.state is ServerState.IDLE and status.fault is None
    assert status["state"] == "idle" and status["azimuth"] == status.azimuth == 0
    assert status["counters"]["scans"] == 0
    conn = status.connections[data]
    assert isinstance(conn, ConnectionStatus) and conn["kind"] == "DATA" and conn.queued == 0
    assert set(status) >= {"state", "fault", "azimuth", "counters", "connections", "interrupts"}
    assert dict(status)["state"] == "idle"
    with pytest.raises(KeyError):
        status["no such key"]
    with pytest.raises(dataclasses.FrozenInstanceError):
        status.azimuth = 5  # type: ignore[misc]


def test_a_fault_is_a_state_with_its_kind_beside_it() -> None:
    core = Core()
    core.initialise()
    core.send(m.BirisParityErr())
    status = core.admin.status()
    assert status.state is ServerState.FAULT and status.fault == "parity"
    assert status["state"] == "fault:parity" and status.state_name == "fault:parity"
    assert status.counters["faults"] == 1

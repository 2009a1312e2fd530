"""A new driver (or a reset) waits for a busy BIRIS before its first command (issue 11, defect 8).

A driver that dies mid-scan leaves BIRIS executing its BI_ACQUIRE; a command written meanwhile is
lost, and the simulator's audit records CMD_WHILE_BUSY (checked after every test, see conftest).
Each test also spies on the bundle's BIEXEC_COM driver and asserts that COMMAND read 0 whenever a
command was written, which is the rule itself rather than its symptom. A BIRIS that never
finishes is a HardwareFault("timeout") once the bound derived from what it runs has passed.
"""

from __future__ import annotations

import pytest

from biris_hw import BirisInitRecord, Direction, MotorParams
from biris_hw.devices import BirisLink
from biris_hw.errors import HardwareFault
from biris_hw.server import BirisServer
from biris_hw.server.initialiser import LONGEST_ACQUISITION_S
from regs.biexec import BiCommand
from regs.layout import STARTUP_LATENCY_S
from sim import SimulatedBiris
from tests.conftest import RigFactory, until

WAIT = 30.0
"""Real seconds for what takes well under one at x30; reached only when a test fails."""


class Writes:
    """COMMAND as it read just before each command the bundle's link wrote."""

    def __init__(self, link: BirisLink, mp: pytest.MonkeyPatch) -> None:
        self.before: list[tuple[int, int]] = []
        issue = link.issue

        def spy(code: int, param: str) -> None:
            self.before.append((code, link.command()))
            issue(code, param)

        mp.setattr(link, "issue", spy)

    def assert_never_while_busy(self) -> None:
        assert self.before, "no command was written"
        busy = [(code, was) for code, was in self.before if was != 0]
        assert not busy, f"commands written while COMMAND was non-zero: {busy}"


def _boot(rig: SimulatedBiris, record: BirisInitRecord) -> None:
    """A first driver that initialised (BIRIS booted) and went away."""
    with BirisServer(rig.hardware, record):
        pass


@pytest.mark.slow  # fast-tier budget (issue 13 added the transports); make test-slow
def test_a_restarted_driver_waits_for_the_old_drivers_scan(
    make_rig: RigFactory, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The repro: the driver goes away at the start of a 720-degree scan; the new one
    initialises without writing over BIRIS's running BI_ACQUIRE, and homes to true zero."""
    rig = make_rig()
    first = BirisServer(rig.hardware, BirisInitRecord())
    try:
        conn = first.open()
        conn.set_motor_params(MotorParams(max_vel=1))  # half speed: a long BI_ACQUIRE
        conn.single_scan(-360.0)
        conn.wait_idle(timeout=WAIT)
        conn.single_scan(360.0)
        until(lambda: rig.supervisor.busy, what="BIRIS executing the scan's BI_ACQUIRE")
    finally:
        first.close()  # the driver goes away mid-scan (a crash, a restart)
    assert rig.supervisor.busy, "the scan ended before the driver went away: nothing to test"
    writes = Writes(rig.hardware.devices.link, monkeypatch)
    with BirisServer(rig.hardware, BirisInitRecord()) as second:
        assert second.status()["state"] == "idle"
        conn = second.open()
        conn.single_scan(45.0)
        conn.wait_idle(timeout=WAIT)
        scan = conn.request_scan_data(Direction.CCW)
        assert scan is not None and scan.n_acq > 0
    writes.assert_never_while_busy()
    assert abs(rig.azimuth_counts - 512) <= 3  # homed to true zero, then 45 degrees


@pytest.mark.slow
def test_the_old_acquisition_runs_to_its_end(
    make_rig: RigFactory, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A BI_ACQUIRE the dead driver wrote (300 acquisitions, 10 s of hardware time) is waited
    for, not written over: BIRIS completes every acquisition of it."""
    rig = make_rig()
    record = BirisInitRecord()
    _boot(rig, record)
    writes = Writes(rig.hardware.devices.link, monkeypatch)
    made = rig.supervisor.acquisitions_made
    rig.hardware.devices.link.issue(BiCommand.BI_ACQUIRE, "300")  # the dead driver's last word
    writes.before.clear()
    with BirisServer(rig.hardware, record) as server:
        assert server.status()["state"] == "idle"
        assert rig.supervisor.acquisitions_made - made == 300
    writes.assert_never_while_busy()


@pytest.mark.parametrize(
    ("code", "param", "running_s"),
    [
        (BiCommand.BI_ACQUIRE, "20", STARTUP_LATENCY_S + 20 * LONGEST_ACQUISITION_S),
        pytest.param(BiCommand.BI_LOAD_LUT, "0", 0.0, marks=pytest.mark.slow),
    ],
    ids=["acquire", "load_lut"],
)
def test_a_hung_biris_is_a_timeout_after_the_bound(
    make_rig: RigFactory, code: BiCommand, param: str, running_s: float
) -> None:
    """BIRIS hangs with a command in COMMAND: the new driver waits exactly as long as that
    command could take (its acquisitions, the start-up, the record's BIRIS timeout), then
    reports a timeout naming it. Once BIRIS answers again, the next start succeeds."""
    rig = make_rig()
    record = BirisInitRecord(timeout_s=1.0)
    _boot(rig, record)
    rig.faults.hang_supervisor()
    rig.hardware.devices.link.issue(code, param)
    started = rig.clock.now()
    with pytest.raises(HardwareFault) as caught:
        BirisServer(rig.hardware, record)
    waited = rig.clock.now() - started
    fault = caught.value
    assert fault.kind == "timeout"
    assert f"BIRIS still busy with {code.name}" in fault.message
    bound = record.timeout_s + running_s
    assert bound <= waited <= bound + 0.5 * rig.time_scale  # half a real second of slack
    rig.faults.clear_hang()
    with BirisServer(rig.hardware, record) as server:
        assert server.status()["state"] == "idle"


def test_a_reset_during_a_long_scan_waits_for_biris(
    rig: SimulatedBiris, server: BirisServer, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A reset abandons the running scan; its BI_ACQUIRE is waited for, not written over."""
    conn = server.open()
    conn.single_scan(-360.0)
    conn.wait_idle(timeout=WAIT)
    conn.single_scan(360.0)
    until(lambda: rig.supervisor.busy, what="BIRIS executing the scan's BI_ACQUIRE")
    writes = Writes(rig.hardware.devices.link, monkeypatch)
    server.reset()
    assert server.status()["state"] == "idle"
    assert abs(rig.azimuth_counts) <= 3
    conn.single_scan(30.0)
    conn.wait_idle(timeout=WAIT)
    writes.assert_never_while_busy()

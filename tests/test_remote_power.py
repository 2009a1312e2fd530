"""The BIRIS crate loses power (issue 26, item 11): the Bit 3 coupler's NO_CONNECT and TIMEOUT
are a ``bus`` fault, at initialisation and during a scan, within a stated bound, and ``reset()``
recovers once power is back.

The bound (``biris_hw.server.isr``): the level-2 routine reads LOCAL_STATUS at least every
``COUPLER_WATCH_S`` (0.9 s) of hardware time, since a BIRIS without power raises no interrupt
and NO_CONNECT raises none either; an access across the coupler that times out is a fault at
once. On virtual time the measured delays are exact hardware seconds, whatever the host does.
"""

from __future__ import annotations

import errno
import threading
from collections.abc import Callable

import pytest

from biris_hw import BirisInitRecord, ConnectionKind, Direction
from biris_hw.bus.memory import MemoryWindow
from biris_hw.devices import Coupler
from biris_hw.errors import BusError, HardwareFault
from biris_hw.irq import EventFdLine
from biris_hw.server import BirisServer
from biris_hw.server.isr import COUPLER_WATCH_S, Level2Demux
from regs.biexec import OFF_COMMAND
from regs.bit3 import BIT3_SPACE, Bit3Reg, LocalCommand, LocalIntControl, LocalStatus
from sim import SimulatedBiris
from tests.conftest import WAIT, RigFactory, join, spawn, until

BOUND_S = 1.0
"""The issue's aim: every blocked caller told within 1 s of hardware time."""

TOLD_S = COUPLER_WATCH_S + 0.05
"""What the design gives on virtual time: one look of the level-2 routine, plus the
administrator's case and the callers' wake-ups (no hardware time at all on virtual time)."""


# -- the simulated coupler -------------------------------------------------------------------------


def test_a_powered_off_crate_shows_no_connect_and_every_access_times_out(
    make_rig: RigFactory,
) -> None:
    rig = make_rig()
    coupler = rig.hardware.coupler
    biris = rig.hardware.biris
    coupler.write8(
        Bit3Reg.LOCAL_INT_CONTROL,
        LocalIntControl.ERROR_INT_ENABLE | LocalIntControl.NORMAL_INT_ENABLE,
    )
    assert not coupler.read8(Bit3Reg.LOCAL_STATUS) & LocalStatus.NO_CONNECT
    before = rig.supervisor
    rig.faults.remote_power_off()
    assert coupler.read8(Bit3Reg.LOCAL_STATUS) & LocalStatus.NO_CONNECT
    raised = rig.level2_gate.raised_by("timeout")
    for access in (
        lambda: biris.read16(OFF_COMMAND),
        lambda: biris.write16(OFF_COMMAND, 1),
        lambda: biris.read(0, 16),
        lambda: biris.read_many([(0, 2), (4, 2)]),
    ):
        with pytest.raises(BusError) as failed:
            access()
        assert failed.value.errno == errno.ETIMEDOUT
        assert "NO_CONNECT" in str(failed.value)
    assert rig.coupler.timeouts == 4
    # error interrupts are enabled: one as the sticky bit is set, none while it stays set
    assert rig.level2_gate.raised_by("timeout") == raised + 1
    status = coupler.read8(Bit3Reg.LOCAL_STATUS)
    assert status & LocalStatus.TIMEOUT and status & LocalStatus.NO_CONNECT
    coupler.write8(Bit3Reg.LOCAL_COMMAND, LocalCommand.CLR_ERROR)
    status = coupler.read8(Bit3Reg.LOCAL_STATUS)
    assert not status & LocalStatus.TIMEOUT, "CLR_ERROR clears the sticky timeout"
    assert status & LocalStatus.NO_CONNECT, "but not the lost connection: a state, not an error"
    with pytest.raises(BusError):
        biris.read8(0)
    assert rig.level2_gate.raised_by("timeout") == raised + 2  # set again: raised again

    rig.faults.remote_power_on()
    assert not coupler.read8(Bit3Reg.LOCAL_STATUS) & LocalStatus.NO_CONNECT
    assert rig.supervisor is not before, "BIRIS powered up afresh"
    assert not rig.supervisor.booted
    assert biris.read16(OFF_COMMAND) == 0
    rig.faults.remote_power_off()
    rig.faults.clear_all()  # undoes a power cut too
    assert rig.coupler.remote_powered


def test_the_coupler_check_refuses_a_crate_that_is_not_connected() -> None:
    with MemoryWindow(BIT3_SPACE) as window:
        coupler = Coupler(window)
        coupler.check_link()  # all clear
        window.write8(Bit3Reg.LOCAL_STATUS, LocalStatus.NO_CONNECT | LocalStatus.CARD_READY)
        with pytest.raises(HardwareFault) as lost:
            coupler.check_link()
        assert lost.value.kind == "bus"
        assert "NO_CONNECT" in lost.value.message
        # a memory window keeps what is written: an error bit CLR_ERROR does not clear
        window.write8(Bit3Reg.LOCAL_STATUS, LocalStatus.PARITY_ERROR)
        with pytest.raises(HardwareFault) as stuck:
            coupler.check_link()
        assert stuck.value.kind == "parity"
        assert window.read8(Bit3Reg.LOCAL_COMMAND) == LocalCommand.CLR_ERROR  # it tried


class CountedCoupler(MemoryWindow):
    """Coupler registers in memory that count the reads of LOCAL_STATUS."""

    def __init__(self) -> None:
        super().__init__(BIT3_SPACE)
        self.looks = 0

    def read8(self, offset: int) -> int:
        if offset == Bit3Reg.LOCAL_STATUS:
            self.looks += 1
        return super().read8(offset)


def test_the_level2_routine_looks_at_the_coupler_without_an_interrupt(no_leaks: None) -> None:
    """No interrupt comes from a crate without power: the routine's own look finds it. What
    its first look finds is the initialiser's (a TIMEOUT left from before a power cycle)."""
    with (
        EventFdLine() as physical,
        CountedCoupler() as coupler,
        MemoryWindow(0x200) as biris,
    ):
        coupler.write8(Bit3Reg.LOCAL_STATUS, LocalStatus.TIMEOUT)
        demux = Level2Demux(physical, coupler, biris, 0x100, watch_s=0.01)
        raised: list[BaseException] = []

        def body() -> None:
            try:
                demux.serve()
            except BaseException as exc:
                raised.append(exc)

        thread = spawn(body, name="level2-test")
        try:
            until(lambda: coupler.looks >= 2, what="the routine to look twice")
            assert not raised, "a TIMEOUT already there when it began is not news"
            coupler.write8(Bit3Reg.LOCAL_STATUS, 0)  # the initialiser's CLR_ERROR
            coupler.write8(Bit3Reg.LOCAL_STATUS, LocalStatus.NO_CONNECT)
            assert join(thread), "the routine never looked at LOCAL_STATUS"
        finally:
            demux.close()
            join(thread)
        assert len(raised) == 1 and isinstance(raised[0], HardwareFault)
        assert raised[0].kind == "bus" and "lost the BIRIS crate" in raised[0].message


# -- the server ------------------------------------------------------------------------------------


class Callers:
    """A client blocked in wait_idle and a DATA client taking every buffer: each records the
    exception that ended it and the hardware time it came at."""

    def __init__(self, rig: SimulatedBiris, server: BirisServer) -> None:
        self._rig = rig
        self.normal = server.open()
        self.data = server.open(ConnectionKind.DATA)
        self.ended: dict[str, tuple[BaseException, float]] = {}
        self._admin = server.admin
        self._threads: list[threading.Thread] = []

    def block(self) -> None:
        """Start both (a scan runs: wait_idle waits for it) and return once wait_idle is
        parked."""
        self._threads = [
            spawn(self._run, "wait_idle", self._wait_idle, name="wait-idle"),
            spawn(self._run, "ready_for_data", self._take_data, name="data"),
        ]
        until(lambda: self._admin.life.idle_waiters, what="wait_idle parked")

    def _wait_idle(self) -> None:
        self.normal.wait_idle(timeout=WAIT)

    def _take_data(self) -> None:
        while True:
            self.data.ready_for_data(timeout=WAIT)

    def _run(self, name: str, call: Callable[[], None]) -> None:
        try:
            call()
        except BaseException as exc:
            self.ended[name] = (exc, self._rig.clock.now())

    def told(self, since: float) -> dict[str, tuple[str, float]]:
        """Each caller's fault kind, and how many hardware seconds after ``since`` it came."""
        for thread in self._threads:
            assert join(thread)
        out: dict[str, tuple[str, float]] = {}
        for name, (exc, when) in self.ended.items():
            assert isinstance(exc, HardwareFault), f"{name} ended with {exc!r}"
            out[name] = (exc.kind, when - since)
        assert {name: kind for name, (kind, _) in out.items()} == {
            "wait_idle": "bus",
            "ready_for_data": "bus",
        }
        return out


def test_power_lost_mid_scan_is_a_bus_fault_to_every_caller_within_the_bound(
    make_rig: RigFactory,
) -> None:
    rig = make_rig()
    with BirisServer(rig.hardware, BirisInitRecord()) as server:
        callers = Callers(rig, server)
        callers.normal.single_scan(300.0)  # about 3 s of hardware time
        callers.block()
        until(lambda: rig.supervisor.acquisitions_made >= 5, what="the scan to acquire")
        off = rig.clock.now()
        rig.faults.remote_power_off()
        told = callers.told(since=off)
        slowest = max(after for _, after in told.values())
        print(f"power lost mid-scan: every caller told {slowest:.3f} s (hardware) later")
        assert slowest <= TOLD_S <= BOUND_S, told
        assert server.status()["state"] == "fault:bus"
        message = str(callers.ended["wait_idle"][0])
        assert "NO_CONNECT" in message or "timed out" in message, message

        with pytest.raises(HardwareFault) as still_off:
            server.reset()
        assert still_off.value.kind == "bus" and "NO_CONNECT" in still_off.value.message

        rig.faults.remote_power_on()
        fresh = rig.supervisor
        booted_at_power_up = fresh.booted
        assert not booted_at_power_up
        server.reset()  # recovers: BIRIS booted anew, homed, scanning
        assert fresh.booted
        conn = server.open()
        conn.single_scan(30.0)
        conn.wait_idle(timeout=WAIT)
        scan = conn.request_scan_data(Direction.CCW)
        assert scan is not None and scan.n_acq > 0
        assert server.status()["state"] == "idle"


def test_power_lost_while_idle_is_a_bus_fault_within_the_bound(make_rig: RigFactory) -> None:
    """Nobody touches BIRIS while idle: only the routine's look can notice."""
    rig = make_rig()
    with BirisServer(rig.hardware, BirisInitRecord()) as server:
        data = server.open(ConnectionKind.DATA)
        ended: list[tuple[BaseException, float]] = []

        def take() -> None:
            try:
                data.ready_for_data(timeout=WAIT)
            except BaseException as exc:
                ended.append((exc, rig.clock.now()))

        thread = spawn(take, name="data")
        until(lambda: server.status()["state"] == "idle", what="the server idle")
        off = rig.clock.now()
        rig.faults.remote_power_off()
        assert join(thread)
        ((exc, when),) = ended
        assert isinstance(exc, HardwareFault) and exc.kind == "bus", exc
        assert "NO_CONNECT" in exc.message
        assert when - off <= TOLD_S
        rig.faults.remote_power_on()
        server.reset()
        assert server.status()["state"] == "idle"


def test_a_server_started_on_a_crate_without_power_fails_with_bus_at_once(
    make_rig: RigFactory,
) -> None:
    rig = make_rig()
    rig.faults.remote_power_off()
    started = rig.clock.now()
    with pytest.raises(HardwareFault) as refused:
        BirisServer(rig.hardware, BirisInitRecord())
    assert refused.value.kind == "bus"
    # the link check's own words: it came before anything crossed the coupler
    assert "not connected to the BIRIS crate" in refused.value.message
    assert "NO_CONNECT" in refused.value.message
    assert rig.clock.now() - started <= BOUND_S
    rig.faults.remote_power_on()
    with BirisServer(rig.hardware, BirisInitRecord()) as server:
        assert server.status()["state"] == "idle"


@pytest.mark.slow  # the fast tier keeps a cheaper test of the same (make test-slow runs this)
@pytest.mark.realtime
def test_power_lost_behind_a_vmusb_is_a_bus_fault_and_reset_recovers(
    make_rig: RigFactory,
) -> None:
    """The VM-USB's crate holds the coupler and the Model 7600 and keeps its power: the coupler
    is read through the bridge as before, and an access across it ends in a VME bus error."""
    rig = make_rig(transport="vmusb")
    with BirisServer(rig.hardware, BirisInitRecord()) as server:
        data = server.open(ConnectionKind.DATA)
        ended: list[BaseException] = []

        def take() -> None:
            try:
                data.ready_for_data(timeout=WAIT)
            except BaseException as exc:
                ended.append(exc)

        thread = spawn(take, name="data")
        rig.faults.remote_power_off()
        assert join(thread)
        assert isinstance(ended[0], HardwareFault) and ended[0].kind == "bus", ended
        with pytest.raises(BusError):
            rig.hardware.biris.read16(OFF_COMMAND)  # the bridge's BERR, from the coupler
        rig.faults.remote_power_on()
        server.reset()
        conn = server.open()
        conn.single_scan(20.0)
        conn.wait_idle(timeout=WAIT)
        assert server.status()["state"] == "idle"

"""A stock CiA 402 drive (issue 26, items 6-9): what the driver may assume of a drive it did not
build, against simulated drives that behave as the public sources say real ones do.

- Standard objects only: the simulated drive is stock by default (the rig's too), so a write to
  an object it lacks is the SDO abort a real one answers; BIRIS_MOTOR_PARAMS' filter goes to the
  drive's own objects only where ``gains`` names them.
- Homing on the current position by method 37 (35 on request), started only once the mode
  display 0x6061 shows homing, and judged done on fresh reads: a drive that keeps "homing
  attained" from an earlier homing is homed afresh all the same.
- TPDO1 carries the statusword alone: a drive sends an event PDO on any change of a mapped
  object, a frame per sample with the position mapped.
- Units: a drive whose position, velocity or acceleration units are not counts, counts/s and
  counts/s^2 is refused at start, before anything is written.

Each test runs one drive and the driver on a python-can ``virtual`` channel of its own; nothing
sleeps to synchronise (the driver's own bounded waits, the end-of-motion line).
"""

from __future__ import annotations

import itertools
import re
import threading
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest
from canopen.sdo.exceptions import SdoAbortedError

import biris_hw.axes.cia402 as cia402
from biris_hw.axes.cia402 import (
    GAIN_KEYS,
    Cia402Axis,
    Cia402Bus,
    Cia402Controller,
    DriveState,
    Sw,
    profile_for,
)
from biris_hw.errors import BusError, HardwareFault
from biris_hw.pan_reference import PanReference
from biris_hw.records import MotorParams
from regs.tech80 import Axis, AxisBit
from sim.cia402 import GAIN_RECORD, POWER_UP_PARAMS, STOCK, DriveVariant, SimulatedDrive
from sim.clock import SimClock
from sim.motor import MotorPlant
from sim.rig import SimulatedBiris
from tests.conftest import WAIT

NODE = 5
SCALE = 10.0
START_AZIMUTH = -300.4
SI_UNITS = frozenset({0x60A8, 0x60A9})
"""The SI unit objects: a drive of the older profile has the factor group alone."""


@dataclass
class Rig:
    clock: SimClock
    drive: SimulatedDrive
    bus: Cia402Bus
    axis: Cia402Axis
    controller: Cia402Controller

    def held(self, params: MotorParams | None = None) -> None:
        """Started, configured, holding, end of scan enabled."""
        self.controller.start()
        self.axis.configure(params or MotorParams())
        self.axis.hold_here()
        self.controller.enable_end_of_scan(Axis.AZIMUTH, 0x70)

    def move(self, destination: int) -> None:
        """A move as the server makes one: start, the interrupt, acknowledge, settle."""
        self.controller.acknowledge(Axis.AZIMUTH)
        self.axis.start_trapezoid(destination)
        assert self.controller.end_of_motion.wait(WAIT) == 1
        assert self.controller.ended_axes() == AxisBit.AZIMUTH
        self.controller.acknowledge(Axis.AZIMUTH)
        assert self.axis.wait_settled(threading.Event())

    def standing(self) -> None:
        """Idle (no torque) with the head come to rest."""
        self.axis.idle()
        self.axis.wait_still(threading.Event())


@contextmanager
def _rig(
    variant: DriveVariant = STOCK, axis_class: type[Cia402Axis] = Cia402Axis, **options: Any
) -> Iterator[Rig]:
    channel = f"stock-{uuid.uuid4().hex}"
    clock = SimClock(SCALE)
    plant = MotorPlant(np.random.default_rng(1), initial_azimuth_counts=START_AZIMUTH)
    drive = SimulatedDrive(channel, NODE, plant, clock, variant=variant)
    bus = Cia402Bus(
        interface="virtual", channel=channel, heartbeat_period_s=0.02, heartbeat_timeout_s=0.5
    )
    axis = axis_class(bus, NODE, Axis.AZIMUTH, clock, SCALE, **options)
    controller = Cia402Controller(bus, {Axis.AZIMUTH: axis})
    try:
        yield Rig(clock, drive, bus, axis, controller)
    finally:
        controller.close()
        bus.close()
        drive.close()
    assert drive.violations == []


Event = tuple[str, int, int, int]
"""What a drive took, in order: ("mode", 0x6061 read, 0, 0) or ("cw", controlword, mode run,
statusword then)."""


def _record(drive: SimulatedDrive, monkeypatch: pytest.MonkeyPatch) -> list[Event]:
    """Every read of the mode display and every controlword the drive takes, in the order it
    takes them (both in its network's receive thread)."""
    events: list[Event] = []
    read, take = drive._read_value, drive._controlword

    def reading(index: int, subindex: int) -> int:
        value = read(index, subindex)
        if index == 0x6061:
            events.append(("mode", value, 0, 0))
        return value

    def taking(cw: int) -> None:
        events.append(("cw", cw, drive._mode, drive._statusword()))
        take(cw)

    monkeypatch.setattr(drive, "_read_value", reading)
    monkeypatch.setattr(drive, "_controlword", taking)
    return events


def _homing_start(events: list[Event]) -> int:
    """Where the homing's start edge (bit 4 rising in homing mode) is in ``events``."""
    cws = [(i, e) for i, e in enumerate(events) if e[0] == "cw"]
    for (_, before), (i, now) in itertools.pairwise(cws):
        if now[2] == 6 and now[1] & 0x10 and not before[1] & 0x10:
            return i
    raise AssertionError(f"no homing start in {events}")


# -- standard objects only (item 6) ----------------------------------------------------------------


def test_a_stock_drive_has_standard_objects_only_and_takes_the_driver_as_it_comes(
    no_leaks: None,
) -> None:
    """Nothing but CiA 301/402 objects (a write elsewhere would be aborted, a bus fault): the
    profile is written converted, and read_params names the set it converts from."""
    with _rig() as rig:
        assert all(0x1000 <= i < 0x2000 or 0x6000 <= i < 0xA000 for i in rig.drive.od)
        assert GAIN_RECORD not in rig.drive.od
        rig.held()
        held = [rig.drive.value(index) for index in (0x6081, 0x6083, 0x6084)]
        assert held == [1420, 25_792_555, 25_792_555]
        assert rig.axis.read_params() == MotorParams().to_dict()
        rig.move(300)
        assert abs(rig.axis.actual_position() - 300) <= 8


def test_the_rigs_drives_are_stock() -> None:
    """The simulator stands in for the hardware a user has: stock drives, on which the driver's
    defaults must work (every server test over CAN is then one of the standard path)."""
    with SimulatedBiris(axes="canopen", seed=4) as rig:
        for drive in rig.drives.values():
            assert drive.variant == STOCK
            assert GAIN_RECORD not in drive.od


def test_gains_map_the_filter_onto_the_drives_own_objects(no_leaks: None) -> None:
    gains = {key: f"0x2000:{sub}" for sub, key in enumerate(GAIN_KEYS, start=1)}
    with _rig(DriveVariant(gain_record=True), gains=gains) as rig:
        power_up = [getattr(POWER_UP_PARAMS, key) for key in GAIN_KEYS]
        assert [rig.drive.value(GAIN_RECORD, sub) for sub in range(1, 5)] == power_up
        params = MotorParams(sample=0x9F, zero=0x70, pole=0xE0, gain=0x40, max_vel=3)
        rig.controller.start()
        rig.axis.configure(params)
        written = [rig.drive.value(GAIN_RECORD, sub) for sub in range(1, 5)]
        assert written == [0x9F, 0x70, 0xE0, 0x40]
        assert rig.axis.read_params() == params.to_dict()
        rig.drive.node.set_data(GAIN_RECORD, 3, (0x10).to_bytes(2, "little"))  # behind our back
        held = rig.axis.read_params()
        assert held["pole"] == 0x10 and held != params.to_dict()
        assert (held["max_vel"], held["max_accel"]) == profile_for(params)  # as the drive has it


def test_read_params_tells_a_kept_profile_from_a_drive_that_restored_its_own(
    no_leaks: None,
) -> None:
    """After a restart of the driver the journal names the set loaded; a drive that still holds
    what it converts to kept its count, one showing its power-on profile did not."""
    with _rig() as rig:
        params = MotorParams(max_vel=3)
        rig.controller.start()
        rig.axis.configure(params)
        reference = PanReference()  # the restarted driver's journal, in memory
        reference.configured(params.to_dict())
        reference.homed()
        restarted = Cia402Axis(rig.bus, NODE, Axis.AZIMUTH, rig.clock, SCALE, reference=reference)
        try:
            assert restarted.read_params() == params.to_dict()
            assert reference.locate(0, restarted.read_params()).how == "referenced"
            rig.drive.node.set_data(0x6081, 0, (1000).to_bytes(4, "little"))  # its power-on value
            held = restarted.read_params()
            assert held["max_vel"] == 1000 and held != params.to_dict()
            assert reference.locate(0, held).how == "chip reset"
        finally:
            restarted.close()


# -- homing (item 7) -------------------------------------------------------------------------------


@pytest.mark.parametrize("method", [37, 35])
def test_homing_on_the_current_position_is_37_by_default_and_35_on_request(
    method: int, no_leaks: None
) -> None:
    options: dict[str, Any] = {} if method == 37 else {"homing_method": 35}
    with _rig(**options) as rig:
        rig.held()
        rig.move(150)
        rig.standing()
        rig.axis.hold_here(zero_counter=True)
        assert rig.drive.value(0x6098) == method
        assert rig.axis.actual_position() == 0
        assert rig.drive.state is DriveState.OPERATION_ENABLED


def test_a_drive_that_keeps_homing_attained_is_homed_afresh(
    no_leaks: None, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The drive shows "homing attained" from its first homing when the second starts, and
    takes a while to home: the driver waits for fresh reads (bit 4 stays set until the drive
    homed: its fall would interrupt the homing), having read 0x6061 == 6 before the start."""
    variant = DriveVariant(keeps_homing_attained=True, homing_s=0.5)
    with _rig(variant) as rig:
        rig.held()
        rig.standing()
        rig.axis.hold_here(zero_counter=True)  # the first homing
        assert rig.axis.actual_position() == 0
        rig.move(500)
        rig.standing()
        events = _record(rig.drive, monkeypatch)
        rig.axis.hold_here(zero_counter=True)
        assert rig.axis.actual_position() == 0
        start = _homing_start(events)
        _, _, _, status = events[start]
        assert status & Sw.SET_POINT_ACKNOWLEDGE  # bit 12 kept from the first: no proof of homing
        assert ("mode", 6, 0, 0) in events[:start]
        fall = next(e for e in events[start + 1 :] if e[0] == "cw" and not e[1] & 0x10)
        assert fall[2] == 6 and fall[3] & Sw.SET_POINT_ACKNOWLEDGE  # after it homed again
        rig.move(-20)
        assert abs(rig.axis.actual_position() + 20) <= 8


def test_a_drive_takes_a_new_mode_at_its_next_cycle(no_leaks: None) -> None:
    """The simulated drive as a drive running its modes in its loop: 0x6060 shows in 0x6061 only
    once a cycle has run (here the clock stands until the test moves it)."""

    class Standing:
        t = 0.0

        def __call__(self) -> float:
            return self.t

    clock = Standing()
    plant = MotorPlant(np.random.default_rng(2), initial_azimuth_counts=0.0)
    drive = SimulatedDrive(
        f"mode-{uuid.uuid4().hex}", NODE, plant, clock, variant=DriveVariant(mode_at_cycle=True)
    )
    try:
        drive.node.set_data(0x6060, 0, bytes([6]))
        assert drive.value(0x6060) == 6
        assert drive.mode_display == 0
        clock.t += 0.01
        assert drive.mode_display == 6
    finally:
        drive.close()


def test_the_driver_waits_for_the_mode_display_before_it_starts_homing(
    no_leaks: None, monkeypatch: pytest.MonkeyPatch
) -> None:
    with _rig(DriveVariant(mode_at_cycle=True)) as rig:
        rig.held()
        rig.move(80)
        rig.standing()
        events = _record(rig.drive, monkeypatch)
        rig.axis.hold_here(zero_counter=True)
        assert rig.axis.actual_position() == 0
        start = _homing_start(events)
        assert ("mode", 6, 0, 0) in events[:start]
        assert events[start][2] == 6  # the drive ran homing when the edge came
        rig.move(100)  # back in profile position: a set-point, not a homing start
        assert abs(rig.axis.actual_position() - 100) <= 8


# -- TPDO1 (item 8) --------------------------------------------------------------------------------


def test_tpdo1_carries_the_statusword_alone_and_a_move_sends_a_handful(no_leaks: None) -> None:
    with _rig() as rig:
        rig.held()
        before = rig.drive.tpdo_sent
        rig.move(1024)
        sent = rig.drive.tpdo_sent - before
        print(f"TPDO1 frames for a 1024-count move, statusword mapped: {sent}")
        assert 2 <= sent <= 8, sent


def test_a_drive_sends_an_event_pdo_on_every_change_of_a_mapped_object(
    no_leaks: None, monkeypatch: pytest.MonkeyPatch
) -> None:
    """What a driver that maps the position as well gets: a frame per sample while the head
    moves (1024 counts in about 0.7 hardware seconds at Appendix B's profile)."""
    monkeypatch.setattr(cia402, "TPDO1_MAPPING", (0x60410010, 0x60640020))
    with _rig() as rig:
        rig.held()
        before = rig.drive.tpdo_sent
        rig.move(1024)
        sent = rig.drive.tpdo_sent - before
        print(f"TPDO1 frames for a 1024-count move, position mapped: {sent}")
        assert sent >= 300, sent


class _Inhibited(Cia402Axis):
    """Sets an inhibit time of 10 ms on TPDO1 (while it is invalid, as CiA 301 requires)."""

    def _map_pdos(self) -> None:
        super()._map_pdos()
        cob = 0x180 + self.node_id
        self._write(0x1800, 1, "<I", cob | 0x8000_0000)
        self._write(0x1800, 3, "<H", 100)
        self._write(0x1800, 1, "<I", cob)


def test_an_inhibit_time_bounds_the_frames_and_holds_the_last_change_until_it_expires(
    no_leaks: None, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(cia402, "TPDO1_MAPPING", (0x60410010, 0x60640020))
    with _rig(axis_class=_Inhibited) as rig:
        rig.held()
        assert rig.drive.value(0x1800, 3) == 100
        with pytest.raises(SdoAbortedError) as refused:  # not while the PDO is valid
            rig.bus.network[NODE].sdo.download(0x1800, 3, (50).to_bytes(2, "little"))
        assert refused.value.code == 0x08000022
        before, t0 = rig.drive.tpdo_sent, rig.clock.now()
        rig.move(1024)  # its end arrives: the change within the inhibit time was sent after it
        sent, took = rig.drive.tpdo_sent - before, rig.clock.now() - t0
        assert sent <= took / 0.010 + 2, (sent, took)


# -- units (item 9) --------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("variant", "message"),
    [
        pytest.param(
            DriveVariant(values={(0x60A9, 0): 0x00B44700}),
            r"0x60A9 \(SI unit velocity\) = 0x00B44700 gives revolution per minute, not "
            r"increments per second",
            id="rpm",
        ),
        pytest.param(
            DriveVariant(values={(0x60A8, 0): 0xFF410000}),
            r"0x60A8 \(SI unit position\) = 0xFF410000 gives 10\^-1 degree, not encoder increments",
            id="tenth-degrees",
        ),
        pytest.param(
            DriveVariant(absent=SI_UNITS, values={(0x6092, 1): 1}),
            r"0x6092 \(feed constant\) gives a position factor of 4096 \(",
            id="revolutions",
        ),
        pytest.param(
            DriveVariant(absent=SI_UNITS, values={(0x6094, 1): 10}),
            r"0x6094 \(velocity encoder factor\) gives a factor of 10, not 1",
            id="velocity-factor",
        ),
        pytest.param(
            DriveVariant(absent=SI_UNITS, values={(0x6097, 2): 1000}),
            r"0x6097 \(acceleration factor\) gives a factor of 1/1000, not 1",
            id="acceleration-factor",
        ),
    ],
)
def test_a_drive_whose_units_differ_is_refused_before_anything_is_written(
    variant: DriveVariant, message: str, no_leaks: None
) -> None:
    with _rig(variant) as rig:
        with pytest.raises(HardwareFault) as caught:
            rig.controller.start()
        assert caught.value.kind == "protocol" and not isinstance(caught.value, BusError)
        text = str(caught.value)
        assert re.search(message, text), text
        assert f"node {NODE}" in text and "counts/s" in text
        assert rig.drive.node.nmt.state == "PRE-OPERATIONAL"
        assert rig.drive.value(0x1017) == 0  # no heartbeat asked for: nothing was written
        assert rig.drive.value(0x1A00) == 0


@pytest.mark.parametrize(
    "absent",
    [
        pytest.param(SI_UNITS, id="factor-group-only"),
        pytest.param(SI_UNITS | {0x608F, 0x6091, 0x6092, 0x6094, 0x6097}, id="no-unit-objects"),
    ],
)
def test_a_drive_of_the_older_profile_in_counts_is_taken(
    absent: frozenset[int], no_leaks: None
) -> None:
    with _rig(DriveVariant(absent=absent)) as rig:
        rig.held()
        rig.move(200)
        assert abs(rig.axis.actual_position() - 200) <= 8

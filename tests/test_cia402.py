"""CiA 402 drives over CANopen: the axis interface, and the driver against a simulated drive.

Both ends run in this process on a python-can ``virtual`` channel of their own (a uuid), the
driver's :class:`Cia402Bus` on one canopen Network and the :class:`SimulatedDrive` on another.
Nothing here sleeps to synchronise: the tests wait on the end-of-motion line, on fault
listeners' events, or on the driver's own bounded waits.
"""

from __future__ import annotations

import struct
import threading
import uuid
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import pytest

from biris_hw.axes import MotionAxis, MotionController
from biris_hw.axes.cia402 import (
    DEFAULT_HOMING_METHOD,
    HOMING_METHODS,
    TOUCH_PROBE_INDEX,
    Cia402Axes,
    Cia402Axis,
    Cia402Bus,
    Cia402Controller,
    DriveBusError,
    DriveFault,
    DriveState,
    check_homing_method,
    check_node_id,
    profile_for,
    stop_periodic_task,
)
from biris_hw.devices import AxisDriver, MotionBoard
from biris_hw.errors import BusError, HardwareFault
from biris_hw.pan_reference import PanReference
from biris_hw.records import MotorParams
from regs.tech80 import Axis, AxisBit
from sim.cia402 import DriveRule, SimulatedDrive
from sim.clock import SimClock
from sim.motor import MotorPlant

NODE = 3
SCALE = 10.0
WAIT = 5.0
"""Seconds for what should happen almost at once; reached only when a test fails."""
HEARTBEAT_TIMEOUT_S = 0.5
"""Real seconds of silence before either end declares the other lost: a loaded test host can
stall a thread for a couple of hundred ms, which is no lost drive."""
START_AZIMUTH = -300.4
"""Where the head wakes, counts from true zero: the index is at encoder count 300/301."""


@dataclass
class Rig:
    clock: SimClock
    plant: MotorPlant
    drive: SimulatedDrive
    bus: Cia402Bus
    axis: Cia402Axis
    controller: Cia402Controller
    faulted: threading.Event

    def held(self) -> None:
        """Started, configured with Appendix B's values, holding, end of scan enabled."""
        self.controller.start()
        self.axis.configure(MotorParams())
        self.axis.hold_here()
        self.controller.enable_end_of_scan(Axis.AZIMUTH, 0x70)

    def move(self, destination: int) -> int:
        """A move the way the server makes one: start, the interrupt, acknowledge, settle."""
        self.controller.acknowledge(Axis.AZIMUTH)
        sent = self.axis.start_trapezoid(destination)
        assert self.controller.end_of_motion.wait(WAIT) == 1
        assert self.controller.ended_axes() == AxisBit.AZIMUTH
        self.controller.acknowledge(Axis.AZIMUTH)
        assert self.axis.wait_settled(threading.Event())
        return sent

    def fault(self) -> DriveFault:
        assert self.faulted.wait(WAIT), "no fault reported"
        return self.controller.faults[-1]


@pytest.fixture
def rig(no_leaks: None, request: pytest.FixtureRequest) -> Iterator[Rig]:
    channel = f"cia402-{uuid.uuid4().hex}"
    clock = SimClock(SCALE)
    plant = MotorPlant(np.random.default_rng(1), initial_azimuth_counts=START_AZIMUTH)
    drive = SimulatedDrive(channel, NODE, plant, clock)
    bus = Cia402Bus(
        interface="virtual",
        channel=channel,
        heartbeat_period_s=0.02,
        heartbeat_timeout_s=HEARTBEAT_TIMEOUT_S,
    )
    axis = Cia402Axis(bus, NODE, Axis.AZIMUTH, clock, SCALE)
    faulted = threading.Event()
    controller = Cia402Controller(bus, {Axis.AZIMUTH: axis}, on_fault=lambda _f: faulted.set())
    try:
        yield Rig(clock, plant, drive, bus, axis, controller, faulted)
    finally:
        controller.close()
        bus.close()
        drive.close()
    if request.node.get_closest_marker("audit_violations_expected") is None:
        assert drive.violations == []


# -- the interface -----------------------------------------------------------------------------


def test_hctl_axis_driver_satisfies_the_axis_protocol() -> None:
    assert issubclass(AxisDriver, MotionAxis)
    assert issubclass(Cia402Axis, MotionAxis)
    assert issubclass(Cia402Controller, MotionController)


def test_hctl_motion_board_satisfies_the_controller_protocol() -> None:
    assert issubclass(MotionBoard, MotionController)


def test_motion_board_has_every_other_controller_method() -> None:
    needed = ("reset_chip", "enable_end_of_scan", "disable_all", "index_seen", "clear_index")
    assert all(callable(getattr(MotionBoard, name, None)) for name in (*needed, "acknowledge"))


# -- set-up -------------------------------------------------------------------------------------


def test_start_configures_the_drive_without_a_violation(rig: Rig) -> None:
    rig.controller.start()
    drive = rig.drive
    assert rig.axis.statusword() & 0x4F == 0x40  # an SDO round trip behind the NMT start
    assert drive.node.nmt.state == "OPERATIONAL"
    assert drive.value(0x1400, 1) == 0x200 + NODE  # RPDO1 valid
    assert [drive.value(0x1600, s) for s in range(3)] == [2, 0x60400010, 0x607A0020]
    assert drive.value(0x1800, 1) == 0x180 + NODE
    assert drive.value(0x1800, 2) == 255  # event-driven
    assert (drive.value(0x1800, 3), drive.value(0x1800, 5)) == (0, 0)  # no inhibit, no timer
    assert [drive.value(0x1A00, s) for s in range(2)] == [1, 0x60410010]  # the statusword alone
    assert drive.value(0x6060) == 1  # profile position
    assert drive.value(0x1017) == 20  # heartbeat producer, ms
    assert drive.value(0x1016, 1) == (0x7F << 16) | 500  # consumer of the bus's heartbeat
    assert drive.value(0x60B8) == TOUCH_PROBE_INDEX
    assert drive.state is DriveState.SWITCH_ON_DISABLED


def test_parameters_round_trip_and_convert_to_profile_objects(rig: Rig) -> None:
    """A stock drive holds the converted profile: read_params names the set that converts to
    what it holds (nothing else is written: no gain objects are named)."""
    params = MotorParams(sample=0x9F, zero=0x70, pole=0xE0, gain=0x40, max_vel=3, max_accel=0x2000)
    rig.axis.configure(params)
    assert rig.axis.read_params() == params.to_dict()
    period = 16 * (0x9F + 1) / 2_000_000
    velocity = round(3 / period)
    accel = round(0x2000 / 256 / period**2)
    assert (rig.drive.value(0x6081), rig.drive.value(0x6083)) == (velocity, accel)
    assert rig.drive.value(0x6084) == accel
    assert rig.axis.profile_params() == (velocity, accel, accel)
    assert profile_for(params) == (velocity, accel)
    assert velocity == round(params.max_velocity_counts_per_s)


# -- holding and moving -------------------------------------------------------------------------


def test_hold_here_takes_the_head_where_it_stands(rig: Rig) -> None:
    rig.controller.start()
    rig.axis.configure(MotorParams())
    rig.drive.turn_by_hand(60, 0.1)
    here = rig.axis.actual_position()
    assert abs(here) > 20  # the stale target (0) would be a jump
    rig.axis.hold_here()
    assert rig.drive.state is DriveState.OPERATION_ENABLED
    assert rig.drive.value(0x607A) == here
    assert abs(rig.axis.actual_position() - here) <= 1
    assert rig.axis.wait_settled(threading.Event())
    assert not rig.axis.profile_active()


@pytest.mark.audit_violations_expected
def test_enabling_with_a_stale_target_is_audited(rig: Rig) -> None:
    rig.controller.start()
    rig.drive.turn_by_hand(60, 0.1)
    for controlword in (0x06, 0x07, 0x0F):  # a driver that forgets the target
        rig.bus.network.send_message(0x200 + NODE, struct.pack("<Hi", controlword, 0))
    rig.axis.statusword()  # an SDO round trip behind the frames: they have been taken
    assert [v.rule for v in rig.drive.violations] == [DriveRule.ENABLE_WITH_JUMP]


def test_a_move_ends_with_one_interrupt_and_settles(rig: Rig) -> None:
    rig.held()
    assert rig.axis.start_trapezoid(1024) == 1024
    assert rig.axis.profile_active()
    assert rig.controller.end_of_motion.wait(WAIT) == 1
    assert rig.controller.ended_axes() == AxisBit.AZIMUTH
    rig.controller.acknowledge(Axis.AZIMUTH)
    assert rig.controller.ended_axes() == 0
    assert not rig.axis.profile_active()
    assert rig.axis.wait_settled(threading.Event())
    assert abs(rig.axis.actual_position() - 1024) <= 8
    assert rig.axis.command_position() == 1024
    assert rig.controller.end_of_motion.wait(0.05) == 0  # once


def test_a_disabled_axis_ends_its_move_without_an_interrupt(rig: Rig) -> None:
    rig.held()
    rig.controller.disable_all()
    rig.axis.start_trapezoid(40)
    assert rig.axis.wait_settled(threading.Event())
    assert rig.controller.ended_axes() == AxisBit.AZIMUTH
    assert rig.controller.end_of_motion.wait(0.0) == 0


def test_a_far_destination_is_clamped_before_it_reaches_the_drive(rig: Rig) -> None:
    rig.held()
    assert rig.axis.start_trapezoid(10**6) == 4096
    assert rig.drive.value(0x607A) == 4096
    with pytest.raises(HardwareFault) as caught:
        rig.axis.start_trapezoid(-(10**6))  # the first has not ended
    assert caught.value.kind == "motor_stall"


def test_index_latch_is_set_by_crossing_the_index_and_rearmed_by_clearing(rig: Rig) -> None:
    rig.held()
    rig.controller.clear_index(Axis.AZIMUTH)
    assert not rig.controller.index_seen(Axis.AZIMUTH)
    rig.move(200)  # short of the index (encoder count ~300)
    assert not rig.controller.index_seen(Axis.AZIMUTH)
    rig.move(400)
    assert rig.controller.index_seen(Axis.AZIMUTH)
    assert abs(rig.axis.index_position() - 300) <= 3
    rig.controller.clear_index(Axis.AZIMUTH)
    assert not rig.controller.index_seen(Axis.AZIMUTH)
    rig.move(350)
    assert not rig.controller.index_seen(Axis.AZIMUTH)
    rig.move(250)
    assert rig.controller.index_seen(Axis.AZIMUTH)


def test_hold_here_zero_counter_makes_this_spot_zero(rig: Rig) -> None:
    rig.held()
    rig.move(150)
    rig.axis.idle()
    assert rig.drive.state is DriveState.SWITCHED_ON
    rig.axis.wait_still(threading.Event())
    true_before = rig.plant.true_azimuth_counts
    rig.axis.hold_here(zero_counter=True)
    assert rig.drive.state is DriveState.OPERATION_ENABLED
    assert rig.axis.actual_position() == 0
    assert rig.axis.command_position() == 0
    assert abs(rig.plant.true_azimuth_counts - true_before) < 2  # nothing moved
    assert rig.move(-20) == -20
    assert abs(rig.axis.actual_position() + 20) <= 8


def test_reset_chip_zeroes_the_count_and_leaves_the_axis_idle(rig: Rig) -> None:
    rig.held()
    rig.move(120)
    rig.controller.reset_chip(Axis.AZIMUTH)
    assert rig.drive.state is DriveState.SWITCHED_ON
    assert rig.axis.actual_position() == 0
    assert not rig.axis.profile_active()


def test_the_pan_reference_hears_of_parameters_moves_and_settling(rig: Rig) -> None:
    reference = PanReference()  # in memory, nothing known: destinations pass unchanged
    rig.axis.reference = reference
    rig.held()
    assert reference.state.params == MotorParams().to_dict()
    sent = rig.axis.start_trapezoid(100)
    assert reference.state.move == (0, 100)  # recorded before it was sent
    assert rig.controller.end_of_motion.wait(WAIT) == 1
    assert rig.axis.wait_settled(threading.Event())
    low, high = reference.state.move  # where the head settled: within the settling rule's count
    assert low == high and abs(low - 100) <= 1 and abs(rig.axis.actual_position() - low) <= 1
    assert sent == 100


# -- faults -------------------------------------------------------------------------------------


def test_emcy_is_reported_and_a_faulted_drive_refuses_moves(rig: Rig) -> None:
    rig.held()
    rig.drive.emcy(0x4310)  # excess temperature: the drive faults
    fault = rig.fault()
    assert (fault.node_id, fault.axis, fault.code) == (NODE, Axis.AZIMUTH, 0x4310)
    assert (fault.kind, fault.source) == ("motor_stall", "emcy")
    assert rig.axis.faults == [fault]
    assert fault.error().kind == "motor_stall"
    assert rig.controller.end_of_motion.wait(WAIT) == 1  # the level-3 routine's wake...
    assert rig.controller.take_fault() is not None  # ...and what it raises
    with pytest.raises(HardwareFault) as caught:
        rig.axis.start_trapezoid(100)
    assert caught.value.kind == "motor_stall"
    assert "0x4310" in str(caught.value)
    rig.controller.reset_chip(Axis.AZIMUTH)  # the server's reset clears it
    rig.axis.hold_here()
    rig.move(30)


def test_an_idle_drives_emcy_is_held_and_raises_the_line_at_once(rig: Rig) -> None:
    """A drive standing idle (holding, no move) that faults: the controller holds the fault
    and raises the level-3 line now, not when the next move is refused; once per fault, until
    the chip reset that clears it."""
    rig.held()
    assert not rig.axis.profile_active()
    rig.drive.emcy(0x2310)  # over-current
    assert rig.controller.end_of_motion.wait(WAIT) == 1
    held = rig.controller.take_fault()
    assert held is not None and not isinstance(held, BusError)
    assert held.kind == "motor_stall"
    assert f"node {NODE}" in str(held) and "0x2310" in str(held)
    assert rig.controller.take_fault() is None  # once
    assert rig.controller.ended_axes() == 0  # no move to end
    rig.drive.emcy(0x3210)  # the same failure reported again (over-voltage): recorded only
    rig.axis.statusword()  # an SDO round trip behind the EMCY: it has been heard
    assert [f.code for f in rig.controller.faults] == [0x2310, 0x3210]
    assert rig.controller.end_of_motion.wait(0.0) == 0
    assert rig.controller.take_fault() is None
    rig.controller.reset_chip(Axis.AZIMUTH)  # the server's reset: fault reset, held again
    rig.axis.hold_here()
    rig.drive.emcy(0x2310)
    assert rig.controller.end_of_motion.wait(WAIT) == 1
    again = rig.controller.take_fault()
    assert again is not None and again.kind == "motor_stall"


def test_a_held_fault_the_chip_reset_clears_is_dropped(rig: Rig) -> None:
    """A motion-side fault not yet taken when the reset's chip reset clears it would fail the
    fresh initialisation with a fault already gone: the chip reset drops it."""
    rig.held()
    rig.drive.emcy(0x5000)  # device hardware
    assert rig.controller.end_of_motion.wait(WAIT) == 1
    rig.controller.reset_chip(Axis.AZIMUTH)
    assert rig.controller.take_fault() is None
    assert rig.drive.state is DriveState.SWITCHED_ON


def test_communication_emcy_is_a_bus_fault(rig: Rig) -> None:
    rig.held()
    rig.drive.emcy(0x8120, fault=False)  # CAN error passive: a warning
    fault = rig.fault()
    assert (fault.code, fault.kind) == (0x8120, "bus")
    error = fault.error()
    assert isinstance(error, BusError)
    assert error.kind == "bus"


def test_heartbeat_loss_is_a_bus_fault_raised_once_on_the_line(rig: Rig) -> None:
    rig.held()
    rig.drive.lose_power()
    fault = rig.fault()
    assert (fault.kind, fault.source) == ("bus", "heartbeat")
    with pytest.raises(DriveBusError) as caught:
        rig.axis.actual_position()
    assert isinstance(caught.value, BusError)
    assert isinstance(caught.value, HardwareFault)
    assert caught.value.kind == "bus"
    assert f"node {NODE}" in str(caught.value)
    assert rig.controller.end_of_motion.wait(WAIT) == 1  # the level-3 routine is woken
    held = rig.controller.take_fault()
    assert isinstance(held, DriveBusError) and f"node {NODE}" in str(held)
    assert rig.controller.take_fault() is None  # once
    assert rig.controller.ended_axes() == 0  # not taken for the end of a move
    assert not rig.controller.end_of_motion.closed  # usable again after the server's reset


def test_a_stalled_motor_faults_and_its_move_ends_unsettled_far_from_its_target(
    rig: Rig,
) -> None:
    """As the HCTL-1000 ends its profile whatever the shaft does: the interrupted move is
    reported ended at once, and only the settling check and the arrival check tell the truth."""
    rig.held()
    rig.drive.stall()
    rig.axis.start_trapezoid(1024)
    fault = rig.fault()
    assert (fault.code, fault.kind) == (0x8611, "motor_stall")  # following error
    assert rig.drive.state is DriveState.FAULT
    assert rig.controller.end_of_motion.wait(WAIT) >= 1  # the fault held, the move ended
    assert rig.controller.ended_axes() == AxisBit.AZIMUTH
    held = rig.controller.take_fault()  # what the level-3 routine raises before the end
    assert held is not None and held.kind == "motor_stall" and "0x8611" in str(held)
    assert not rig.axis.profile_active()
    assert not rig.axis.wait_settled(threading.Event())  # a faulted drive holds nothing
    assert abs(rig.axis.actual_position() - 1024) > 500
    with pytest.raises(HardwareFault, match="0x8611"):
        rig.axis.start_trapezoid(0)


def test_sdo_errors_name_the_node_and_the_object(rig: Rig) -> None:
    """A gain object the (stock) drive does not have: its abort names the node, the object and
    what it was to hold."""
    other = Cia402Axis(rig.bus, NODE, Axis.ELEVATION, rig.clock, SCALE, gains={"zero": "0x2100:2"})
    with pytest.raises(DriveBusError) as caught:
        other.configure(MotorParams())
    text = str(caught.value)
    assert f"node {NODE}" in text
    assert "0x2100:02" in text
    assert "motor parameter zero" in text


def test_an_absent_drive_is_a_bus_error(rig: Rig) -> None:
    rig.bus.sdo_timeout_s = 0.02
    ghost = Cia402Axis(rig.bus, 9, Axis.ELEVATION, rig.clock, SCALE)
    with pytest.raises(DriveBusError, match=r"node 9 .*0x1000:00 \(device type\)"):
        ghost.start()


def test_a_drive_that_loses_the_masters_heartbeat_faults(rig: Rig) -> None:
    rig.held()
    assert rig.drive.master_heard.wait(WAIT)  # the drive's watch starts with the first one
    stop_periodic_task(rig.bus._producer)  # the host stops (or its cable is pulled)
    fault = rig.fault()
    assert (fault.code, fault.kind, fault.source) == (0x8130, "bus", "emcy")
    assert rig.drive.state is DriveState.FAULT


def test_node_ids_and_homing_methods_have_one_rule(no_leaks: None) -> None:
    """The driver's rule (what the target file's check uses too): node ids 1..127, homing on
    the current position by 37 (35 in the older numbering) only, 37 by default; Cia402Axes
    applies it before it opens a bus."""
    for node in (1, 127):
        assert check_node_id(node) == node
    for bad in (0, 128, True, 2.0):
        with pytest.raises(ValueError, match=r"must be in 1\.\.127"):
            check_node_id(bad)
    assert [check_homing_method(m) for m in HOMING_METHODS] == [37, 35]
    assert DEFAULT_HOMING_METHOD == 37
    for bad in (36, 34, True):
        with pytest.raises(ValueError, match=r"^homing_method: must be 37 \(homing on the"):
            check_homing_method(bad)
    channel = f"t-{uuid.uuid4().hex}"
    with pytest.raises(ValueError, match="pan_node"):
        Cia402Axes(pan_node=0, tilt_node=3, interface="virtual", channel=channel)
    with pytest.raises(ValueError, match="homing_method"):
        Cia402Axes(pan_node=2, tilt_node=3, homing_method=36, interface="virtual", channel=channel)

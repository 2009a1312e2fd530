"""CiA 402 servo drives in profile-position mode over CANopen, as an alternative to the HCTL-1000s.

One :class:`Cia402Bus` owns the CAN network (python-can underneath, any interface); one
:class:`Cia402Axis` per drive implements :class:`~biris_hw.axes.base.MotionAxis`; one
:class:`Cia402Controller` stands in for the Model 7600's board
(:class:`~biris_hw.axes.base.MotionController`) and raises its ``end_of_motion`` line -- the
"level 3 interrupt" -- when a drive's event TPDO says a move reached its target.

The driver uses standard objects only (CiA 301 and CiA 402), so that a stock drive takes it as
it comes; a manufacturer object is written only where a target file names one (``gains``, below).

**What the driver checks and sets up on a drive** (:meth:`Cia402Axis.start`, once, before the
first use): device type 0x1000 is CiA 402; the drive's units are the driver's (below; checked
before anything is written); NMT pre-operational; heartbeat producer 0x1017
(``heartbeat_period_s``) and, when the bus produces a heartbeat of its own, consumer 0x1016 sub 1
(its id and ``heartbeat_timeout_s``; skipped on a drive without it); RPDO1 = controlword 0x6040 +
target position 0x607A (transmission type 255); TPDO1 = the statusword 0x6041 alone, event-driven
(type 255), inhibit time 0x1800 sub 3 and event timer sub 5 both 0 (skipped where the drive lacks
them); RPDO2-4 and TPDO2-4 disabled where they exist; modes of operation 0x6060 = 1 (profile
position), awaited in the mode display 0x6061; following error window 0x6065/0x6066, position
window 0x6067/0x6068; touch probe 1 armed on the encoder's zero impulse (0x60B8); then NMT
operational.

**TPDO1 carries what the end of a move needs, the statusword, and nothing else.** A drive sends an
event-driven PDO whenever a mapped object changes: with the position actual mapped that is about a
frame per count while the head moves, which the driver never reads (it reads 0x6064 by SDO when it
needs it). An inhibit time would bound that rate but delay the end of every move by up to that
time; with the statusword alone the drive sends a handful of frames per move (set-point
acknowledged, acknowledge cleared, target reached), each at once.

**Units.** The driver writes positions in encoder counts (4096 per head revolution), the profile
velocity 0x6081 in counts/s and the accelerations 0x6083/0x6084 in counts/s^2, and reads them back
in those units. :meth:`Cia402Axis.start` reads the drive's units and refuses a drive whose units
differ (``HardwareFault("protocol")`` naming the object, its value and what it must be): where the
drive has the SI unit objects (0x60A8 position, 0x60A9 velocity: prefix in bits 24-31, unit in
16-23, time unit in 8-15), position must be encoder increments (0xB5) and velocity increments per
second (0x03), both without a power of ten; otherwise the factor group must scale by exactly 1:
the position factor (0x608F encoder increments per motor revolution x 0x6091 gear ratio / 0x6092
feed constant, or 0x6093), the velocity encoder factor 0x6094 and the acceleration factor 0x6097,
each where the drive has it. An absent object scales nothing. The driver never writes them:
they are the drive's commissioning (they also scale its own limits, windows and homing speeds).

**Moves** go by RPDO1: the target with the new-set-point bit (controlword bit 4) rising, a wait
for set-point acknowledge (statusword bit 12, seen in TPDO1), then bit 4 cleared (single
set-point, absolute, not "change immediately"). CiA 402's handshake is kept: bit 4 rises only
once the drive shows bit 12 clear again (it has seen bit 4 fall after the previous set-point; a
drive takes no new set-point before that). A set-point that can no longer be taken ends at once
as ``motor_stall``, never as a bus fault: the drive shows FAULT, an EMCY interrupted the move, or
the axis was idled, held or reset meanwhile. The last is an *epoch* that moves on under the lock
every controlword frame is sent under, so a motor worker the fault left waiting for an
acknowledge that cannot come sends nothing into the reset's own controlwords and does not outlast
it (which would fail the reset as ``bus``). A move *ends* at the first TPDO1 after that
acknowledge with bit 12 clear and target reached (bit 10) set: only then does the controller
set the axis's bit of :meth:`Cia402Controller.ended_axes` and trigger ``end_of_motion``, so a
status sent before the set-point was taken can never end it. Every destination is clamped to
+-0x1000 (and cut by the pan reference, which records it first), as on the HCTL-1000.

**Holding never jumps**: :meth:`Cia402Axis.hold_here` reads the position actual and sends it as
the target in every controlword frame that walks the state machine up to OPERATION ENABLED.
``hold_here(zero_counter=True)`` homes on the current position with home offset 0, so the
position actual becomes 0 where the head stands: method 37 (``homing_method``; CiA 402-2 /
IEC 61800-7-201 number it so, and ETG.6010's table marks 35 obsolete), or 35 for a drive built
to the older DSP 402 numbering. Homing is started only once the mode display 0x6061 shows 6, and
its end is judged on fresh reads, never on a statusword kept from before: bit 4 stays set until
an SDO read of the statusword shows homing attained (bits 12 and 10; bit 13 is a homing error)
*and* the position actual reads 0 (within the position window), since a drive may keep "homing
attained" set from an earlier homing. The board's chip reset
(:meth:`Cia402Controller.reset_chip`) does the same after a fault reset and a disable, because the
pan reference takes a reset to restart the count where the head stood. :meth:`Cia402Axis.idle` is
"disable operation" (SWITCHED ON: no torque, the head coasts).

**Index latch**: touch probe 1 (0x60B8 = 0x0015: enabled, first event, zero impulse, positive
edge); :meth:`Cia402Controller.index_seen` reads 0x60B9 bit 1, :meth:`clear_index` re-arms it
(0x60B8 = 0, then 0x0015). 0x60BA holds the latched position (:meth:`Cia402Axis.index_position`).

**BIRIS_MOTOR_PARAMS** (``[motor]`` of the init record) map as follows, with the HCTL sample
period T = 16 (sample + 1) / 2 MHz:

==========================  ==========================  =====================================
parameter                   drive object                value written
==========================  ==========================  =====================================
max_vel                     0x6081 profile velocity     round(max_vel / T) counts/s
max_accel                   0x6083 / 0x6084 acc / dec   round(max_accel / 256 / T^2)
                                                        counts/s^2 (both)
sample, zero, pole, gain    the drive's own objects     raw, only where ``gains`` names them
                            named by ``gains``          (:class:`GainObject`); by default not
                                                        at all: the drive's own tuning holds
==========================  ==========================  =====================================

There is no standard object for a position loop's gains: each maker has its own, with its own
meaning, so the driver writes none unless told where (a target file's ``[axes.gains]``, e.g.
``sample = "0x2000:1"``). :meth:`Cia402Axis.read_params` says which BIRIS_MOTOR_PARAMS the drive
holds: the set last loaded (or the pan reference's journal's) when the drive's profile objects and
mapped gains hold exactly what that set converts to, else the drive's own values (0x6081 as
``max_vel``, 0x6083 as ``max_accel``, each mapped gain as read, 0 for the others), which no init
record converts to. The pan reference compares them to tell a drive that kept its count from one
that was power-cycled (and so restored its power-on profile); the driver never stores them
(0x1010), so a drive keeps them in RAM only.

**Faults.** An EMCY becomes a :class:`DriveFault` in :attr:`Cia402Axis.faults` (and the
controller's), handed to every fault listener: communication codes (0x81xx, 0x82xx) are kind
``bus``, every other code ``motor_stall`` (the head can no longer be trusted to move: a
following error, a blocked motor, over-current, a drive fault); an error reset (0x00xx) is only
logged. A drive in FAULT refuses moves with HardwareFault("motor_stall") (its statusword never
shows the interrupted move's target reached). **Heartbeat loss** (no heartbeat for
``heartbeat_timeout_s``, or a boot-up message: the drive restarted and lost its set-up) makes
every later access of that axis raise :class:`DriveBusError` -- a
:class:`~biris_hw.errors.BusError` *and* a ``HardwareFault("bus")`` -- until
:meth:`Cia402Axis.relink` (the server's reset, through :meth:`Cia402Axes.relink`) brings the drive
back: NMT reset communication, its boot-up awaited (``boot_timeout_s``), then the set-up above
again; its CiA 402 state is left to the reset's chip reset (a fault reset first, if it faulted).
**Every fault reaches the server at once**, whatever the drive was doing: the controller holds
it and raises its ``end_of_motion`` line, the server's level-3 routine takes it
(:meth:`Cia402Controller.take_fault`) and raises it, and its supervisor reports it with its kind
(``bus`` or ``motor_stall``) to every caller -- an EMCY from a drive standing idle included,
which would otherwise surface only when the next move was refused. One fault is held until the
server's reset (the controller's notes say why and what is dropped). A ``motor_stall`` EMCY also
ends the move it interrupted, as the HCTL-1000 ends its profile whatever the shaft does. SDO
aborts and timeouts are DriveBusErrors too, naming the node and the object. A reset clears a
drive's FAULT (fault reset) and brings back a drive whose heartbeat was lost, once it answers; a
drive that stays silent fails the reset with ``bus``, saying what to restore.

:class:`Cia402Axes` is the whole set a hardware bundle takes (``BirisHardware(axes=...)``): the
bus, the pan and tilt drives, the controller and its line.
"""

from __future__ import annotations

import enum
import logging
import re
import struct
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from fractions import Fraction
from typing import Any, Literal, NoReturn

import can
import canopen
from canopen.emcy import EmcyError
from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

from biris_hw.angles import clamp_counts
from biris_hw.axes.base import (
    SETTLE_LIMIT_S,
    SETTLE_POLL_S,
    AxisSet,
    MotionAxis,
    MotionController,
    wait_settled,
    wait_still,
)
from biris_hw.errors import BusError, FaultKind, HardwareFault, RequestError
from biris_hw.irq.eventfd import EventFdLine
from biris_hw.pan_reference import PanReference
from biris_hw.records import MotorParams
from biris_hw.timebase import StopEvent
from regs.hctl1000 import F_CLK_HZ, sample_period
from regs.tech80 import Axis, AxisBit

__all__ = [
    "CIA402_PROFILE",
    "DEFAULT_HOMING_METHOD",
    "DEFAULT_MASTER_ID",
    "GAIN_KEYS",
    "GAIN_TYPES",
    "HOMING_METHODS",
    "NODE_IDS",
    "PARAM_KEYS",
    "RPDO1_MAPPING",
    "SI_INCREMENT",
    "SI_SECOND",
    "TOUCH_PROBE_INDEX",
    "TPDO1_MAPPING",
    "Cia402Axes",
    "Cia402Axis",
    "Cia402Bus",
    "Cia402Controller",
    "Cw",
    "DriveBusError",
    "DriveFault",
    "DriveState",
    "GainObject",
    "Obj",
    "Sw",
    "check_gains",
    "check_homing_method",
    "check_node_id",
    "fault_kind",
    "parse_gain_object",
    "profile_for",
    "state_of",
    "stop_periodic_task",
]

log = logging.getLogger(__name__)

CIA402_PROFILE = 402
"""The device profile number in the low word of 0x1000 (device type)."""

DEFAULT_MASTER_ID = 0x7F
"""The node id the bus's own heartbeat is sent under (0x77F), which drives consume (0x1016)."""

NOTIFIER_CYCLE_S = 0.02
"""How long the network's receive thread blocks in one read: how long closing waits for it."""

NODE_IDS = range(1, 128)
"""The node ids a CANopen drive may have (0 addresses every node in NMT)."""

HOMING_METHODS = (37, 35)
"""The homing methods on the current position (0x6098), the only ones the driver homes by (none
moves the head): 37, its number in CiA 402-2 / IEC 61800-7-201 (ETG.6010's homing table marks 35
obsolete; KEB's drives built to IEC 61800-7-200 preset 37 "on current position"), and 35, its
number in the older DSP 402 (what canopen's ``Homing.HM_ON_CURRENT_POSITION`` still says), for a
drive built to that."""

DEFAULT_HOMING_METHOD = 37
"""The current number: a drive of the older numbering is given ``homing_method = 35``."""


def check_node_id(node: object, what: str = "CANopen node id") -> int:
    """``node`` if it is a node id (:data:`NODE_IDS`); ValueError otherwise."""
    if isinstance(node, bool) or not isinstance(node, int) or node not in NODE_IDS:
        raise ValueError(f"{what}: must be in {NODE_IDS.start}..{NODE_IDS.stop - 1}, not {node!r}")
    return node


def check_homing_method(method: object, what: str = "homing_method") -> int:
    """``method`` if the driver homes by it (:data:`HOMING_METHODS`); ValueError otherwise."""
    if isinstance(method, bool) or not isinstance(method, int) or method not in HOMING_METHODS:
        raise ValueError(
            f"{what}: must be 37 (homing on the current position), or 35 for a drive of the "
            f"older numbering, not {method!r}"
        )
    return method


PARAM_KEYS = ("sample", "zero", "pole", "gain", "max_vel", "max_accel")
"""BIRIS_MOTOR_PARAMS in :meth:`MotorParams.to_dict` order."""

GAIN_KEYS = ("sample", "zero", "pole", "gain")
"""The BIRIS_MOTOR_PARAMS a drive may take raw into objects of its own (``gains``): its loop's
sample period and filter. ``max_vel`` and ``max_accel`` always go to the standard profile
objects, converted."""

GAIN_TYPES: dict[str, str] = {
    "u8": "<B",
    "u16": "<H",
    "u32": "<I",
    "i8": "<b",
    "i16": "<h",
    "i32": "<i",
}
"""The data types a gain object may have (CiA 301's UNSIGNED8..INTEGER32), as struct formats."""

GAIN_INDICES = range(0x2000, 0x6000)
"""Where a gain object may be: CiA 301's manufacturer-specific area. The profile area holds no
loop gains, so an index there is a mistake that would write a standard object."""

_GAIN_SYNTAX = re.compile(
    r"0x(?P<index>[0-9a-f]{1,4}):(?P<sub>0x[0-9a-f]{1,2}|[0-9]{1,3})(?::(?P<type>[a-z0-9]+))?"
)


@dataclass(frozen=True)
class GainObject:
    """One object of the drive's own that takes one BIRIS_MOTOR_PARAMS value raw."""

    index: int
    subindex: int
    type: str = "u16"
    """A key of :data:`GAIN_TYPES`."""

    def __post_init__(self) -> None:
        if self.index not in GAIN_INDICES:
            raise ValueError(
                f"0x{self.index:04X} is not a manufacturer object (0x2000..0x5FFF): the drive's "
                "own gains are there"
            )
        if not 0 <= self.subindex <= 0xFF:
            raise ValueError(f"sub-index {self.subindex} is beyond 0..255")
        if self.type not in GAIN_TYPES:
            raise ValueError(f"type {self.type!r} is none of {', '.join(GAIN_TYPES)}")

    @property
    def fmt(self) -> str:
        return GAIN_TYPES[self.type]

    def __str__(self) -> str:
        return f"0x{self.index:04X}:{self.subindex}:{self.type}"


def parse_gain_object(text: object, what: str = "gain object") -> GainObject:
    """``"0x2000:1"`` (UNSIGNED16) or ``"0x2000:1:u32"`` as a :class:`GainObject`: the index in
    hex, the sub-index in decimal (or hex with 0x), the type one of :data:`GAIN_TYPES`;
    ValueError starting with ``what`` otherwise."""
    if isinstance(text, GainObject):
        return text
    if not isinstance(text, str):
        raise ValueError(f'{what}: must be a string such as "0x2000:1", not {text!r}')
    match = _GAIN_SYNTAX.fullmatch(text.strip().lower())
    if match is None:
        raise ValueError(
            f'{what}: {text!r} is not INDEX:SUB[:TYPE] (e.g. "0x2000:1" or "0x2101:3:u32")'
        )
    sub = match["sub"]
    try:
        return GainObject(
            int(match["index"], 16),
            int(sub, 16) if sub.startswith("0x") else int(sub),
            match["type"] or "u16",
        )
    except ValueError as exc:
        raise ValueError(f"{what}: {exc}") from None


def check_gains(gains: Mapping[str, object], what: str = "gains") -> dict[str, GainObject]:
    """The ``gains`` mapping checked: keys among :data:`GAIN_KEYS`, values :class:`GainObject`
    or their text, no object named twice; ValueError naming the key otherwise."""
    checked: dict[str, GainObject] = {}
    for key, value in gains.items():
        if key not in GAIN_KEYS:
            raise ValueError(
                f"{what}.{key}: not a value a drive's own object takes (one of "
                f"{', '.join(GAIN_KEYS)}; max_vel and max_accel go to 0x6081/0x6083/0x6084)"
            )
        obj = parse_gain_object(value, f"{what}.{key}")
        for other, known in checked.items():
            if (known.index, known.subindex) == (obj.index, obj.subindex):
                raise ValueError(f"{what}.{key}: 0x{obj.index:04X}:{obj.subindex} is {other}'s")
        checked[key] = obj
    return checked


class Obj(enum.IntEnum):
    """Object dictionary indices the driver uses (CiA 301 and CiA 402)."""

    DEVICE_TYPE = 0x1000
    CONSUMER_HEARTBEAT = 0x1016
    PRODUCER_HEARTBEAT = 0x1017
    RPDO1_COMM = 0x1400
    RPDO1_MAP = 0x1600
    TPDO1_COMM = 0x1800
    TPDO1_MAP = 0x1A00
    CONTROLWORD = 0x6040
    STATUSWORD = 0x6041
    MODES_OF_OPERATION = 0x6060
    MODES_DISPLAY = 0x6061
    POSITION_DEMAND = 0x6062
    POSITION_ACTUAL = 0x6064
    FOLLOWING_ERROR_WINDOW = 0x6065
    FOLLOWING_ERROR_TIMEOUT = 0x6066
    POSITION_WINDOW = 0x6067
    POSITION_WINDOW_TIME = 0x6068
    TARGET_POSITION = 0x607A
    HOME_OFFSET = 0x607C
    PROFILE_VELOCITY = 0x6081
    PROFILE_ACCELERATION = 0x6083
    PROFILE_DECELERATION = 0x6084
    QUICK_STOP_DECELERATION = 0x6085
    POSITION_ENCODER_RESOLUTION = 0x608F
    GEAR_RATIO = 0x6091
    FEED_CONSTANT = 0x6092
    POSITION_FACTOR = 0x6093
    VELOCITY_ENCODER_FACTOR = 0x6094
    ACCELERATION_FACTOR = 0x6097
    HOMING_METHOD = 0x6098
    SI_UNIT_POSITION = 0x60A8
    SI_UNIT_VELOCITY = 0x60A9
    TOUCH_PROBE_FUNCTION = 0x60B8
    TOUCH_PROBE_STATUS = 0x60B9
    TOUCH_PROBE_1_POSITIVE = 0x60BA
    SUPPORTED_MODES = 0x6502


_NAMES = {
    int(Obj.DEVICE_TYPE): "device type",
    int(Obj.CONSUMER_HEARTBEAT): "consumer heartbeat time",
    int(Obj.PRODUCER_HEARTBEAT): "producer heartbeat time",
    int(Obj.RPDO1_COMM): "RPDO1 communication",
    int(Obj.RPDO1_MAP): "RPDO1 mapping",
    int(Obj.TPDO1_COMM): "TPDO1 communication",
    int(Obj.TPDO1_MAP): "TPDO1 mapping",
    int(Obj.CONTROLWORD): "controlword",
    int(Obj.STATUSWORD): "statusword",
    int(Obj.MODES_OF_OPERATION): "modes of operation",
    int(Obj.MODES_DISPLAY): "modes of operation display",
    int(Obj.POSITION_DEMAND): "position demand value",
    int(Obj.POSITION_ACTUAL): "position actual value",
    int(Obj.FOLLOWING_ERROR_WINDOW): "following error window",
    int(Obj.FOLLOWING_ERROR_TIMEOUT): "following error time out",
    int(Obj.POSITION_WINDOW): "position window",
    int(Obj.POSITION_WINDOW_TIME): "position window time",
    int(Obj.TARGET_POSITION): "target position",
    int(Obj.HOME_OFFSET): "home offset",
    int(Obj.PROFILE_VELOCITY): "profile velocity",
    int(Obj.PROFILE_ACCELERATION): "profile acceleration",
    int(Obj.PROFILE_DECELERATION): "profile deceleration",
    int(Obj.POSITION_ENCODER_RESOLUTION): "position encoder resolution",
    int(Obj.GEAR_RATIO): "gear ratio",
    int(Obj.FEED_CONSTANT): "feed constant",
    int(Obj.POSITION_FACTOR): "position factor",
    int(Obj.VELOCITY_ENCODER_FACTOR): "velocity encoder factor",
    int(Obj.ACCELERATION_FACTOR): "acceleration factor",
    int(Obj.HOMING_METHOD): "homing method",
    int(Obj.SI_UNIT_POSITION): "SI unit position",
    int(Obj.SI_UNIT_VELOCITY): "SI unit velocity",
    int(Obj.TOUCH_PROBE_FUNCTION): "touch probe function",
    int(Obj.TOUCH_PROBE_STATUS): "touch probe status",
    int(Obj.TOUCH_PROBE_1_POSITIVE): "touch probe 1 positive edge",
}


def _object_name(index: int, subindex: int, gains: Mapping[str, GainObject] | None = None) -> str:
    for key, obj in (gains or {}).items():
        if (obj.index, obj.subindex) == (index, subindex):
            return f"motor parameter {key}, the drive's own object"
    if 0x1400 <= index <= 0x1BFF:
        kind = {0x14: "RPDO communication", 0x16: "RPDO mapping", 0x18: "TPDO communication"}
        return f"{kind.get(index >> 8, 'TPDO mapping')} {(index & 0x1FF) + 1}"
    return _NAMES.get(index, "object")


class Cw(enum.IntFlag):
    """Controlword 0x6040 bits (CiA 402)."""

    SWITCH_ON = 0x0001
    ENABLE_VOLTAGE = 0x0002
    QUICK_STOP = 0x0004
    """Active low: clear to quick-stop."""
    ENABLE_OPERATION = 0x0008
    NEW_SET_POINT = 0x0010
    """Profile position: a rising edge takes the target. Homing: a rising edge starts homing."""
    CHANGE_SET_IMMEDIATELY = 0x0020
    RELATIVE = 0x0040
    FAULT_RESET = 0x0080
    HALT = 0x0100


SHUTDOWN = 0x0006
SWITCH_ON = 0x0007
DISABLE_OPERATION = 0x0007
ENABLE_OPERATION = 0x000F
DISABLE_VOLTAGE = 0x0000
FAULT_RESET = 0x0080


class Sw(enum.IntFlag):
    """Statusword 0x6041 bits (CiA 402)."""

    READY_TO_SWITCH_ON = 0x0001
    SWITCHED_ON = 0x0002
    OPERATION_ENABLED = 0x0004
    FAULT = 0x0008
    VOLTAGE_ENABLED = 0x0010
    QUICK_STOP = 0x0020
    """Active low: clear while a quick stop is active."""
    SWITCH_ON_DISABLED = 0x0040
    WARNING = 0x0080
    REMOTE = 0x0200
    TARGET_REACHED = 0x0400
    INTERNAL_LIMIT = 0x0800
    SET_POINT_ACKNOWLEDGE = 0x1000
    """Profile position: the set-point was taken. Homing: homing attained."""
    FOLLOWING_ERROR = 0x2000
    """Profile position: following error. Homing: homing error."""


class DriveState(enum.Enum):
    """The CiA 402 power state machine's states, as the statusword shows them."""

    NOT_READY_TO_SWITCH_ON = "NOT READY TO SWITCH ON"
    SWITCH_ON_DISABLED = "SWITCH ON DISABLED"
    READY_TO_SWITCH_ON = "READY TO SWITCH ON"
    SWITCHED_ON = "SWITCHED ON"
    OPERATION_ENABLED = "OPERATION ENABLED"
    QUICK_STOP_ACTIVE = "QUICK STOP ACTIVE"
    FAULT_REACTION_ACTIVE = "FAULT REACTION ACTIVE"
    FAULT = "FAULT"


_STATE_MASKS = (
    (0x4F, 0x00, DriveState.NOT_READY_TO_SWITCH_ON),
    (0x4F, 0x40, DriveState.SWITCH_ON_DISABLED),
    (0x6F, 0x21, DriveState.READY_TO_SWITCH_ON),
    (0x6F, 0x23, DriveState.SWITCHED_ON),
    (0x6F, 0x27, DriveState.OPERATION_ENABLED),
    (0x6F, 0x07, DriveState.QUICK_STOP_ACTIVE),
    (0x4F, 0x0F, DriveState.FAULT_REACTION_ACTIVE),
    (0x4F, 0x08, DriveState.FAULT),
)


def state_of(statusword: int) -> DriveState | None:
    """The state a statusword shows (CiA 402's masks), None for an impossible combination."""
    for mask, value, state in _STATE_MASKS:
        if statusword & mask == value:
            return state
    return None


class Mode(enum.IntEnum):
    """Modes of operation 0x6060 the driver uses."""

    PROFILE_POSITION = 1
    HOMING = 6


_POLL_S = 0.002
"""Real seconds between two SDO polls of a drive the driver waits for (mode display, homing):
a drive's cycle is a millisecond or so, and a TPDO wakes the wait earlier."""


TOUCH_PROBE_INDEX = 0x0015
"""0x60B8: touch probe 1 enabled (bit 0), first event only (bit 1 clear), triggered by the
encoder's zero impulse (bits 2-3 = 01), latching on the positive edge (bit 4)."""
TOUCH_PROBE_STORED = 0x0002
"""0x60B9 bit 1: touch probe 1 has latched a positive edge."""

_FRAME = struct.Struct("<Hi")
"""RPDO1: controlword (U16) then target position (I32)."""
_STATUS = struct.Struct("<H")
"""TPDO1: the statusword."""

RPDO1_MAPPING = (0x60400010, 0x607A0020)
"""RPDO1's entries (CiA 301: index << 16 | sub-index << 8 | bits): controlword, target."""
TPDO1_MAPPING = (0x60410010,)
"""TPDO1's entries: the statusword alone, all the end of a move needs (module notes)."""

_PDO_INVALID = 0x8000_0000
_EVENT_DRIVEN = 255
_INHIBIT_TIME = 3
"""0x18xx sub 3: the least time between two sends of the PDO, in 100 us (CiA 301)."""
_EVENT_TIMER = 5
"""0x18xx sub 5: a send every so many ms whatever changed (CiA 301); 0 is none."""

_NO_OBJECT = (0x06020000, 0x06090011)
"""SDO abort codes for "object does not exist" and "sub-index does not exist" (CiA 301)."""

SI_INCREMENT = 0xB5
"""The SI-unit code of an encoder increment, in 0x60A8/0x60A9's unit byte (as drives document
CiA 402's unit table, e.g. Nanotec's "user-defined units")."""
SI_SECOND = 0x03
"""The code of the second, in 0x60A9's time-unit byte (CiA 303-2: the SI base units metre 0x01,
kilogram 0x02, second 0x03; minute 0x47, which drives' rpm 0x00B44700 shows)."""
_SI_NAMES = {
    0x00: "none",
    0x01: "metre",
    0x03: "second",
    0x10: "radian",
    0x41: "degree",
    0x47: "minute",
    0x48: "hour",
    0xAC: "step",
    0xB4: "revolution",
    0xB5: "increment",
}


def _si_unit(value: int, *, with_time: bool) -> str:
    """0x60A8/0x60A9's coding in words: power of ten, unit, per time unit."""
    exponent = struct.unpack("<b", bytes([(value >> 24) & 0xFF]))[0]
    unit = (value >> 16) & 0xFF
    text = _SI_NAMES.get(unit, f"unit 0x{unit:02X}")
    if exponent:
        text = f"10^{exponent} {text}"
    if with_time:
        time_unit = (value >> 8) & 0xFF
        text += f" per {_SI_NAMES.get(time_unit, f'time unit 0x{time_unit:02X}')}"
    return text


def profile_for(params: MotorParams) -> tuple[int, int]:
    """(profile velocity in counts/s, profile acceleration in counts/s^2) for BIRIS_MOTOR_PARAMS:
    the HCTL-1000's counts-per-sample units through its sample period, rounded, at least 1
    (a zero would be a profile that never leaves its start)."""
    period = sample_period(params.sample, F_CLK_HZ)
    velocity = params.max_vel / period
    accel = params.max_accel / 256.0 / period**2
    return max(1, round(velocity)), max(1, round(accel))


def fault_kind(code: int) -> FaultKind:
    """The server's fault kind for an EMCY error code: communication errors (0x81xx, 0x82xx)
    are ``bus``; every other error leaves the head unable to move as told: ``motor_stall``."""
    return "bus" if code & 0xFF00 in (0x8100, 0x8200) else "motor_stall"


class DriveBusError(BusError, HardwareFault):
    """A drive or its bus failed: an SDO abort or timeout, a frame that could not be sent, a
    heartbeat lost. A BusError, so the server's supervisor reports a ``bus`` fault, and a
    ``HardwareFault("bus")``, so the initialiser reports it as one too."""

    def __init__(self, message: str) -> None:
        BusError.__init__(self, message)
        self.kind: FaultKind = "bus"
        self.message = message


@dataclass(frozen=True)
class DriveFault:
    """One fault a drive reported (EMCY) or that the bus saw (heartbeat lost)."""

    node_id: int
    axis: Axis
    kind: FaultKind
    code: int
    """The EMCY error code (0x8130, life guard / heartbeat error, for a lost heartbeat)."""
    register: int
    """The EMCY error register (0x1001)."""
    text: str
    source: Literal["emcy", "heartbeat"]

    def error(self) -> HardwareFault:
        """The exception the server raises for it."""
        if self.kind == "bus":
            return DriveBusError(self.text)
        return HardwareFault(self.kind, self.text)


class _Move(enum.Enum):
    NONE = "none"
    REQUESTED = "requested"
    """Set-point sent, acknowledge not yet seen."""
    ACKNOWLEDGED = "acknowledged"
    """Bit 12 seen: the next status with bit 12 clear and bit 10 set ends the move."""
    ENDED = "ended"


class Cia402Bus:
    """One CANopen network on python-can, its heartbeat and the watch over the drives' ones.

    ``can_config`` goes to :class:`can.Bus` (``interface="socketcan", channel="can0",
    bitrate=500000``; ``interface="pcan", channel="PCAN_USBBUS1"``; ``interface="virtual"``...).
    The bus sends its own heartbeat as node ``master_id`` (None: none, and drives are not asked
    to watch it) every ``heartbeat_period_s``, asks each drive for one as often, and declares a
    drive lost after ``heartbeat_timeout_s`` without one. All of it is real time: a CAN bus
    runs at wall-clock speed whatever the simulator's time scale.
    """

    def __init__(
        self,
        *,
        heartbeat_period_s: float = 0.1,
        heartbeat_timeout_s: float = 0.35,
        master_id: int | None = DEFAULT_MASTER_ID,
        sdo_timeout_s: float = 0.3,
        **can_config: Any,
    ) -> None:
        if not 0.0 < heartbeat_period_s < heartbeat_timeout_s:
            raise ValueError("the heartbeat timeout must exceed its (positive) period")
        self.heartbeat_period_s = heartbeat_period_s
        self.heartbeat_timeout_s = heartbeat_timeout_s
        self.master_id = master_id
        self.sdo_timeout_s = sdo_timeout_s
        self.network = canopen.Network()
        self.network.NOTIFIER_CYCLE = NOTIFIER_CYCLE_S
        self.network.NOTIFIER_SHUTDOWN_TIMEOUT = 4 * NOTIFIER_CYCLE_S
        try:
            self.network.connect(**can_config)
        except (can.CanError, OSError, ValueError) as exc:
            raise DriveBusError(f"CAN bus {can_config}: cannot connect ({exc})") from exc
        self._lock = threading.Lock()
        self._booted = threading.Condition(self._lock)
        self._seen: dict[int, float] = {}
        self._boots: dict[int, int] = {}
        """Boot-up messages heard from each node (a drive that (re)started, or answered an
        NMT reset): :meth:`wait_boot` waits for the next one."""
        self._watchers: dict[int, Callable[[str], None]] = {}
        self._closing = threading.Event()
        self._producer: Any = None
        if master_id is not None:
            self._producer = self.network.send_periodic(
                0x700 + master_id, bytes([0x05]), heartbeat_period_s
            )
        self._watchdog = threading.Thread(
            target=self._watch_heartbeats, name="cia402-heartbeat", daemon=True
        )
        self._watchdog.start()

    def add_node(self, node_id: int) -> canopen.RemoteNode:
        """The network's client for drive ``node_id`` (no object dictionary: the driver
        knows the types of what it reads)."""
        new_dictionary: Any = canopen.ObjectDictionary  # untyped
        node = self.network.add_node(node_id, new_dictionary())
        node.sdo.RESPONSE_TIMEOUT = self.sdo_timeout_s
        self.network.subscribe(0x700 + node_id, self._heartbeat)
        return node

    def watch(self, node_id: int, on_lost: Callable[[str], None]) -> None:
        """Call ``on_lost(reason)`` once if drive ``node_id``'s heartbeat stops or it restarts.
        The clock starts now, so a drive that never sends one is lost too."""
        with self._lock:
            self._seen[node_id] = time.monotonic()
            self._watchers[node_id] = on_lost

    def unwatch(self, node_id: int) -> None:
        with self._lock:
            self._watchers.pop(node_id, None)

    def boots(self, node_id: int) -> int:
        """How many boot-up messages node ``node_id`` has sent since the bus was opened."""
        with self._lock:
            return self._boots.get(node_id, 0)

    def wait_boot(self, node_id: int, after: int, timeout: float) -> bool:
        """Block until node ``node_id`` has sent more than ``after`` boot-up messages (see
        :meth:`boots`), at most ``timeout`` real seconds; False if none came."""
        with self._booted:
            return self._booted.wait_for(lambda: self._boots.get(node_id, 0) > after, timeout)

    def _heartbeat(self, can_id: int, data: bytearray, timestamp: float) -> None:
        node_id = can_id - 0x700
        lost: Callable[[str], None] | None = None
        with self._lock:
            self._seen[node_id] = time.monotonic()
            if data and data[0] & 0x7F == 0:
                self._boots[node_id] = self._boots.get(node_id, 0) + 1
                self._booted.notify_all()
                if node_id in self._watchers:  # a boot-up: it restarted, set-up lost
                    lost = self._watchers.pop(node_id)
        if lost is not None:
            lost(f"node {node_id} restarted (boot-up message): its set-up is lost")

    def _watch_heartbeats(self) -> None:
        while not self._closing.wait(self.heartbeat_timeout_s / 5):
            now = time.monotonic()
            expired: list[tuple[int, Callable[[str], None], float]] = []
            with self._lock:
                for node_id, on_lost in list(self._watchers.items()):
                    silent = now - self._seen.get(node_id, now)
                    if silent > self.heartbeat_timeout_s:
                        expired.append((node_id, on_lost, silent))
                        del self._watchers[node_id]
            for node_id, on_lost, silent in expired:
                on_lost(f"node {node_id}: no heartbeat for {silent * 1e3:.0f} ms")

    def close(self) -> None:
        """Stop the heartbeat and its watch, then disconnect; idempotent."""
        if self._closing.is_set():
            return
        self._closing.set()
        self._watchdog.join()
        stop_periodic_task(self._producer)
        try:
            self.network.disconnect()
        except (can.CanError, OSError) as exc:
            log.warning("CAN bus: disconnect failed (%s)", exc)

    def __enter__(self) -> Cia402Bus:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class Cia402Axis:
    """One CiA 402 drive in profile-position mode: a :class:`~biris_hw.axes.base.MotionAxis`.

    ``clock`` and ``time_scale`` pace the settling polls in hardware time, as
    :class:`~biris_hw.devices.AxisDriver` does; the CAN timeouts (``state_timeout_s``, the
    bus's SDO and heartbeat ones) are real seconds. ``reference`` (the pan's only) records every
    move before it is sent and cuts its destination, and hears of every settle position and
    parameter load. The drive is set up on first use (:meth:`start`). ``gains`` names the drive's
    own objects that take BIRIS_MOTOR_PARAMS' sample and filter values raw (:func:`check_gains`:
    :class:`GainObject` or its text by key); none by default, so that nothing but standard
    objects is written.

    Raises:
        ValueError: a bad node id, homing method, gains mapping or boot timeout.
    """

    def __init__(
        self,
        bus: Cia402Bus,
        node_id: int,
        axis: Axis,
        clock: Callable[[], float] = time.monotonic,
        time_scale: float = 1.0,
        reference: PanReference | None = None,
        *,
        gains: Mapping[str, GainObject | str] | None = None,
        homing_method: int = DEFAULT_HOMING_METHOD,
        following_error_window: int = 256,
        following_error_timeout_ms: int = 20,
        position_window: int = 2,
        position_window_time_ms: int = 0,
        state_timeout_s: float = 0.5,
        boot_timeout_s: float = 1.0,
    ) -> None:
        check_node_id(node_id)
        check_homing_method(homing_method)
        self.gains = check_gains(gains or {})
        if not boot_timeout_s > 0.0:
            raise ValueError(f"boot_timeout_s must be positive, not {boot_timeout_s!r}")
        self.bus = bus
        self.node_id = node_id
        self.axis = axis
        self.reference = reference
        self.homing_method = homing_method
        self.following_error_window = following_error_window
        self.following_error_timeout_ms = following_error_timeout_ms
        self.position_window = position_window
        self.position_window_time_ms = position_window_time_ms
        self.state_timeout_s = state_timeout_s
        self.boot_timeout_s = boot_timeout_s
        """Real seconds :meth:`relink` waits for the boot-up that answers its NMT reset."""
        self._clock = clock
        self._scale = time_scale
        self._node = bus.add_node(node_id)
        self._sdo_lock = threading.Lock()
        """canopen's SDO client keeps one response queue: one transfer at a time."""
        self._start_lock = threading.Lock()
        self._started = False
        self._listening = False
        """TPDO1 and EMCY are subscribed to (once: a re-link starts the drive again)."""
        self._cond = threading.Condition()
        """Guards everything the receive thread updates: status, move, lost."""
        self._status = 0
        self._move = _Move.NONE
        self._lost: str | None = None
        self._cw_lock = threading.Lock()
        """Held while a controlword frame is sent and while :attr:`_epoch` moves on, so that a
        set-point abandoned meanwhile never sends another frame (:meth:`_send`)."""
        self._epoch = 0
        """Moves on whenever the axis is idled, held or reset: a set-point of an earlier epoch
        (a motor worker that the fault and the reset left behind) sends nothing more and waits
        no longer."""
        self.relinks = 0
        """How many times :meth:`relink` brought the drive back."""
        self._target = 0
        self._loaded: MotorParams | None = None
        """The BIRIS_MOTOR_PARAMS :meth:`configure` last loaded (:meth:`read_params`)."""
        self._end_listeners: list[Callable[[Axis], None]] = []
        self._fault_listeners: list[Callable[[DriveFault], None]] = []
        self.faults: list[DriveFault] = []
        """Every fault reported, oldest first."""

    def __repr__(self) -> str:
        return f"Cia402Axis(node {self.node_id}, {self.axis.name})"

    @property
    def _who(self) -> str:
        return f"drive node {self.node_id} ({self.axis.name.lower()})"

    # -- listeners ------------------------------------------------------------------------------
    def add_end_listener(self, listener: Callable[[Axis], None]) -> None:
        """``listener(axis)`` is called (in the CAN receive thread) when a move ends."""
        self._end_listeners.append(listener)

    def add_fault_listener(self, listener: Callable[[DriveFault], None]) -> None:
        """``listener(fault)`` is called (in the CAN receive or watch thread) for each fault."""
        self._fault_listeners.append(listener)

    # -- set-up ---------------------------------------------------------------------------------
    def start(self) -> None:
        """Set the drive up (see the module notes) and start it; once, idempotent."""
        with self._start_lock:
            if self._started:
                return
            self._check_lost()
            device_type = self._read(Obj.DEVICE_TYPE, 0, "<I")
            if device_type & 0xFFFF != CIA402_PROFILE:
                raise HardwareFault(
                    "protocol",
                    f"{self._who}: device type 0x{device_type:08X} is not a CiA 402 drive",
                )
            self._check_units()  # before anything is written: a refused drive is left as it was
            self._nmt(0x80)  # pre-operational: PDO mappings may change only there
            bus = self.bus
            self._write(Obj.PRODUCER_HEARTBEAT, 0, "<H", _ms(bus.heartbeat_period_s))
            if bus.master_id is not None:
                consumer = (bus.master_id << 16) | _ms(bus.heartbeat_timeout_s)
                self._write(Obj.CONSUMER_HEARTBEAT, 1, "<I", consumer, optional=True)
            self._map_pdos()
            self._set_mode(Mode.PROFILE_POSITION)
            self._write(Obj.FOLLOWING_ERROR_WINDOW, 0, "<I", self.following_error_window)
            self._write(Obj.FOLLOWING_ERROR_TIMEOUT, 0, "<H", self.following_error_timeout_ms)
            self._write(Obj.POSITION_WINDOW, 0, "<I", self.position_window)
            self._write(Obj.POSITION_WINDOW_TIME, 0, "<H", self.position_window_time_ms)
            self._write(Obj.TOUCH_PROBE_FUNCTION, 0, "<H", 0)
            self._write(Obj.TOUCH_PROBE_FUNCTION, 0, "<H", TOUCH_PROBE_INDEX)
            if not self._listening:
                self.bus.network.subscribe(0x180 + self.node_id, self._on_tpdo)
                self._node.emcy.add_callback(self._on_emcy)
                self._listening = True
            status = self._read(Obj.STATUSWORD, 0, "<H")
            with self._cond:
                self._status = status
            self._nmt(0x01)  # operational: the PDOs run
            bus.watch(self.node_id, self._heartbeat_lost)
            self._started = True

    def _map_pdos(self) -> None:
        """RPDO1 = controlword + target, TPDO1 = the statusword (event-driven, no inhibit time,
        no event timer: sent at once when the statusword changes, and only then); the other
        PDOs off, where the drive has them (CiA 301's order: invalidate, unmap, map, count,
        validate; the inhibit time may change only while the PDO is invalid)."""
        node_id = self.node_id
        for comm, mapping, cob, entries in (
            (Obj.RPDO1_COMM, Obj.RPDO1_MAP, 0x200 + node_id, RPDO1_MAPPING),
            (Obj.TPDO1_COMM, Obj.TPDO1_MAP, 0x180 + node_id, TPDO1_MAPPING),
        ):
            self._write(comm, 1, "<I", cob | _PDO_INVALID)
            if comm == Obj.TPDO1_COMM:  # a drive's defaults could delay or add frames
                self._write(comm, _INHIBIT_TIME, "<H", 0, optional=True)
                self._write(comm, _EVENT_TIMER, "<H", 0, optional=True)
            self._write(mapping, 0, "<B", 0)
            for sub, entry in enumerate(entries, start=1):
                self._write(mapping, sub, "<I", entry)
            self._write(mapping, 0, "<B", len(entries))
            self._write(comm, 2, "<B", _EVENT_DRIVEN)
            self._write(comm, 1, "<I", cob)
        for n in range(1, 4):
            self._write(0x1400 + n, 1, "<I", 0x200 + 0x100 * n + node_id | _PDO_INVALID, True)
            self._write(0x1800 + n, 1, "<I", 0x180 + 0x100 * n + node_id | _PDO_INVALID, True)

    def _check_units(self) -> None:
        """Refuse a drive whose position, velocity or acceleration units are not encoder
        counts, counts/s and counts/s^2 (the module notes say which objects decide)."""
        position = self._read_optional(Obj.SI_UNIT_POSITION, 0, "<I")
        velocity = self._read_optional(Obj.SI_UNIT_VELOCITY, 0, "<I")
        if position is not None or velocity is not None:
            if position is not None and position & 0xFFFF0000 != SI_INCREMENT << 16:
                self._wrong_units(
                    Obj.SI_UNIT_POSITION,
                    position,
                    _si_unit(position, with_time=False),
                    "encoder increments (0x00B50000)",
                )
            want = SI_INCREMENT << 16 | SI_SECOND << 8
            if velocity is not None and velocity & 0xFFFFFF00 != want:
                self._wrong_units(
                    Obj.SI_UNIT_VELOCITY,
                    velocity,
                    _si_unit(velocity, with_time=True),
                    f"increments per second (0x{want:08X})",
                )
            return  # the SI units say what the user units are; the factors serve them
        ratios = {
            index: self._read_ratio(index)
            for index in (
                Obj.POSITION_ENCODER_RESOLUTION,
                Obj.GEAR_RATIO,
                Obj.FEED_CONSTANT,
                Obj.POSITION_FACTOR,
                Obj.VELOCITY_ENCODER_FACTOR,
                Obj.ACCELERATION_FACTOR,
            )
        }
        encoder, feed = ratios[Obj.POSITION_ENCODER_RESOLUTION], ratios[Obj.FEED_CONSTANT]
        if encoder is not None and feed is not None:
            gear = ratios[Obj.GEAR_RATIO] or Fraction(1)
            factor = encoder * gear / feed
            if factor != 1:
                self._wrong_units(
                    Obj.FEED_CONSTANT,
                    None,
                    f"a position factor of {factor} (0x608F encoder resolution {encoder} x "
                    f"0x6091 gear ratio {gear} / 0x6092 feed constant {feed})",
                    "1: one position unit per encoder increment",
                )
        for index, what in (
            (Obj.POSITION_FACTOR, "one position unit per encoder increment"),
            (Obj.VELOCITY_ENCODER_FACTOR, "velocity in increments per second"),
            (Obj.ACCELERATION_FACTOR, "acceleration in increments per second squared"),
        ):
            ratio = ratios[index]
            if ratio is not None and ratio != 1:
                self._wrong_units(index, None, f"a factor of {ratio}", f"1: {what}")

    def _wrong_units(self, index: int, value: int | None, shown: str, wanted: str) -> NoReturn:
        raw = f" = 0x{value:08X}" if value is not None else ""
        raise HardwareFault(
            "protocol",
            f"{self._who}: 0x{index:04X} ({_object_name(index, 0)}){raw} gives {shown}, not "
            f"{wanted}. The driver writes positions in encoder counts (4096 per head "
            "revolution), velocities in counts/s and accelerations in counts/s^2: set the "
            "drive's units so with its maker's tool (docs/transports.md, drive requirements)",
        )

    def _read_ratio(self, index: int) -> Fraction | None:
        """A two-entry factor object (sub 1 / sub 2, UNSIGNED32) as a fraction; None when the
        drive has no such object. A zero term is no scale at all: refused."""
        numerator = self._read_optional(index, 1, "<I")
        if numerator is None:
            return None
        denominator = self._read(index, 2, "<I")
        if numerator == 0 or denominator == 0:
            self._wrong_units(
                index, None, f"{numerator}/{denominator}", "a ratio of two non-zero numbers"
            )
        return Fraction(numerator, denominator)

    def _read_optional(self, index: int, subindex: int, fmt: str) -> int | None:
        """:meth:`_read`, or None when the drive answers that the object does not exist."""
        try:
            with self._sdo_lock:
                raw = self._node.sdo.upload(index, subindex)
        except SdoAbortedError as exc:
            if exc.code in _NO_OBJECT:
                return None
            self._check_lost()
            raise self._sdo_error("read", index, subindex, exc) from exc
        except (SdoCommunicationError, can.CanError) as exc:
            self._check_lost()
            raise self._sdo_error("read", index, subindex, exc) from exc
        try:
            value: int = struct.unpack(fmt, bytes(raw[: struct.calcsize(fmt)]))[0]
        except struct.error as exc:
            raise self._sdo_error("read", index, subindex, exc) from exc
        return value

    def _set_mode(self, mode: Mode) -> None:
        """Modes of operation 0x6060 = ``mode``, then the mode display 0x6061 read until it
        shows it: a drive takes a new mode at its next cycle, and a controlword meant for one
        mode sent while the drive still runs the other starts the wrong thing (bit 4 is a
        set-point in profile position, the start of homing in homing mode)."""
        self._write(Obj.MODES_OF_OPERATION, 0, "<b", mode)
        deadline = time.monotonic() + self.state_timeout_s
        while True:
            shown = self._read(Obj.MODES_DISPLAY, 0, "<b")
            if shown == mode:
                return
            if time.monotonic() > deadline:
                raise HardwareFault(
                    "protocol",
                    f"{self._who}: modes of operation display 0x6061 shows {shown}, not "
                    f"{int(mode)} ({mode.name.lower().replace('_', ' ')}), "
                    f"{self.state_timeout_s:g} s after 0x6060 was written",
                )
            with self._cond:  # a poll, woken early by a TPDO (the drive's next cycle)
                self._cond.wait(_POLL_S)

    @property
    def lost(self) -> bool:
        """The drive's heartbeat was lost (or it restarted): every access raises until
        :meth:`relink` brings it back."""
        return self._lost is not None

    def relink(self) -> None:
        """Bring a lost drive back, as at its first use; at once when it is not lost.

        The drive is told NMT *reset communication* (its communication objects back to their
        power-on values, which a drive that restarted has anyway) and must answer with its
        boot-up message within :attr:`boot_timeout_s`; then it is set up again exactly as
        :meth:`start` does the first time (pre-operational, heartbeats, PDO mappings, mode and
        windows, touch probe, operational) and watched again. Its CiA 402 state is left as it is:
        the reset's chip reset (:meth:`reset`) takes it through the state machine, a fault reset
        first when it faulted meanwhile (losing the master's heartbeat faults a drive too).

        Raises:
            DriveBusError: no boot-up came (the drive is still unpowered or off the bus: the
                message says so), or the set-up failed.
        """
        with self._start_lock:
            lost = self._lost
            if lost is None:
                return
            bus = self.bus
            booted = bus.boots(self.node_id)
            self._nmt(0x82)  # reset communication
            if not bus.wait_boot(self.node_id, booted, self.boot_timeout_s):
                raise DriveBusError(
                    f"{self._who} is still silent (no boot-up within {self.boot_timeout_s:g} s "
                    f"of an NMT reset communication; it was lost: {lost}); restore its power "
                    "and its CAN cable, then reset again"
                )
            with self._cond:
                self._lost = None
                self._started = False
                self._status = 0
                self._move = _Move.NONE
                self._cond.notify_all()
        self.start()
        self.relinks += 1
        log.warning("%s: back on the bus (NMT reset communication), set up again", self._who)

    def close(self) -> None:
        """Stop listening to the drive (it is left as it is)."""
        self.bus.unwatch(self.node_id)
        if self._listening:
            try:
                self.bus.network.unsubscribe(0x180 + self.node_id, self._on_tpdo)
            except (KeyError, ValueError):
                pass
            self._listening = False
        with self._cond:
            self._started = False
            self._cond.notify_all()

    # -- the drive's reports (CAN receive thread) ------------------------------------------------
    def _on_tpdo(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if len(data) < _STATUS.size:
            log.warning("%s: short TPDO1 %s", self._who, bytes(data).hex())
            return
        (status,) = _STATUS.unpack_from(data)
        ended = False
        with self._cond:
            self._status = status
            if self._move is _Move.REQUESTED and status & Sw.SET_POINT_ACKNOWLEDGE:
                self._move = _Move.ACKNOWLEDGED
            elif (
                self._move is _Move.ACKNOWLEDGED
                and not status & Sw.SET_POINT_ACKNOWLEDGE
                and status & Sw.TARGET_REACHED
            ):
                self._move = _Move.ENDED
                ended = True
            self._cond.notify_all()
        if ended:
            for listener in self._end_listeners:
                listener(self.axis)

    def _on_emcy(self, entry: EmcyError) -> None:
        if entry.code & 0xFF00 == 0:
            log.info("%s: error reset (EMCY 0x%04X)", self._who, entry.code)
            return
        kind = fault_kind(entry.code)
        text = (
            f"{self._who} reported EMCY 0x{entry.code:04X} ({entry.get_desc() or 'error'}), "
            f"error register 0x{entry.register:02X}"
        )
        self._fault(
            DriveFault(self.node_id, self.axis, kind, entry.code, entry.register, text, "emcy")
        )
        if kind == "motor_stall":
            self._interrupted()

    def _interrupted(self) -> None:
        """A fault stopped the move under way: report it ended, as the HCTL-1000 ends its
        profile whatever the shaft does. The fault itself reaches the server first (the
        controller holds it and the level-3 routine raises it before it looks at ended axes);
        a level-3 routine that did not ask for faults would still find the head short of its
        destination here (verified arrival), not wait for the watchdog. Runs in the CAN
        receive thread: no SDO here."""
        with self._cond:
            if self._move not in (_Move.REQUESTED, _Move.ACKNOWLEDGED):
                return
            self._move = _Move.ENDED
            self._cond.notify_all()
        for listener in self._end_listeners:
            listener(self.axis)

    def _heartbeat_lost(self, reason: str) -> None:
        text = f"{self._who}: {reason}; it is no longer driven"
        with self._cond:
            self._lost = text
            self._cond.notify_all()
        self._fault(DriveFault(self.node_id, self.axis, "bus", 0x8130, 0, text, "heartbeat"))

    def _fault(self, fault: DriveFault) -> None:
        log.error("%s", fault.text)
        self.faults.append(fault)
        for listener in self._fault_listeners:
            listener(fault)

    # -- access ---------------------------------------------------------------------------------
    def _check_lost(self) -> None:
        lost = self._lost
        if lost is not None:
            raise DriveBusError(lost)

    def _ready(self) -> None:
        self._check_lost()
        if not self._started:
            self.start()

    def _sdo_error(self, what: str, index: int, subindex: int, exc: Exception) -> DriveBusError:
        name = _object_name(index, subindex, self.gains)
        return DriveBusError(
            f"{self._who}: SDO {what} of 0x{index:04X}:{subindex:02X} ({name}) failed: {exc}"
        )

    def _read(self, index: int, subindex: int, fmt: str) -> int:
        try:
            with self._sdo_lock:
                raw = self._node.sdo.upload(index, subindex)
            value: int = struct.unpack(fmt, bytes(raw[: struct.calcsize(fmt)]))[0]
        except (SdoAbortedError, SdoCommunicationError, can.CanError, struct.error) as exc:
            self._check_lost()
            raise self._sdo_error("read", index, subindex, exc) from exc
        return value

    def _write(
        self, index: int, subindex: int, fmt: str, value: int, optional: bool = False
    ) -> None:
        try:
            with self._sdo_lock:
                self._node.sdo.download(index, subindex, struct.pack(fmt, value))
        except SdoAbortedError as exc:
            if optional and exc.code in _NO_OBJECT:
                log.info("%s: no object 0x%04X:%02X; skipped", self._who, index, subindex)
                return
            self._check_lost()
            raise self._sdo_error("write", index, subindex, exc) from exc
        except (SdoCommunicationError, can.CanError, struct.error) as exc:
            self._check_lost()
            raise self._sdo_error("write", index, subindex, exc) from exc

    def _nmt(self, command: int) -> None:
        try:
            self._node.nmt.send_command(command)
        except (can.CanError, RuntimeError) as exc:
            raise DriveBusError(
                f"{self._who}: NMT command 0x{command:02X} not sent: {exc}"
            ) from exc

    def _send(self, controlword: int, target: int, epoch: int | None = None) -> bool:
        """RPDO1: controlword and target in one frame, so the target is in place before the
        controlword that uses it. With ``epoch``, only while the axis is still in that epoch
        (a set-point's frames: see :attr:`_epoch`); returns whether the frame was sent."""
        with self._cw_lock:
            if epoch is not None and epoch != self._epoch:
                return False
            try:
                frame = _FRAME.pack(controlword, target)
                self.bus.network.send_message(0x200 + self.node_id, frame)
            except (can.CanError, RuntimeError) as exc:
                raise DriveBusError(f"{self._who}: RPDO1 not sent: {exc}") from exc
        return True

    def _state(self) -> DriveState | None:
        with self._cond:
            return state_of(self._status)

    def _await(self, done: Callable[[int], bool], what: str) -> int:
        """Wait (real time) for a statusword satisfying ``done``, from TPDO1; at the end, one
        SDO read in case an event was missed. A drive in FAULT is a motor fault; silence a bus
        one."""
        ok, status = self._wait_status(done)
        if ok:
            return status
        state = state_of(status)
        text = f"{self._who} did not reach {what} (statusword 0x{status:04X}, {_name(state)})"
        if state in (DriveState.FAULT, DriveState.FAULT_REACTION_ACTIVE):
            raise HardwareFault("motor_stall", text + self._last_fault())
        raise DriveBusError(text)

    def _wait_status(
        self, done: Callable[[int], bool], over: Callable[[int], str | None] | None = None
    ) -> tuple[bool, int]:
        """Wait (real time, :attr:`state_timeout_s`) for a statusword satisfying ``done``, from
        TPDO1, then one SDO read in case an event was missed: (satisfied, the statusword).

        Raises:
            DriveBusError: the drive is lost (no heartbeat, the bus gone).
            HardwareFault: ``motor_stall`` (:meth:`_given_up`) as soon as ``over`` names why
                waiting on is pointless.
        """
        deadline = time.monotonic() + self.state_timeout_s
        with self._cond:
            while True:
                if self._lost is not None:
                    raise DriveBusError(self._lost)
                why = None if over is None else over(self._status)
                if why is not None:
                    raise self._given_up(why)
                if done(self._status):
                    return True, self._status
                remaining = deadline - time.monotonic()
                if remaining <= 0.0:
                    break
                self._cond.wait(remaining)
        status = self._read(Obj.STATUSWORD, 0, "<H")
        with self._cond:
            self._status = status
            why = None if over is None else over(status)
        if why is not None:
            raise self._given_up(why)
        return done(status), status

    def _last_fault(self) -> str:
        return f": {self.faults[-1].text}" if self.faults else ""

    def _go(self, controlword: int, target: int, state: DriveState) -> None:
        self._send(controlword, target)
        self._await(lambda sw: state_of(sw) is state, state.value)

    def _enable(self, target: int) -> None:
        """Walk the state machine up to OPERATION ENABLED, ``target`` in every frame."""
        steps = {
            DriveState.SWITCH_ON_DISABLED: (SHUTDOWN, DriveState.READY_TO_SWITCH_ON),
            DriveState.READY_TO_SWITCH_ON: (SWITCH_ON, DriveState.SWITCHED_ON),
            DriveState.SWITCHED_ON: (ENABLE_OPERATION, DriveState.OPERATION_ENABLED),
            DriveState.QUICK_STOP_ACTIVE: (DISABLE_VOLTAGE, DriveState.SWITCH_ON_DISABLED),
        }
        for _ in range(len(steps) + 1):
            state = self._state()
            if state is DriveState.OPERATION_ENABLED:
                return
            if state is DriveState.NOT_READY_TO_SWITCH_ON:
                self._await(
                    lambda sw: state_of(sw) is not DriveState.NOT_READY_TO_SWITCH_ON,
                    "SWITCH ON DISABLED",
                )
                continue
            step = steps.get(state) if state is not None else None
            if step is None:
                raise HardwareFault(
                    "motor_stall",
                    f"{self._who} cannot be enabled from {_name(state)}{self._last_fault()}",
                )
            self._go(step[0], target, step[1])
        raise DriveBusError(f"{self._who}: the state machine did not reach OPERATION ENABLED")

    def _forget_move(self) -> None:
        """Whoever idles, holds or resets the axis takes its controlword over: the epoch moves
        on, so a set-point still waiting for its acknowledge gives up and sends nothing more."""
        with self._cw_lock:
            self._epoch += 1
        with self._cond:
            self._move = _Move.NONE
            self._cond.notify_all()

    def _await_set_point(
        self, done: Callable[[int], bool], what: str, epoch: int, *, sent: bool = False
    ) -> int:
        """:meth:`_await` for a step of the set-point handshake, which ends at once -- as a
        ``motor_stall``, never as a bus fault -- when the set-point can no longer be taken: the
        drive shows FAULT, a fault interrupted the move once ``sent`` (:meth:`_interrupted`),
        or the axis was idled, held or reset meanwhile (the epoch moved on: a reset has begun,
        and this worker must not fail it). Silence past :attr:`state_timeout_s` stays a bus
        fault."""

        def over(status: int) -> str | None:
            if epoch != self._epoch:
                return "the axis was stopped or reset meanwhile"
            if sent and self._move is _Move.ENDED:
                return "a fault interrupted it"
            if state_of(status) in (DriveState.FAULT, DriveState.FAULT_REACTION_ACTIVE):
                return "the drive is in FAULT"
            return None

        ok, status = self._wait_status(done, over)
        if ok:
            return status
        state = _name(state_of(status))
        raise DriveBusError(
            f"{self._who} did not reach {what} (statusword 0x{status:04X}, {state})"
        )

    def _given_up(self, why: str) -> HardwareFault:
        """The ``motor_stall`` a set-point that cannot be taken any more ends with."""
        return HardwareFault(
            "motor_stall", f"{self._who}: set-point given up ({why}){self._last_fault()}"
        )

    # -- MotionAxis -----------------------------------------------------------------------------
    def actual_position(self) -> int:
        """0x6064 position actual value (counts), read now."""
        self._ready()
        return self._read(Obj.POSITION_ACTUAL, 0, "<i")

    def command_position(self) -> int:
        """0x6062 position demand value: the profile's present set-point (counts)."""
        self._ready()
        return self._read(Obj.POSITION_DEMAND, 0, "<i")

    def statusword(self) -> int:
        """0x6041, read now."""
        self._ready()
        status = self._read(Obj.STATUSWORD, 0, "<H")
        with self._cond:
            self._status = status
        return status

    def configure(self, params: MotorParams) -> None:
        """The profile limits converted into 0x6081/0x6083/0x6084, and the sample and filter
        values raw into the objects ``gains`` names, if any (module notes); read back for the
        pan reference."""
        self._ready()
        for key, obj in self.gains.items():
            self._write(obj.index, obj.subindex, obj.fmt, getattr(params, key))
        unmapped = [key for key in GAIN_KEYS if key not in self.gains]
        if unmapped and self._loaded is None:  # said once: every reset loads them again
            log.info(
                "%s: %s not written (no gain object named for them): the drive's own tuning",
                self._who,
                ", ".join(unmapped),
            )
        velocity, accel = profile_for(params)
        self._write(Obj.PROFILE_VELOCITY, 0, "<I", velocity)
        self._write(Obj.PROFILE_ACCELERATION, 0, "<I", accel)
        self._write(Obj.PROFILE_DECELERATION, 0, "<I", accel)
        self._loaded = params
        if self.reference is not None:
            self.reference.configured(self.read_params())

    def read_params(self) -> dict[str, int]:
        """BIRIS_MOTOR_PARAMS as the drive holds them, in :meth:`MotorParams.to_dict`'s keys.

        A drive holds the profile (converted) and the mapped gains, not the six raw values, so
        this is the set last loaded here -- or, after a restart of the driver, the one the pan
        reference's journal names -- when the drive's 0x6081/0x6083/0x6084 and mapped gains
        hold exactly what that set converts to; otherwise the drive's own values (0x6081 as
        ``max_vel``, 0x6083 as ``max_accel``, each mapped gain as read, 0 for the others),
        which no init record converts to: a drive that restored its power-on profile."""
        self._ready()
        held = {
            key: self._read(obj.index, obj.subindex, obj.fmt) for key, obj in self.gains.items()
        }
        profile = self.profile_params()
        candidates: list[Mapping[str, int]] = []
        if self._loaded is not None:
            candidates.append(self._loaded.to_dict())
        journal = self.reference.state.params if self.reference is not None else None
        if journal is not None:
            candidates.append(journal)
        for candidate in candidates:
            if self._holds(candidate, held, profile):
                return dict(candidate)
        own = dict.fromkeys(PARAM_KEYS, 0)
        own.update(held)
        own["max_vel"], own["max_accel"] = profile[0], profile[1]
        return own

    @staticmethod
    def _holds(
        candidate: Mapping[str, int], held: Mapping[str, int], profile: tuple[int, int, int]
    ) -> bool:
        """The drive holds what ``candidate`` (a raw BIRIS_MOTOR_PARAMS set) converts to."""
        try:
            params = MotorParams(**{key: candidate[key] for key in PARAM_KEYS})
        except (KeyError, TypeError, RequestError):
            return False  # not a set an init record could hold
        velocity, accel = profile_for(params)
        if profile != (velocity, accel, accel):
            return False
        return all(getattr(params, key) == value for key, value in held.items())

    def profile_params(self) -> tuple[int, int, int]:
        """(0x6081, 0x6083, 0x6084) as the drive holds them."""
        self._ready()
        return (
            self._read(Obj.PROFILE_VELOCITY, 0, "<I"),
            self._read(Obj.PROFILE_ACCELERATION, 0, "<I"),
            self._read(Obj.PROFILE_DECELERATION, 0, "<I"),
        )

    def idle(self) -> None:
        """Disable operation (or voltage, from a quick stop): no torque, the head coasts. A
        move under way is forgotten, as the HCTL-1000's idle clears F0."""
        self._ready()
        self._forget_move()
        state = self._state()
        if state is DriveState.OPERATION_ENABLED:
            self._go(DISABLE_OPERATION, self._target, DriveState.SWITCHED_ON)
        elif state is DriveState.QUICK_STOP_ACTIVE:
            self._go(DISABLE_VOLTAGE, self._target, DriveState.SWITCH_ON_DISABLED)

    def hold_here(self, zero_counter: bool = False) -> None:
        """Enter OPERATION ENABLED holding the present position: the target is the position
        actual in every frame of the way up, so nothing jumps. ``zero_counter`` first makes
        this spot 0 (homing on the current position). Called with the axis idle; an enabled
        axis is disabled first."""
        self._ready()
        self._forget_move()
        if self._state() is DriveState.OPERATION_ENABLED:
            self._go(DISABLE_OPERATION, self._target, DriveState.SWITCHED_ON)
        if zero_counter:
            self._zero_here()
            return
        here = self._read(Obj.POSITION_ACTUAL, 0, "<i")
        self._set_mode(Mode.PROFILE_POSITION)
        self._target = here
        self._enable(here)

    def _zero_here(self) -> None:
        """Homing on the current position with home offset 0: position actual becomes 0 and
        the drive holds it, back in profile position (OPERATION ENABLED). Started only once the
        mode display shows homing; bit 4 (homing active) falls only once fresh reads show it
        done (:meth:`_await_homed`): CiA 402 takes bit 4's fall during homing as "interrupt
        homing", and a drive may show "homing attained" kept from an earlier homing."""
        here = self._read(Obj.POSITION_ACTUAL, 0, "<i")
        self._set_mode(Mode.HOMING)
        self._write(Obj.HOMING_METHOD, 0, "<b", self.homing_method)
        self._write(Obj.HOME_OFFSET, 0, "<i", 0)
        self._target = here
        self._enable(here)
        self._send(ENABLE_OPERATION | Cw.NEW_SET_POINT, here)
        self._await_homed(here)
        self._target = 0
        self._send(ENABLE_OPERATION, 0)
        self._set_mode(Mode.PROFILE_POSITION)

    def _await_homed(self, here: int) -> None:
        """Poll, by SDO (fresh: a statusword kept in a TPDO may predate the start), until the
        statusword shows homing attained with target reached (bits 12 and 10) and the position
        actual reads 0 within the position window; a homing error (bit 13) or FAULT is a
        ``motor_stall``, a drive that shows "attained" but never reads 0 a ``protocol`` fault
        (it kept bit 12 from an earlier homing and did not home), one that never gets there a
        bus fault, as any state not reached. ``here`` is where the head stood (for the
        message)."""
        homed = Sw.SET_POINT_ACKNOWLEDGE | Sw.TARGET_REACHED
        deadline = time.monotonic() + self.state_timeout_s
        actual: int | None = None
        while True:
            status = self.statusword()
            state = state_of(status)
            if state in (DriveState.FAULT, DriveState.FAULT_REACTION_ACTIVE):
                raise HardwareFault(
                    "motor_stall", f"{self._who}: faulted while homing{self._last_fault()}"
                )
            if status & Sw.FOLLOWING_ERROR:
                raise HardwareFault("motor_stall", f"{self._who}: homing error (0x{status:04X})")
            if status & homed == homed:
                actual = self._read(Obj.POSITION_ACTUAL, 0, "<i")
                if abs(actual) <= self.position_window:
                    return
            if time.monotonic() > deadline:
                break
            with self._cond:
                self._cond.wait(_POLL_S)
        if actual is not None:
            raise HardwareFault(
                "protocol",
                f"{self._who} shows homing attained (statusword 0x{status:04X}) but its "
                f"position actual reads {actual}, not 0 (the head stood at {here}): it keeps "
                "bit 12 from an earlier homing and did not home on the current position "
                f"(method {self.homing_method}, home offset 0)",
            )
        raise DriveBusError(
            f"{self._who} did not reach homing attained (statusword 0x{status:04X}, {_name(state)})"
        )

    def reset(self) -> None:
        """The board's chip reset: clear a fault, take the voltage off, let the head come to
        rest, and restart the count at 0 there; left SWITCHED ON (no torque)."""
        self._ready()
        self._forget_move()
        state = self._state()
        if state in (DriveState.FAULT, DriveState.FAULT_REACTION_ACTIVE):
            self._send(DISABLE_VOLTAGE, self._target)
            self._go(FAULT_RESET, self._target, DriveState.SWITCH_ON_DISABLED)
        if self._state() is not DriveState.SWITCH_ON_DISABLED:
            self._go(DISABLE_VOLTAGE, self._target, DriveState.SWITCH_ON_DISABLED)
        self.wait_still(threading.Event())
        self._zero_here()
        self._go(DISABLE_OPERATION, 0, DriveState.SWITCHED_ON)

    def prepare_trapezoid(self, destination: int) -> None:
        """Record the move :meth:`start_trapezoid` of ``destination`` will make in the pan
        reference's journal now (as :meth:`biris_hw.devices.AxisDriver.prepare_trapezoid`)."""
        if self.reference is None:
            return
        dest = self.reference.safe_destination(clamp_counts(destination))
        self.reference.record_move(self.command_position(), dest)

    def start_trapezoid(self, destination: int) -> int:
        """Send a profile-position set-point; returns the destination commanded.

        Clamped to +-0x1000 (and cut by the pan reference, which records the move first), as
        :meth:`biris_hw.devices.AxisDriver.start_trapezoid`. A move not yet ended, or a drive
        not in OPERATION ENABLED, is HardwareFault("motor_stall"); a set-point the drive does
        not acknowledge in time is a DriveBusError.
        """
        epoch = self._epoch  # first: an idle, hold or reset from here on abandons this set-point
        self._ready()
        dest = clamp_counts(destination)
        if self.reference is not None:
            dest = self.reference.safe_destination(dest)
        if dest != destination:
            log.warning("destination %d clamped to %d", destination, dest)
        with self._cond:
            if self._move in (_Move.REQUESTED, _Move.ACKNOWLEDGED):
                raise HardwareFault("motor_stall", f"{self._who}: previous move never ended")
            state = state_of(self._status)
        if state is not DriveState.OPERATION_ENABLED:
            raise HardwareFault(
                "motor_stall", f"{self._who} is {_name(state)}, not moving{self._last_fault()}"
            )
        if self.reference is not None:
            self.reference.record_move(self.command_position(), dest)
        # CiA 402's handshake: bit 4 rises only once the drive shows bit 12 clear, i.e. it has
        # seen bit 4 fall after the previous set-point (a drive ignores an edge before that)
        self._await_set_point(
            lambda sw: not sw & Sw.SET_POINT_ACKNOWLEDGE, "set-point acknowledge cleared", epoch
        )
        with self._cond:
            # the epoch moves on before the move is forgotten: seen unchanged here, a forget
            # still to come clears this REQUESTED, never the other way round
            taken = epoch == self._epoch
            if taken:
                self._move = _Move.REQUESTED
        self._target = dest
        if not taken or not self._send(ENABLE_OPERATION | Cw.NEW_SET_POINT, dest, epoch):
            raise self._given_up("the axis was stopped or reset meanwhile")
        try:
            self._await_set_point(
                lambda sw: bool(sw & Sw.SET_POINT_ACKNOWLEDGE),
                "set-point acknowledge",
                epoch,
                sent=True,
            )
        finally:
            # bit 4 falls, unless the axis has been taken over meanwhile (whoever idled, held
            # or reset it sends its own controlwords, none with bit 4 set)
            self._send(ENABLE_OPERATION, dest, epoch)
        return dest

    def profile_active(self) -> bool:
        """A move sent here has not been reported ended (nor forgotten by idle/hold/reset)."""
        self._ready()
        with self._cond:
            return self._move in (_Move.REQUESTED, _Move.ACKNOWLEDGED)

    def wait_settled(
        self,
        stop: StopEvent,
        limit_s: float = SETTLE_LIMIT_S,
        sample_s: float = SETTLE_POLL_S,
    ) -> bool:
        """:func:`biris_hw.axes.base.wait_settled` on 0x6064 against 0x6062 (the HCTL rule),
        only while the drive is OPERATION ENABLED (a faulted drive's demand follows the head);
        the settle position goes to the pan reference."""
        if self._state() in (DriveState.FAULT, DriveState.FAULT_REACTION_ACTIVE):
            return False  # its demand follows the head: nothing to wait for
        pos = wait_settled(
            lambda: (self.actual_position(), self.command_position()),
            self._clock,
            self._scale,
            stop,
            limit_s,
            sample_s,
            holding=lambda: self._state() is DriveState.OPERATION_ENABLED,
        )
        if pos is None:
            return False
        if self.reference is not None:
            self.reference.settled(pos)
        return True

    def wait_still(self, stop: StopEvent, limit_s: float = 2.0, sample_s: float = 0.002) -> None:
        wait_still(self.actual_position, self._clock, self._scale, stop, limit_s, sample_s)

    # -- the index latch ------------------------------------------------------------------------
    def index_seen(self) -> bool:
        """Touch probe 1 has latched the encoder's zero impulse since last armed (0x60B9)."""
        self._ready()
        return bool(self._read(Obj.TOUCH_PROBE_STATUS, 0, "<H") & TOUCH_PROBE_STORED)

    def clear_index(self) -> None:
        """Re-arm touch probe 1 (0x60B8 off, then on: the enable's edge clears the latch)."""
        self._ready()
        self._write(Obj.TOUCH_PROBE_FUNCTION, 0, "<H", 0)
        self._write(Obj.TOUCH_PROBE_FUNCTION, 0, "<H", TOUCH_PROBE_INDEX)

    def index_position(self) -> int:
        """0x60BA: where touch probe 1 latched the index (counts)."""
        self._ready()
        return self._read(Obj.TOUCH_PROBE_1_POSITIVE, 0, "<i")


_AXIS_BIT = {Axis.AZIMUTH: int(AxisBit.AZIMUTH), Axis.ELEVATION: int(AxisBit.ELEVATION)}


class Cia402Controller:
    """The board's part for CiA 402 axes: a :class:`~biris_hw.axes.base.MotionController`.

    ``end_of_motion`` is the level-3 line: triggered when an axis's move ends (its bit newly
    set in :meth:`ended_axes` while enabled), and whenever the controller comes to *hold* a
    fault, whatever the axes are doing and whether or not their end of scan is enabled: a
    drive's heartbeat lost or a communication EMCY (kind ``bus``), or any other EMCY (kind
    ``motor_stall``: over-current, a following error, a drive fault), from a drive standing
    idle as much as from one moving. :meth:`take_fault` then hands the held fault, once, to the
    level-3 routine, which raises it; the server's supervisor reports it with its own kind to
    every caller at once (not when the next move is asked for), and the line stays usable after
    the reset. A ``motor_stall`` EMCY also ends the move it interrupted
    (:meth:`Cia402Axis._interrupted`), as the HCTL-1000 ends its profile.

    **One report per fault.** Once a fault is held, later EMCYs (a drive often sends several
    for one failure, and the other drive may react to it) are recorded but not held again
    until the next chip reset (:meth:`reset_chip`: the server's reset, whose fault resets clear
    them). Otherwise one held after the level-3 routine had raised the first (and so waits for
    the reset) would be raised as that reset restarts the routine, before the initialiser's
    chip resets clear it, and fail the reset with a fault already gone. A held ``motor_stall``
    fault of an axis is dropped by that axis's chip reset. A lost heartbeat is always held; it
    is dropped when :meth:`relink` brings that drive back (the reset re-links before it
    initialises, and fails with ``bus`` while the drive stays silent). ``on_fault`` (and
    :attr:`faults`) receive every :class:`DriveFault` of every axis.
    """

    def __init__(
        self,
        bus: Cia402Bus,
        axes: Mapping[Axis, Cia402Axis],
        end_of_motion: EventFdLine | None = None,
        on_fault: Callable[[DriveFault], None] | None = None,
    ) -> None:
        self.bus = bus
        self.axes = dict(axes)
        self.end_of_motion = end_of_motion if end_of_motion is not None else EventFdLine()
        self.on_fault = on_fault
        self.faults: list[DriveFault] = []
        self._lock = threading.Lock()
        self._enabled = 0
        self._ended = 0
        self._pending: DriveFault | None = None
        self._reported = False
        """A fault has been held since the last chip reset: later EMCYs are only recorded."""
        for driver in self.axes.values():
            driver.add_end_listener(self._move_ended)
            driver.add_fault_listener(self._fault)

    def start(self) -> None:
        """Set every drive up now rather than on first use."""
        for driver in self.axes.values():
            driver.start()

    def relink(self) -> None:
        """Bring back every drive whose heartbeat was lost (:meth:`Cia402Axis.relink`), and
        drop a fault still held for it: the drive is set up afresh, and the reset's chip reset
        clears the rest. Raises :class:`DriveBusError` for the first drive that stays silent."""
        for axis, driver in self.axes.items():
            if not driver.lost:
                continue
            driver.relink()
            with self._lock:
                pending = self._pending
                if pending is not None and pending.axis is axis:
                    log.info("%s: the drive is back", pending.text)
                    self._pending = None
                self._reported = self._pending is not None

    def _move_ended(self, axis: Axis) -> None:
        bit = _AXIS_BIT[axis]
        with self._lock:
            fresh = not self._ended & bit
            self._ended |= bit
            raise_it = fresh and bool(self._enabled & bit)
        if raise_it and not self.end_of_motion.closed:
            try:
                self.end_of_motion.trigger()
            except Exception as exc:  # closed meanwhile: the supervisor has heard already
                log.info("end of motion on %s not raised: %s", axis.name, exc)

    def _fault(self, fault: DriveFault) -> None:
        """Record every fault; hold one and raise the line (see the class notes)."""
        with self._lock:
            self.faults.append(fault)
            hold = self._pending is None and (fault.source == "heartbeat" or not self._reported)
            if hold:
                self._pending = fault
                self._reported = True
        if hold and not self.end_of_motion.closed:
            try:
                self.end_of_motion.trigger()
            except Exception as exc:  # closed meanwhile: the server is closing
                log.info("fault on %s not raised: %s", fault.axis.name, exc)
        elif not hold:
            log.info("%s: recorded; a fault is already being reported", fault.text)
        if self.on_fault is not None:
            self.on_fault(fault)

    def _axis(self, axis: Axis) -> Cia402Axis:
        try:
            return self.axes[axis]
        except KeyError:
            raise HardwareFault("protocol", f"no CiA 402 drive for the {axis.name}") from None

    # -- MotionController -----------------------------------------------------------------------
    def reset_chip(self, axis: Axis) -> None:
        """The drive's fault reset, then its count restarted at 0 where the head stands
        (:meth:`Cia402Axis.reset`). Its ``motor_stall`` fault still held is dropped (the
        fault reset cleared it), and faults are held again from here on."""
        self._axis(axis).reset()
        with self._lock:
            self._ended &= ~_AXIS_BIT[axis]
            pending = self._pending
            if pending is not None and pending.axis is axis and pending.kind != "bus":
                log.info("%s: cleared by the chip reset", pending.text)
                self._pending = None
            self._reported = self._pending is not None

    def enable_end_of_scan(self, axis: Axis, vector: int, enabled: bool = True) -> None:
        """``vector`` has no meaning on CAN and is ignored."""
        bit = _AXIS_BIT[axis]
        with self._lock:
            self._enabled = self._enabled | bit if enabled else self._enabled & ~bit

    def disable_all(self) -> None:
        with self._lock:
            self._enabled = 0

    def index_seen(self, axis: Axis) -> bool:
        return self._axis(axis).index_seen()

    def clear_index(self, axis: Axis) -> None:
        self._axis(axis).clear_index()

    def acknowledge(self, axis: Axis) -> None:
        with self._lock:
            self._ended &= ~_AXIS_BIT[axis]

    def ended_axes(self) -> int:
        with self._lock:
            return self._ended

    def take_fault(self) -> HardwareFault | None:
        """The fault held since last asked, as the exception to raise, once: a
        :class:`DriveBusError` for ``bus``, a ``HardwareFault("motor_stall")`` naming the EMCY
        otherwise; None when there is none."""
        with self._lock:
            pending, self._pending = self._pending, None
        return pending.error() if pending is not None else None

    def close(self) -> None:
        """Stop listening to the drives and close the line (the bus is its owner's)."""
        for driver in self.axes.values():
            driver.close()
        self.end_of_motion.close()


class Cia402Axes:
    """Pan and tilt as two CiA 402 drives on one CAN bus: an :class:`~biris_hw.axes.base.AxisSet`.

    Owns the :class:`Cia402Bus` it makes from ``can_config`` (python-can's ``can.Bus`` keywords;
    none at all: python-can's own configuration, its config file or ``CAN_*`` environment) and
    closes it. Nothing is sent before the first use: the drives are set up by the server's
    initialisation (or :meth:`Cia402Controller.start` on :attr:`controller`).

    ``gains`` (both drives: the same model) and ``homing_method`` are :class:`Cia402Axis`'s.

    Raises:
        DriveBusError: the CAN interface cannot be opened.
        ValueError: a node id outside 1..127, both axes on one node, bad heartbeat times, a
            homing method or gains mapping the driver does not take.
    """

    def __init__(
        self,
        *,
        pan_node: int,
        tilt_node: int,
        clock: Callable[[], float] = time.monotonic,
        time_scale: float = 1.0,
        heartbeat_period_s: float = 0.1,
        heartbeat_timeout_s: float = 0.35,
        master_id: int | None = DEFAULT_MASTER_ID,
        sdo_timeout_s: float = 0.3,
        state_timeout_s: float = 0.5,
        boot_timeout_s: float = 1.0,
        homing_method: int = DEFAULT_HOMING_METHOD,
        gains: Mapping[str, GainObject | str] | None = None,
        **can_config: Any,
    ) -> None:
        check_node_id(pan_node, "pan_node")  # before the bus is opened
        check_node_id(tilt_node, "tilt_node")
        check_homing_method(homing_method)
        checked_gains = check_gains(gains or {})
        if pan_node == tilt_node:
            raise ValueError(f"pan and tilt cannot both be node {pan_node}")
        self.bus = Cia402Bus(
            heartbeat_period_s=heartbeat_period_s,
            heartbeat_timeout_s=heartbeat_timeout_s,
            master_id=master_id,
            sdo_timeout_s=sdo_timeout_s,
            **can_config,
        )
        options: dict[str, Any] = {
            "gains": checked_gains,
            "homing_method": homing_method,
            "state_timeout_s": state_timeout_s,
            "boot_timeout_s": boot_timeout_s,
        }
        self.pan = Cia402Axis(self.bus, pan_node, Axis.AZIMUTH, clock, time_scale, **options)
        self.tilt = Cia402Axis(self.bus, tilt_node, Axis.ELEVATION, clock, time_scale, **options)
        self._controller = Cia402Controller(
            self.bus, {Axis.AZIMUTH: self.pan, Axis.ELEVATION: self.tilt}
        )
        self._closed = False

    def __repr__(self) -> str:
        return f"Cia402Axes(pan node {self.pan.node_id}, tilt node {self.tilt.node_id})"

    @property
    def azimuth(self) -> MotionAxis:
        return self.pan

    @property
    def elevation(self) -> MotionAxis:
        return self.tilt

    @property
    def controller(self) -> Cia402Controller:
        return self._controller

    @property
    def end_of_motion(self) -> EventFdLine:
        return self._controller.end_of_motion

    @property
    def faults(self) -> list[DriveFault]:
        """Every fault either drive reported, oldest first."""
        return list(self._controller.faults)

    def use_pan_reference(self, reference: PanReference) -> None:
        self.pan.reference = reference

    def relink(self) -> None:
        """:meth:`Cia402Controller.relink`: every drive whose heartbeat was lost brought back
        (NMT reset communication, set up as at the first use), or a :class:`DriveBusError`
        (``HardwareFault("bus")``) naming the drive that stays silent."""
        if self._closed:
            raise DriveBusError(f"{self!r} is closed")
        self._controller.relink()

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._controller.close()
        self.bus.close()


def stop_periodic_task(task: Any) -> None:
    """Stop a python-can periodic send (a canopen ``PeriodicMessageTask``) and wait for its
    thread: python-can's ``stop`` only asks, and a thread still sending after its bus is shut
    down dies with a traceback."""
    if task is None:
        return
    task.stop()
    thread = getattr(getattr(task, "_task", None), "thread", None)
    if isinstance(thread, threading.Thread) and thread is not threading.current_thread():
        thread.join(timeout=1.0)


def _conforms(
    axis: Cia402Axis, controller: Cia402Controller, axes: Cia402Axes
) -> tuple[MotionAxis, MotionController, AxisSet]:
    """Never called: mypy checks the classes against the protocols here."""
    return axis, controller, axes


def _ms(seconds: float) -> int:
    return max(1, min(0xFFFF, round(seconds * 1000.0)))


def _name(state: DriveState | None) -> str:
    return state.value if state is not None else "an unknown state"

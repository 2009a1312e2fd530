"""A simulated CiA 402 servo drive on a CANopen bus, closing its loop around :class:`MotorPlant`.

:class:`SimulatedDrive` is a canopen :class:`~canopen.LocalNode` whose object dictionary is
built here. By default it is a *stock* drive: standard objects only (CiA 301's 0x1000, 0x1001,
0x1016, 0x1017, RPDO1/TPDO1 communication and mapping; CiA 402's state machine, profile position,
homing, touch probe, factor group and SI units), so that a driver writing anything else gets the
SDO abort a stock drive answers (0x06020000, object does not exist). Its position loop runs the
drive's own commissioned tuning (:attr:`DriveVariant.tuning`), which no object exposes, as on a
stock drive. A :class:`DriveVariant` describes a drive that differs (the tests' way in): one with
a manufacturer record of its own for its loop's sample period and filter (0x2000 sub 1-4,
``gain_record``), other power-on values (its units), objects it lacks, one that keeps "homing
attained" from an earlier homing, one that takes a new mode (and finishes homing) only at a later
cycle. Its write callbacks run the drive; a thread steps it on the simulator's clock (and every
SDO read catches up first, as :mod:`sim.hctl1000` does on access), so the end of a move is
announced by itself, as a real drive's event TPDO is.

What is modelled:

* NMT (canopen's NmtSlave): pre-operational after boot-up, heartbeat producer 0x1017, PDOs only
  while OPERATIONAL, TPDO1 sent once on entering it. Heartbeat consumer 0x1016 sub 1: a master
  heard once and then silent for longer than the consumer time faults the drive (EMCY 0x8130).
  Reset communication (0x82) puts the communication objects (0x1000-0x1FFF) back to their
  power-on values, reset node (0x81) everything, as a power-up does; both end with the boot-up
  message and pre-operational.
* PDOs honour whatever mapping the master wrote (CiA 301 rules: the mapping, and the inhibit
  time, change only while the PDO is invalid and its count is 0; only mappable objects; 64 bits
  at most). An RPDO's values are all stored before its controlword acts, so a frame's target is
  the one its new-set-point edge takes. TPDO1 (type 254/255) is sent as drives send an
  event-driven PDO: whenever any mapped object's value changes (with the position actual mapped,
  a frame per sample in which the head moved), no sooner than the inhibit time (sub 3, 100 us
  units) after the last one -- a change meanwhile goes out when it expires -- and, with an event
  timer (sub 5, ms), at least that often. Its times are the drive's clock's.
* The power state machine (SWITCH ON DISABLED -> READY TO SWITCH ON -> SWITCHED ON ->
  OPERATION ENABLED; quick stop; fault and fault reset on bit 7's rising edge). Enabling holds
  the head where it stands (a compliant drive).
* Modes of operation: 0x6060 written takes effect at once (the display 0x6061 shows it), or, with
  ``mode_at_cycle``, at the drive's next cycle, as a drive running its modes in its control loop
  does; until then the drive acts in the mode its display shows.
* Profile position: single set-point, absolute (bit 6 relative too); acknowledge (bit 12) on
  the new-set-point edge, dropped at the first cycle (sample) after bit 4 falls, and a rising
  edge while bit 12 is still set is not taken (CiA 402's handshake: the host waits for bit 12
  to fall before it sets bit 4 again); a trapezoid from 0x6081/0x6083/0x6084 (counts/s and
  counts/s^2, whatever the unit objects say: they are only reported) sampled at the loop's sample
  period; target reached (bit 10) once the profile has ended and the head is within 0x6067 for
  0x6068 ms. A new set-point during a move re-plans from where the profile is (and is audited).
  Halt (bit 8) is not modelled.
* The position loop is the HCTL-1000's filter, ``MC = (K/4)(X - (A/256) X[n-1]) - (B/256)
  MC[n-1]``, at its sample period 16 (T + 1) / 2 MHz: from the drive's tuning (Appendix B's
  values, so that the loop is the one sim.motor documents), or, with ``gain_record``, from the raw
  0x2000 values the master wrote (the mapping a drive "with such gains" makes).
* Following error: beyond 0x6065 for longer than 0x6066 ms -> FAULT, EMCY 0x8611 (a stalled
  shaft, :meth:`SimulatedDrive.stall`, ends that way as soon as a move pulls away from it).
* Homing methods 35/37 (mode 6, bit 4's rising edge starts it, its fall before the end interrupts
  it, as does leaving the mode or OPERATION ENABLED): the position actual becomes the home offset
  0x607C, at once or ``homing_s`` later; the statusword shows homing in progress (bits 12, 10
  clear), attained (12 and 10), interrupted or not started (10), error (13). "Homing attained" is
  cleared by a mode change or re-enabling, unless ``keeps_homing_attained`` (then only a new
  homing or a power-on clears it).
* Touch probe 1 on the zero impulse (0x60B8/0x60B9/0x60BA): the plant's index latch.
* Power-on: the profile objects hold the drive's own values (not BIRIS's; with ``gain_record``
  its record holds :data:`POWER_UP_PARAMS`' filter), the position actual starts at 0 where the
  head stands.
* The fault panel: :meth:`stall`, :meth:`lose_power` (no heartbeat, no answers, no torque) and
  :meth:`restore_power` (a power-on as above, the boot-up message included),
  :meth:`disconnect` and :meth:`reconnect` (the CAN cable: nothing heard or sent meanwhile, the
  drive keeps its state and faults as a heartbeat consumer), :meth:`emcy`.

The drive's own audit (:attr:`SimulatedDrive.violations`, and the shared
:class:`~sim.audit.Audit` where a rule has a counterpart there): a set-point beyond +-0x1000
(MOTOR_BEYOND_LIMIT), a set-point while not OPERATION ENABLED, entering OPERATION ENABLED with
a target more than :data:`JUMP_COUNTS` from the position actual (POSITION_MODE_WHILE_MOVING:
a drive that takes its target on enabling would jump), a new set-point while the previous move
runs, a new set-point edge while bit 12 still acknowledges the previous one (ignored, as a
drive does), a set-point before the profile (and, with ``gain_record``, the record) was written
(MOTION_WHILE_UNINITIALISED), an RPDO while not OPERATIONAL.
"""

from __future__ import annotations

import collections
import enum
import logging
import math
import struct
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import canopen
from canopen import objectdictionary as od
from canopen.sdo.exceptions import SdoAbortedError

from biris_hw.axes.cia402 import (
    CIA402_PROFILE,
    NOTIFIER_CYCLE_S,
    SI_INCREMENT,
    SI_SECOND,
    Cw,
    DriveState,
    Sw,
    stop_periodic_task,
)
from biris_hw.records import MotorParams
from regs.hctl1000 import F_CLK_HZ, MOTION_LIMIT_COUNTS, SAMPLE_TIMER_MIN
from sim.audit import Audit, Rule, Violation
from sim.motor import MotorPlant

__all__ = [
    "DRIVE_TUNING",
    "GAIN_RECORD",
    "JUMP_COUNTS",
    "POWER_UP_PARAMS",
    "STOCK",
    "DriveRule",
    "DriveVariant",
    "SimulatedDrive",
    "build_dictionary",
]

log = logging.getLogger(__name__)

JUMP_COUNTS = 2
"""Enabling with a target further than this from the position actual is audited: a drive
that starts from its target would jump."""

STEP_REAL_S = 0.001
"""How often (real seconds) the drive's thread catches up with the clock."""

MAX_CATCH_UP = 20_000
"""Samples one catch-up may run (28 hardware seconds at Appendix B's period); a host further
behind skips the rest rather than stall the bus thread."""

HISTORY = 4096
"""Samples of position actual kept for :meth:`SimulatedDrive.position_at` (5.8 hardware
seconds at Appendix B's sample period)."""

EMCY_FOLLOWING_ERROR = 0x8611
EMCY_HEARTBEAT = 0x8130

_BASE = {
    DriveState.NOT_READY_TO_SWITCH_ON: 0x00,
    DriveState.SWITCH_ON_DISABLED: 0x40,
    DriveState.READY_TO_SWITCH_ON: 0x31,
    DriveState.SWITCHED_ON: 0x33,
    DriveState.OPERATION_ENABLED: 0x37,
    DriveState.QUICK_STOP_ACTIVE: 0x17,
    DriveState.FAULT_REACTION_ACTIVE: 0x0F,
    DriveState.FAULT: 0x08,
}
"""Statusword state bits (with voltage enabled, bit 4, where the power stage is on)."""

_PACK = {
    od.UNSIGNED8: "<B",
    od.INTEGER8: "<b",
    od.UNSIGNED16: "<H",
    od.INTEGER16: "<h",
    od.UNSIGNED32: "<I",
    od.INTEGER32: "<i",
}
"""How a mapped object of each data type goes into a PDO (CiA 301: little-endian)."""

_REMOTE = int(Sw.REMOTE)
_TARGET_REACHED = int(Sw.TARGET_REACHED)
_ACKNOWLEDGE = int(Sw.SET_POINT_ACKNOWLEDGE)
_FOLLOWING_ERROR = int(Sw.FOLLOWING_ERROR)


def _encoder(var: od.ODVariable, nbytes: int) -> Callable[[int], bytes]:
    """canopen's own encoding of ``var``, cut to the mapped length."""
    return lambda value: bytes(var.encode_raw(value)[:nbytes])


_MAPPABLE_RX = frozenset({(0x6040, 0), (0x607A, 0), (0x6060, 0), (0x60B8, 0)})
_MAPPABLE_TX = frozenset({(0x6041, 0), (0x6064, 0), (0x6061, 0), (0x6062, 0), (0x60B9, 0)})

_SUPPORTED_MODES = (1, 6)


class DriveRule(str, enum.Enum):
    """The drive's audit rules; the value is the name used in reports."""

    TARGET_BEYOND_LIMIT = "TARGET_BEYOND_LIMIT"
    SET_POINT_NOT_ENABLED = "SET_POINT_NOT_ENABLED"
    ENABLE_WITH_JUMP = "ENABLE_WITH_JUMP"
    SET_POINT_WHILE_MOVING = "SET_POINT_WHILE_MOVING"
    SET_POINT_WHILE_ACKNOWLEDGED = "SET_POINT_WHILE_ACKNOWLEDGED"
    MOVE_UNCONFIGURED = "MOVE_UNCONFIGURED"
    RPDO_NOT_OPERATIONAL = "RPDO_NOT_OPERATIONAL"


_SHARED = {
    DriveRule.TARGET_BEYOND_LIMIT: Rule.MOTOR_BEYOND_LIMIT,
    DriveRule.ENABLE_WITH_JUMP: Rule.POSITION_MODE_WHILE_MOVING,
    DriveRule.MOVE_UNCONFIGURED: Rule.MOTION_WHILE_UNINITIALISED,
}


def _var(
    name: str,
    index: int,
    subindex: int,
    data_type: int,
    default: int = 0,
    access: str = "rw",
) -> od.ODVariable:
    var = od.ODVariable(name, index, subindex)
    var.data_type = data_type
    var.access_type = access
    var.default = default
    var.pdo_mappable = (index, subindex) in _MAPPABLE_RX | _MAPPABLE_TX
    return var


def _record(name: str, index: int, members: list[tuple[str, int, int, str]]) -> od.ODRecord:
    record = od.ODRecord(name, index)
    count = max(sub for _, sub, _, _ in members)
    record.add_member(_var(f"{name} entries", index, 0, od.UNSIGNED8, count, "ro"))
    for member, sub, default, access in members:
        data_type = od.UNSIGNED16 if index == GAIN_RECORD else od.UNSIGNED32
        if member in ("transmission type",):
            data_type = od.UNSIGNED8
        elif member in ("inhibit time", "event timer"):
            data_type = od.UNSIGNED16
        record.add_member(_var(member, index, sub, data_type, default, access))
    return record


def _ratio(name: str, index: int, terms: tuple[int, int], names: tuple[str, str]) -> od.ODArray:
    """A factor-group object: two UNSIGNED32 terms, sub 1 over sub 2 (CiA 402)."""
    array = od.ODArray(name, index)
    array.add_member(_var(f"{name} entries", index, 0, od.UNSIGNED8, 2, "ro"))
    for sub, (term, what) in enumerate(zip(terms, names, strict=True), start=1):
        array.add_member(_var(f"{name} {what}", index, sub, od.UNSIGNED32, term))
    return array


def _mapping(name: str, index: int) -> od.ODRecord:
    record = od.ODRecord(name, index)
    record.add_member(_var(f"{name} entries", index, 0, od.UNSIGNED8, 0, "rw"))
    for sub in range(1, 9):
        record.add_member(_var(f"{name} {sub}", index, sub, od.UNSIGNED32, 0))
    return record


POWER_UP_PARAMS = MotorParams(sample=0x40, zero=0xE5, pole=0x00, gain=0x40, max_vel=1, max_accel=1)
"""The filter a ``gain_record`` drive's record holds at power-on: its firmware's own values, not
BIRIS's (the HCTL-1000 model's power-up filter, :data:`sim.hctl1000.POWER_UP`)."""

GAIN_RECORD = 0x2000
"""Where a ``gain_record`` drive keeps its loop's sample period and filter (U16 sub 1-4: sample,
zero, pole, gain): a manufacturer object, so a stock drive has nothing there."""
_GAIN_SUBS = {"sample": 1, "zero": 2, "pole": 3, "gain": 4}

COUNTS_PER_REV = 4096
"""Encoder increments per head revolution: the factor group's power-on values say so."""


DRIVE_TUNING = MotorParams()
"""A stock drive's loop, as its commissioning tuned it: Appendix B's sample period and filter."""


@dataclass(frozen=True)
class DriveVariant:
    """How a simulated drive differs from the stock one (every field's default is stock)."""

    gain_record: bool = False
    """A manufacturer record :data:`GAIN_RECORD` for the loop's sample and filter, which the
    loop then runs (power-on: :data:`POWER_UP_PARAMS`); the master maps BIRIS_MOTOR_PARAMS onto
    it (the driver's ``gains``)."""
    values: Mapping[tuple[int, int], int] = field(default_factory=dict)
    """Power-on values replacing the dictionary's, by (index, sub-index): other units, say."""
    absent: frozenset[int] = frozenset()
    """Standard objects this drive does not have (e.g. the SI unit objects 0x60A8/0x60A9 of a
    drive built to the older profile)."""
    keeps_homing_attained: bool = False
    """"Homing attained" (statusword bit 12 in homing mode) stays set from a finished homing
    through mode changes and re-enabling, until the next homing starts or the power goes."""
    homing_s: float = 0.0
    """Hardware seconds a homing on the current position takes (0: done at bit 4's edge)."""
    mode_at_cycle: bool = False
    """0x6060 takes effect (and shows in 0x6061) at the drive's next cycle, not at once."""
    tuning: MotorParams = DRIVE_TUNING
    """The loop's sample and filter on a drive without ``gain_record``: its commissioning's,
    which no object exposes (Appendix B's: the drive was tuned for this motor as the HCTL-1000
    was)."""


STOCK = DriveVariant()
"""The stock drive: standard objects only (what :class:`SimulatedDrive` is by default)."""


def build_dictionary(node_id: int, variant: DriveVariant = STOCK) -> od.ObjectDictionary:
    """The simulated drive's object dictionary: standard objects (the CiA 402 set a driver in
    profile position with homing, touch probe and unit objects needs), with a drive's power-up
    values (PDOs invalid, no heartbeat, its own profile, units of encoder increments per second),
    as ``variant`` changes them."""
    new_dictionary: Any = od.ObjectDictionary
    d: od.ObjectDictionary = new_dictionary()
    d.node_id = node_id
    for var in (
        _var("device type", 0x1000, 0, od.UNSIGNED32, 0x0002_0000 | CIA402_PROFILE, "const"),
        _var("error register", 0x1001, 0, od.UNSIGNED8, 0, "ro"),
        _var("producer heartbeat time", 0x1017, 0, od.UNSIGNED16, 0),
        _var("controlword", 0x6040, 0, od.UNSIGNED16, 0),
        _var("statusword", 0x6041, 0, od.UNSIGNED16, 0, "ro"),
        _var("quick stop option code", 0x605A, 0, od.INTEGER16, 5),
        _var("modes of operation", 0x6060, 0, od.INTEGER8, 0),
        _var("modes of operation display", 0x6061, 0, od.INTEGER8, 0, "ro"),
        _var("position demand value", 0x6062, 0, od.INTEGER32, 0, "ro"),
        _var("position actual value", 0x6064, 0, od.INTEGER32, 0, "ro"),
        _var("following error window", 0x6065, 0, od.UNSIGNED32, 1000),
        _var("following error time out", 0x6066, 0, od.UNSIGNED16, 10),
        _var("position window", 0x6067, 0, od.UNSIGNED32, 2),
        _var("position window time", 0x6068, 0, od.UNSIGNED16, 0),
        _var("target position", 0x607A, 0, od.INTEGER32, 0),
        _var("home offset", 0x607C, 0, od.INTEGER32, 0),
        _var("profile velocity", 0x6081, 0, od.UNSIGNED32, 1000),
        _var("profile acceleration", 0x6083, 0, od.UNSIGNED32, 10000),
        _var("profile deceleration", 0x6084, 0, od.UNSIGNED32, 10000),
        _var("quick stop deceleration", 0x6085, 0, od.UNSIGNED32, 100000),
        _var("homing method", 0x6098, 0, od.INTEGER8, 35),
        _var("touch probe function", 0x60B8, 0, od.UNSIGNED16, 0),
        _var("touch probe status", 0x60B9, 0, od.UNSIGNED16, 0, "ro"),
        _var("touch probe 1 positive edge", 0x60BA, 0, od.INTEGER32, 0, "ro"),
        _var("supported drive modes", 0x6502, 0, od.UNSIGNED32, 0x21, "ro"),
        _var("SI unit position", 0x60A8, 0, od.UNSIGNED32, SI_INCREMENT << 16),
        _var("SI unit velocity", 0x60A9, 0, od.UNSIGNED32, SI_INCREMENT << 16 | SI_SECOND << 8),
    ):
        d.add_object(var)
    for array in (
        _ratio("position encoder resolution", 0x608F, (COUNTS_PER_REV, 1), ("increments", "revs")),
        _ratio("gear ratio", 0x6091, (1, 1), ("motor revs", "shaft revs")),
        _ratio("feed constant", 0x6092, (COUNTS_PER_REV, 1), ("feed", "shaft revs")),
        _ratio("velocity encoder factor", 0x6094, (1, 1), ("numerator", "divisor")),
        _ratio("acceleration factor", 0x6097, (1, 1), ("numerator", "divisor")),
    ):
        d.add_object(array)
    consumer = od.ODArray("consumer heartbeat time", 0x1016)
    consumer.add_member(_var("consumer heartbeat entries", 0x1016, 0, od.UNSIGNED8, 1, "ro"))
    consumer.add_member(_var("consumer heartbeat time 1", 0x1016, 1, od.UNSIGNED32, 0))
    d.add_object(consumer)
    rpdo_cob = 0x8000_0000 | (0x200 + node_id)  # invalid until the master maps it
    tpdo_cob = 0x8000_0000 | (0x180 + node_id)
    rx = [("COB-ID", 1, rpdo_cob, "rw"), ("transmission type", 2, 255, "rw")]
    d.add_object(_record("RPDO1 communication", 0x1400, rx))
    d.add_object(_mapping("RPDO1 mapping", 0x1600))
    tx = [
        ("COB-ID", 1, tpdo_cob, "rw"),
        ("transmission type", 2, 255, "rw"),
        ("inhibit time", 3, 0, "rw"),
        ("event timer", 5, 0, "rw"),
    ]
    d.add_object(_record("TPDO1 communication", 0x1800, tx))
    d.add_object(_mapping("TPDO1 mapping", 0x1A00))
    if variant.gain_record:
        filter_values = POWER_UP_PARAMS.to_dict()
        members = [(key, sub, filter_values[key], "rw") for key, sub in _GAIN_SUBS.items()]
        d.add_object(_record("loop gains", GAIN_RECORD, members))
    for index in variant.absent:
        if index in d:
            del d[index]
    for (index, subindex), value in variant.values.items():
        target = d.get_variable(index, subindex)
        if target is None:
            raise ValueError(f"the drive has no object 0x{index:04X}:{subindex:02X} to set")
        target.default = value
    return d


class _Profile:
    """A trapezoid (or triangle) from where the demand is, at whatever speed it has: each
    sample, the speed toward the target is the least of the cruise speed, the speed one
    sample's acceleration adds, and the speed from which the deceleration stops exactly there."""

    def __init__(
        self, pos: float, vel: float, target: int, vmax: float, acc: float, dec: float
    ) -> None:
        self.pos = pos
        self.vel = vel
        self.target = target
        self.vmax = max(vmax, 1e-9)
        self.acc = max(acc, 1e-9)
        self.dec = max(dec, 1e-9)
        self.done = False

    def step(self, dt: float) -> None:
        remaining = self.target - self.pos
        if remaining == 0.0:
            self.vel = 0.0
            self.done = True
            return
        direction = 1.0 if remaining > 0.0 else -1.0
        toward = self.vel * direction
        dist = abs(remaining)
        cap = min(self.vmax, math.sqrt(2.0 * self.dec * dist))
        if toward < 0.0:  # still going the other way: brake first
            speed = min(toward + self.dec * dt, cap)
        else:
            speed = min(toward + self.acc * dt, cap)
        advance = speed * dt
        if advance >= dist:
            self.pos = float(self.target)
            self.vel = 0.0
            self.done = True
            return
        self.pos += direction * advance
        self.vel = direction * speed


class SimulatedDrive:
    """One CiA 402 drive (node ``node_id``) driving ``plant`` on hardware clock ``clock``.

    ``network_or_channel`` is a connected :class:`canopen.Network` (shared by several drives)
    or the name of a python-can ``virtual`` channel, for which the drive makes (and owns) a
    network of its own. ``audit`` is the simulator's shared audit, which gets the violations
    that have a rule there; every violation is in :attr:`violations`. ``variant`` says how the
    drive differs from a stock one (:class:`DriveVariant`; the rig's drives are stock).
    """

    def __init__(
        self,
        network_or_channel: canopen.Network | str,
        node_id: int,
        plant: MotorPlant,
        clock: Callable[[], float],
        audit: Audit | None = None,
        *,
        variant: DriveVariant = STOCK,
        step_real_s: float = STEP_REAL_S,
        name: str = "",
        head_limit: float | None = None,
    ) -> None:
        self.node_id = node_id
        self.variant = variant
        self._head_limit = head_limit
        """Counts from true zero beyond which the head winds its cable: HEAD_BEYOND_LIMIT in
        ``audit`` (the pan's, as on the board: :data:`sim.hctl1000.HEAD_LIMIT_COUNTS`)."""
        self._head_out = False
        self.plant = plant
        self.name = name or f"drive {node_id}"
        self._clock = clock
        self._audit = audit
        self._step_real_s = step_real_s
        self._lock = threading.RLock()
        self._own_audit = Audit(clock)
        self.emcy_sent: list[int] = []
        """EMCY error codes sent, oldest first (backdoor for tests)."""
        if isinstance(network_or_channel, str):
            network = canopen.Network()
            network.NOTIFIER_CYCLE = NOTIFIER_CYCLE_S
            network.NOTIFIER_SHUTDOWN_TIMEOUT = 4 * NOTIFIER_CYCLE_S
            network.connect(interface="virtual", channel=network_or_channel)
            self._own_network = True
        else:
            network = network_or_channel
            self._own_network = False
        self.network = network
        # -- the drive's state (under _lock) --
        self._powered = True
        self._cut = False
        """The CAN cable is pulled (:meth:`disconnect`): nothing heard, nothing sent."""
        self._t = clock()
        self._history: collections.deque[tuple[float, int]] = collections.deque(maxlen=HISTORY)
        """(clock time, position actual) after each sample, for :meth:`position_at`."""
        self._sent_frame: bytes | None = None
        """TPDO1's last frame sent (None: send the next whatever it holds)."""
        self._sent_t: float | None = None
        """When (drive clock) TPDO1 was last sent: the inhibit time and event timer count
        from it."""
        self._tpdo_held = False
        """A change came within the inhibit time: it goes out when that expires."""
        self.tpdo_sent = 0
        """TPDO1 frames sent since power-on (backdoor for tests and benchmarks)."""
        self._batch = False
        self._cw_pending: int | None = None
        self._consumer: tuple[int, float] | None = None
        self._master_seen: float | None = None
        self._master_lost = False
        self.master_heard = threading.Event()
        """Set when the consumer has heard the master's heartbeat (its monitoring starts
        there, CiA 301); cleared when the consumer is set anew (backdoor for tests)."""
        self._rpdo_cob: int | None = None
        self._tpdo_cob: int | None = None
        self._error_register = 0
        self._profile: _Profile | None = None
        self._configured: set[tuple[int, int]] = set()
        """Objects the master has written since power-on (the MOVE_UNCONFIGURED audit)."""
        self._reset_application()
        # -- the node --
        self.od = build_dictionary(node_id, variant)
        self.node = network.create_node(node_id, self.od)
        self._values: dict[tuple[int, int], int] = {}
        self._dynamic_objects = self._dynamic()
        self._tpdo_layout: list[tuple[Callable[[], int], Callable[[int], bytes]]] | None = None
        """TPDO1's mapping as readers and packers (:meth:`_tpdo_frame`); None: build it anew."""
        self._load_defaults(communication_only=False)
        local: Any = self.node  # canopen's callbacks are untyped
        local.add_read_callback(self._on_read)
        local.add_write_callback(self._on_write)
        self._subscribed: list[tuple[int, Callable[[int, bytearray, float], None]]] = []
        self._subscribe(0, self._on_nmt)
        self._boot()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"cia402-{node_id}", daemon=True)
        self._thread.start()

    # -- power-on and NMT resets -------------------------------------------------------------------
    def _load_defaults(self, *, communication_only: bool) -> None:
        """The object dictionary's power-on values: all of them, or only the communication
        profile's (0x1000-0x1FFF), which is what NMT reset communication restores."""
        self._tpdo_layout = None
        for index in self.od:
            if communication_only and not 0x1000 <= index < 0x2000:
                continue
            obj = self.od[index]
            members = [obj] if isinstance(obj, od.ODVariable) else list(obj.values())
            for var in members:
                self._values[(var.index, var.subindex)] = int(var.default or 0)
        if communication_only:
            self._configured = {k for k in self._configured if not 0x1000 <= k[0] < 0x2000}

    def _reset_application(self) -> None:
        """The drive's own state at power-on (and NMT reset node): SWITCH ON DISABLED, no mode,
        no move, no fault, the touch probe off, and the position actual restarting at 0 where
        the head stands (an incremental encoder's count does not survive)."""
        self._state = DriveState.SWITCH_ON_DISABLED
        self._cw = 0
        self._mode = 0
        """The mode the drive runs (and 0x6061 shows)."""
        self._mode_pending: int | None = None
        """0x6060 written, taken at the next cycle (``mode_at_cycle``)."""
        self._homing_until: float | None = None
        """A homing under way ends at this clock time (``homing_s``)."""
        self._offset = -self.plant.encoder_counts
        self._demand = 0.0
        self._profile = None
        self._move_target = 0
        self._ack = False
        self._ack_falling = False
        """Bit 4 has fallen: bit 12 falls at the next cycle (sample), not at once."""
        self._reached = False
        self._window_s = 0.0
        self._following_s = 0.0
        self._following_error = False
        self._homing_attained = False
        self._homing_error = False
        self._x_prev = 0
        self._mc_prev = 0
        self._error_register = 0
        self._tp_function = 0
        self._tp_stored = False
        self._tp_value = 0
        self._configured = set()
        self._history.clear()

    def _reset_communication(self) -> None:
        """NMT reset communication's part (and power-on's): the heartbeat stops, the PDOs and
        the heartbeat consumer are off, the communication objects take their power-on values."""
        self._silence()
        if self._rpdo_cob is not None:
            self._unsubscribe(self._rpdo_cob, self._on_rpdo)
            self._rpdo_cob = None
        self._tpdo_cob = None
        if self._consumer is not None:
            self._unsubscribe(0x700 + self._consumer[0], self._on_master_heartbeat)
        self._consumer = None
        self._master_seen = None
        self._master_lost = False
        self._load_defaults(communication_only=True)
        self._sent_frame = self._sent_t = None
        self._tpdo_held = False

    def _boot(self) -> None:
        """Boot-up message, then pre-operational (heartbeat from 0x1017 when the master sets
        it: 0 at power-on)."""
        self.node.nmt.send_command(0x81)
        self.node.nmt.send_command(0x80)

    def _serve_sdo(self, serving: bool) -> None:
        """Answer SDO requests, or not (no power, no cable): the master then times out."""
        rx = 0x600 + self.node_id
        try:
            if serving:
                self.network.subscribe(rx, self.node.sdo.on_request)
            else:
                self.network.unsubscribe(rx, self.node.sdo.on_request)
        except (KeyError, ValueError):
            pass

    # -- fault panel ------------------------------------------------------------------------------
    def stall(self, stalled: bool = True) -> None:
        """Lock (or free) the shaft: a move then pulls away from it until the following error
        faults the drive."""
        with self._lock:
            self._advance()
            self.plant.stalled = stalled

    def set_plant(self, attribute: str, value: bool) -> None:
        """Set one of the plant's failure flags (``stalled``, ``amplifier_dead``), caught up
        to now first (the fault panel's way in)."""
        with self._lock:
            self._advance()
            setattr(self.plant, attribute, value)

    def lose_power(self) -> None:
        """The drive goes dark: no heartbeat, no answers, no torque (the head coasts)."""
        with self._lock:
            self._advance()
            if not self._powered:
                return
            self._powered = False
            self._profile = None
            self._state = DriveState.NOT_READY_TO_SWITCH_ON
            self._silence()
            if not self._cut:
                self._serve_sdo(False)

    def restore_power(self) -> None:
        """Power comes back (after :meth:`lose_power`): the drive boots as it did at first --
        every object at its power-on value (PDOs off, no heartbeat, its own profile and, with a
        record, its own gains), SWITCH ON DISABLED, the position actual restarting at 0 where
        the head coasted to -- sends its boot-up message and waits in pre-operational for a
        master to set it up again."""
        with self._lock:
            self._advance()  # the coast so far, unpowered
            if self._powered:
                return
            self._powered = True
            self._reset_communication()
            self._load_defaults(communication_only=False)
            self._reset_application()
            if not self._cut:
                self._serve_sdo(True)
                self._boot()

    def disconnect(self) -> None:
        """The drive's CAN cable is pulled: it keeps its power, its state and its loop, but
        hears nothing and sends nothing (no heartbeat, PDO, EMCY or SDO answer). As a heartbeat
        consumer it then misses the master and faults (EMCY 0x8130, which nobody hears)."""
        with self._lock:
            self._advance()
            if self._cut:
                return
            self._cut = True
            self._silence()
            self._unsubscribe_nmt(True)
            if self._powered:
                self._serve_sdo(False)

    def reconnect(self) -> None:
        """The cable is back (after :meth:`disconnect`): the drive hears the bus again and its
        heartbeat producer resumes; whatever happened meanwhile (a fault) is as it left it."""
        with self._lock:
            self._advance()
            if not self._cut:
                return
            self._cut = False
            self._unsubscribe_nmt(False)
            if self._powered:
                self._serve_sdo(True)
                period = self._values[(0x1017, 0)]
                if period and self.node.nmt.state != "INITIALISING":
                    self.node.nmt.start_heartbeat(period)

    def _unsubscribe_nmt(self, cut: bool) -> None:
        """canopen's own NMT slave stops (or starts again) hearing NMT commands."""
        try:
            if cut:
                self.network.unsubscribe(0, self.node.nmt.on_command)
            else:
                self.network.subscribe(0, self.node.nmt.on_command)
        except (KeyError, ValueError):
            pass

    def emcy(self, code: int, fault: bool = True) -> None:
        """Send EMCY ``code``; with ``fault``, the drive faults with it (as a drive whose EMCY
        reports a fault does), else it is only a warning."""
        with self._lock:
            self._advance()
            if fault:
                self._fault(code, "fault panel")
            else:
                self._send_emcy(code)

    def _silence(self) -> None:
        """Stop the heartbeat producer and wait for its thread (canopen only asks it to stop)."""
        nmt: Any = self.node.nmt
        stop_periodic_task(getattr(nmt, "_send_task", None))
        nmt._send_task = None

    # -- backdoor ---------------------------------------------------------------------------------
    def turn_by_hand(self, command: int, seconds: float) -> None:
        """Drive the plant open loop with ``command`` for ``seconds`` of its time, at once: a
        person turning the head while the drive does not hold it (backdoor; refused while the
        drive is enabled, which would fight the hand)."""
        with self._lock:
            self._advance()
            if self._enabled():
                raise RuntimeError("the drive holds the head: disable it first")
            period = self._period()
            for _ in range(max(1, round(seconds / period))):
                self.plant.step(command, period)
            for _ in range(round(0.2 / period)):  # and let go: it coasts to rest
                self.plant.step(0, period)
            if self.plant.index_seen:
                self.plant.clear_index()
                self._touch_probe_edge()
            self._publish()

    @property
    def state(self) -> DriveState:
        with self._lock:
            self._advance()
            return self._state

    @property
    def position_actual(self) -> int:
        with self._lock:
            self._advance()
            return self._actual()

    @property
    def statusword(self) -> int:
        with self._lock:
            self._advance()
            return self._statusword()

    @property
    def mode_display(self) -> int:
        """The mode the drive runs, as 0x6061 shows it (backdoor)."""
        with self._lock:
            self._advance()
            return self._mode

    def position_at(self, t: float) -> int:
        """The position actual as it read at clock time ``t`` (at or before now): what BIRIS,
        tagging an acquisition mid-exposure, reads from the drive, even when it gets round to
        it late (as :meth:`sim.hctl1000.Hctl1000.position_at`). A moment older than the
        history, or than the last homing, gets the oldest reading on the present zero."""
        with self._lock:
            self._advance()
            for when, actual in reversed(self._history):
                if when <= t:
                    return actual
            return self._history[0][1] if self._history else self._actual()

    def pose(self) -> tuple[float, int, float]:
        """(true counts from the index, position actual, velocity in counts/s), read together
        (backdoor: what the optics and the tilt audit see)."""
        with self._lock:
            self._advance()
            plant = self.plant
            return plant.true_azimuth_counts, self._actual(), plant.velocity_counts_per_s

    def value(self, index: int, subindex: int = 0) -> int:
        """What the drive holds in a configuration object (backdoor)."""
        with self._lock:
            return self._values[(index, subindex)]

    def close(self) -> None:
        """Stop the drive's thread, leave the network (disconnecting it if the drive's own)."""
        self._stop.set()
        self._thread.join()
        with self._lock:
            self._silence()
            self._powered = False
        for can_id, callback in self._subscribed:
            try:
                self.network.unsubscribe(can_id, callback)
            except (KeyError, ValueError):
                pass
        try:
            del self.network[self.node_id]
        except KeyError:
            pass
        if self._own_network:
            self.network.disconnect()

    # -- the clock --------------------------------------------------------------------------------
    def _run(self) -> None:
        while not self._stop.wait(self._step_real_s):
            with self._lock:
                self._advance()
                self._watch_master()

    def _gain(self, key: str) -> int:
        """The loop's sample timer or filter value: the record's, or the drive's tuning."""
        if self.variant.gain_record:
            return self._values[(GAIN_RECORD, _GAIN_SUBS[key])] & 0xFF
        value: int = getattr(self.variant.tuning, key)
        return value

    def _period(self) -> float:
        timer = max(SAMPLE_TIMER_MIN, self._gain("sample"))
        return 16.0 * (timer + 1) / F_CLK_HZ

    def _actual(self) -> int:
        return self.plant.encoder_counts + self._offset

    def _advance(self) -> None:
        """Run the samples up to now (under the lock)."""
        now = self._clock()
        period = self._period()
        n = 0
        while self._t + period <= now:
            if self._quiescent():
                skipped = math.floor((now - self._t) / period)
                self._t += skipped * period
                break
            self._sample(period)
            self._t += period
            self._history.append((self._t, self._actual()))
            n += 1
            if n >= MAX_CATCH_UP:
                self._t = now
                break

    def _quiescent(self) -> bool:
        """Nothing observable can change until the master acts: no profile, no loop output,
        a head that friction holds."""
        if self._profile is not None or self._mc_prev != 0 or self._x_prev != 0:
            return False
        if self._ack_falling or self._mode_pending is not None or self._homing_until is not None:
            return False
        if self._tpdo_held or (self._tpdo_live() and self._values[(0x1800, 5)]):
            return False  # a TPDO is due at a later cycle
        if self._enabled() and (round(self._demand) != self._actual() or not self._reached):
            return False
        return self.plant.holds_at_rest(0)

    def _enabled(self) -> bool:
        return self._powered and self._state in (
            DriveState.OPERATION_ENABLED,
            DriveState.QUICK_STOP_ACTIVE,
        )

    def _sample(self, period: float) -> None:
        if self._ack_falling:  # one cycle after bit 4 fell (CiA 402's handshake)
            self._ack = self._ack_falling = False
        if self._mode_pending is not None:  # the mode written since the last cycle
            self._take_mode(self._mode_pending)
        if self._homing_until is not None and self._t + period >= self._homing_until:
            self._finish_homing()
        actual = self._actual()
        if self._enabled():
            profile = self._profile
            if profile is not None:
                profile.step(period)
                self._demand = profile.pos
                if profile.done:
                    self._profile = None
            x = round(self._demand) - actual
            gain, zero, pole = (self._gain(key) for key in ("gain", "zero", "pole"))
            mc = int(gain * 0.25 * (x - zero / 256.0 * self._x_prev) - pole / 256.0 * self._mc_prev)
            mc = max(-128, min(127, mc))
            self._x_prev, self._mc_prev = x, mc
            self._check_following(abs(x), period)
        else:
            mc = 0
            self._x_prev = self._mc_prev = 0
            self._demand = float(actual)
        self.plant.step(mc if self._powered else 0, period)
        if self._head_limit is not None:
            self._check_head()
        if self.plant.index_seen:
            self.plant.clear_index()
            self._touch_probe_edge()
        if self._state is DriveState.OPERATION_ENABLED and self._mode == 1:
            within = abs(self._move_target - self._actual()) <= self._values[(0x6067, 0)]
            if self._profile is None and within:
                self._window_s += period
                self._reached = self._window_s * 1000.0 >= self._values[(0x6068, 0)]
            else:
                self._window_s = 0.0
                self._reached = False
        self._publish()

    def _check_head(self) -> None:
        """HEAD_BEYOND_LIMIT once per excursion of the true head beyond the limit."""
        assert self._head_limit is not None
        theta = self.plant.true_azimuth_counts
        out = abs(theta) > self._head_limit
        if out and not self._head_out and self._audit is not None:
            self._audit.record(
                Rule.HEAD_BEYOND_LIMIT,
                f"CiA 402 node {self.node_id}: the true head is {theta:+.1f} counts from true "
                f"zero, beyond +-{self._head_limit:g}, while the position actual reads "
                f"{self._actual()}: the cable is being wound",
                TRUE_POS=round(theta),
            )
        self._head_out = out

    def _check_following(self, error: int, period: float) -> None:
        if self._state is not DriveState.OPERATION_ENABLED:
            return
        if error > self._values[(0x6065, 0)]:
            self._following_s += period
            if self._following_s * 1000.0 > self._values[(0x6066, 0)]:
                self._following_error = True
                self._fault(EMCY_FOLLOWING_ERROR, f"following error {error} counts")
        else:
            self._following_s = 0.0

    def _watch_master(self) -> None:
        """Heartbeat consumer: a master heard once, then silent too long, faults the drive."""
        consumer, seen = self._consumer, self._master_seen
        if consumer is None or seen is None or self._master_lost or not self._powered:
            return
        if time.monotonic() - seen > consumer[1]:
            self._master_lost = True
            self._fault(EMCY_HEARTBEAT, f"no heartbeat from master node {consumer[0]}")

    # -- the statusword ---------------------------------------------------------------------------
    def _statusword(self) -> int:
        """The statusword now (plain ints: it is built at every cycle, for the TPDO)."""
        word = _BASE[self._state] | (_REMOTE if self._powered else 0)
        if self._state in (DriveState.FAULT, DriveState.FAULT_REACTION_ACTIVE):
            return word | (_FOLLOWING_ERROR if self._following_error else 0)
        if self._state is not DriveState.OPERATION_ENABLED:
            return word
        if self._mode == 1:
            word |= _TARGET_REACHED if self._reached else 0
            word |= _ACKNOWLEDGE if self._ack else 0
            word |= _FOLLOWING_ERROR if self._following_error else 0
        elif self._mode == 6:
            if self._homing_error:  # error, the head standing
                word |= _FOLLOWING_ERROR | _TARGET_REACHED
            elif self._homing_attained:
                word |= _TARGET_REACHED | _ACKNOWLEDGE
            elif self._homing_until is None:  # not started, or interrupted
                word |= _TARGET_REACHED
        return word

    def _tpdo_live(self) -> bool:
        """TPDO1 is valid, event-driven, and the drive OPERATIONAL: it may be sent."""
        return (
            self._tpdo_cob is not None
            and self._powered
            and self.node.nmt.state == "OPERATIONAL"
            and self._values[(0x1800, 2)] >= 254
        )

    def _publish(self) -> None:
        """TPDO1 as an event-driven PDO goes (type 254/255): when any mapped value changed
        since the last one, or its event timer ran out; never within the inhibit time of the
        last one (a change meanwhile is held until it expires: :meth:`_quiescent` keeps the
        cycles running for it)."""
        if not self._tpdo_live():
            self._tpdo_held = False
            return
        frame = self._tpdo_frame()
        last = self._sent_t
        timer_ms = self._values[(0x1800, 5)]
        due = last is not None and timer_ms > 0 and self._t - last >= timer_ms / 1000.0
        if frame == self._sent_frame and not due:
            self._tpdo_held = False
            return
        inhibit_s = self._values[(0x1800, 3)] * 1e-4
        if last is not None and self._t - last < inhibit_s:
            self._tpdo_held = True
            return
        self._tpdo_held = False
        self._sent_frame, self._sent_t = frame, self._t
        if self._cut:
            return
        assert self._tpdo_cob is not None
        try:
            self.network.send_message(self._tpdo_cob, frame)
            self.tpdo_sent += 1
        except Exception as exc:  # the bus is closing: nobody is listening any more
            log.debug("%s: TPDO not sent (%s)", self.name, exc)

    def _tpdo_frame(self) -> bytes:
        """TPDO1's data as mapped now (built every cycle: its layout is kept until the mapping
        changes)."""
        layout = self._tpdo_layout
        if layout is None:
            layout = self._tpdo_layout = self._layout()
        return b"".join(pack(read()) for read, pack in layout)

    def _layout(self) -> list[tuple[Callable[[], int], Callable[[int], bytes]]]:
        """Each mapped object of TPDO1: how to read it, how to pack it."""
        layout: list[tuple[Callable[[], int], Callable[[int], bytes]]] = []
        for sub in range(1, self._values[(0x1A00, 0)] + 1):
            entry = self._values[(0x1A00, sub)]
            index, subindex, nbytes = entry >> 16, (entry >> 8) & 0xFF, (entry & 0xFF) // 8
            var = self.od.get_variable(index, subindex)
            assert var is not None  # checked when mapped
            read = self._dynamic_objects.get(index) or self._stored(index, subindex)
            fmt = _PACK.get(var.data_type) if var.data_type is not None else None
            pack = struct.Struct(fmt).pack if fmt is not None else _encoder(var, nbytes)
            layout.append((read, pack))
        return layout

    def _stored(self, index: int, subindex: int) -> Callable[[], int]:
        """A reader of a stored object's present value."""
        key = (index, subindex)
        return lambda: self._values[key]

    # -- object access ----------------------------------------------------------------------------
    def _dynamic(self) -> dict[int, Callable[[], int]]:
        """The objects whose value is the drive's state, not a stored value."""
        return {
            0x6041: self._statusword,
            0x6061: lambda: self._mode,
            0x6062: lambda: round(self._demand) if self._enabled() else self._actual(),
            0x6064: self._actual,
            0x60B9: self._touch_probe_status,
            0x60BA: lambda: self._tp_value,
            0x1001: lambda: self._error_register,
        }

    def _read_value(self, index: int, subindex: int) -> int:
        read = self._dynamic_objects.get(index)
        if read is not None:
            return read()
        return self._values[(index, subindex)]

    def _on_read(self, index: int, subindex: int, od: Any) -> int | None:
        with self._lock:
            if not self._powered:
                raise SdoAbortedError(0x08000000)
            self._advance()
            if (index, subindex) in self._values:
                return self._read_value(index, subindex)
            return None

    def _on_write(self, index: int, subindex: int, od: Any, data: bytes) -> None:
        var = self.od.get_variable(index, subindex)
        if var is None:
            raise SdoAbortedError(0x06090011)
        value = int(var.decode_raw(data))
        with self._lock:
            if not self._powered:
                raise SdoAbortedError(0x08000000)
            self._advance()
            self._check_write(index, subindex, value)
            old = self._values.get((index, subindex), 0)
            self._values[(index, subindex)] = value
            self._configured.add((index, subindex))
            self._written(index, subindex, value, old)
            self._publish()

    def _check_write(self, index: int, subindex: int, value: int) -> None:
        """Refuse, as a drive would, what it cannot take (an SDO abort)."""
        if index == 0x6060 and value not in _SUPPORTED_MODES:
            raise SdoAbortedError(0x06090030)
        if index == 0x6098 and value not in (35, 37):
            raise SdoAbortedError(0x06090030)
        if index == 0x1800 and subindex == 3 and not self._values[(0x1800, 1)] & 0x8000_0000:
            raise SdoAbortedError(0x08000022)  # the inhibit time changes only while invalid
        if index in (0x1600, 0x1A00):
            comm = 0x1400 if index == 0x1600 else 0x1800
            if not self._values[(comm, 1)] & 0x8000_0000:
                raise SdoAbortedError(0x08000022)  # mapping changed while the PDO is valid
            if subindex == 0:
                self._check_mapping(index, value)
            elif self._values[(index, 0)] != 0:
                raise SdoAbortedError(0x08000022)
            elif value:
                entry = ((value >> 16) & 0xFFFF, (value >> 8) & 0xFF)
                allowed = _MAPPABLE_RX if index == 0x1600 else _MAPPABLE_TX
                var = self.od.get_variable(*entry)
                if entry not in allowed or var is None or len(var) != value & 0xFF:
                    raise SdoAbortedError(0x06040041)

    def _check_mapping(self, index: int, count: int) -> None:
        if count > 8:
            raise SdoAbortedError(0x06090031)
        bits = sum(self._values[(index, sub)] & 0xFF for sub in range(1, count + 1))
        if bits > 64:
            raise SdoAbortedError(0x06040042)
        for sub in range(1, count + 1):
            if not self._values[(index, sub)]:
                raise SdoAbortedError(0x06040043)

    def _written(self, index: int, subindex: int, value: int, old: int) -> None:
        if index == 0x6040:
            if self._batch:
                self._cw_pending = value
            else:
                self._controlword(value)
        elif index == 0x6060:
            if self.variant.mode_at_cycle:
                self._mode_pending = value
            else:
                self._take_mode(value)
        elif index == 0x60B8:
            self._touch_probe_function(value, old)
        elif index == 0x1A00:
            self._tpdo_layout = None
        elif index == 0x1016 and subindex == 1:
            self._set_consumer(value)
        elif index in (0x1400, 0x1800) and subindex == 1:
            self._set_pdo(index, value)

    def _set_pdo(self, comm: int, cob_id: int) -> None:
        valid = not cob_id & 0x8000_0000
        cob = cob_id & 0x7FF
        if comm == 0x1400:
            if self._rpdo_cob is not None:
                self._unsubscribe(self._rpdo_cob, self._on_rpdo)
                self._rpdo_cob = None
            if valid:
                self._rpdo_cob = cob
                self._subscribe(cob, self._on_rpdo)
        else:
            self._tpdo_cob = cob if valid else None

    def _set_consumer(self, value: int) -> None:
        master, ms = (value >> 16) & 0x7F, value & 0xFFFF
        if self._consumer is not None:
            self._unsubscribe(0x700 + self._consumer[0], self._on_master_heartbeat)
        self._consumer = None
        self._master_seen = None
        self._master_lost = False
        self.master_heard.clear()
        if master and ms:
            self._consumer = (master, ms / 1000.0)
            self._subscribe(0x700 + master, self._on_master_heartbeat)

    def _subscribe(self, can_id: int, callback: Callable[[int, bytearray, float], None]) -> None:
        self.network.subscribe(can_id, callback)
        self._subscribed.append((can_id, callback))

    def _unsubscribe(self, can_id: int, callback: Callable[[int, bytearray, float], None]) -> None:
        if (can_id, callback) in self._subscribed:
            self._subscribed.remove((can_id, callback))
            try:
                self.network.unsubscribe(can_id, callback)
            except (KeyError, ValueError):
                pass

    # -- bus events (the network's receive thread) ------------------------------------------------
    def _on_master_heartbeat(self, can_id: int, data: bytearray, timestamp: float) -> None:
        with self._lock:
            if self._cut:
                return
            self._master_seen = time.monotonic()
            self._master_lost = False
        self.master_heard.set()

    def _on_nmt(self, can_id: int, data: bytearray, timestamp: float) -> None:
        """NMT commands for this node, after canopen's own slave has taken the state: entering
        OPERATIONAL sends the event PDO once; reset node (0x81) restarts the application and
        communication as a power-up does, reset communication (0x82) the communication
        objects only (the CiA 402 state, the count and the profile stay); both end with
        the boot-up message and pre-operational, as CiA 301 has it."""
        with self._lock:
            if len(data) < 2 or data[1] not in (0, self.node_id):
                return
            if self._cut or not self._powered:
                return
            command = data[0]
            if command == 0x01:
                self._sent_frame = None  # entering OPERATIONAL: the event PDO goes out once
                self._advance()
                self._publish()
            elif command in (0x81, 0x82):
                self._advance()
                self._reset_communication()
                if command == 0x81:
                    self._load_defaults(communication_only=False)
                    self._reset_application()
                self._boot()

    def _on_rpdo(self, can_id: int, data: bytearray, timestamp: float) -> None:
        with self._lock:
            if not self._powered or self._cut:
                return
            if self.node.nmt.state != "OPERATIONAL":
                self._violation(DriveRule.RPDO_NOT_OPERATIONAL, f"RPDO {bytes(data).hex()}")
                return
            self._advance()
            self._batch = True
            self._cw_pending = None
            try:
                offset = 0
                for sub in range(1, self._values[(0x1600, 0)] + 1):
                    entry = self._values[(0x1600, sub)]
                    index, subindex, size = entry >> 16, (entry >> 8) & 0xFF, (entry & 0xFF) // 8
                    self.node.set_data(index, subindex, bytes(data[offset : offset + size]))
                    offset += size
            except SdoAbortedError as exc:
                log.warning("%s: RPDO refused (%s)", self.name, exc)
            finally:
                self._batch = False
            pending = self._take_pending()
            if pending is not None:
                self._controlword(pending)
            self._publish()

    def _take_pending(self) -> int | None:
        """The controlword an RPDO carried, taken once all of its values are stored."""
        pending, self._cw_pending = self._cw_pending, None
        return pending

    # -- the state machine ------------------------------------------------------------------------
    def _controlword(self, cw: int) -> None:
        prev, self._cw = self._cw, cw
        if not self._powered:
            return
        state = self._state
        if state in (DriveState.FAULT, DriveState.FAULT_REACTION_ACTIVE):
            if cw & Cw.FAULT_RESET and not prev & Cw.FAULT_RESET:
                self._state = DriveState.SWITCH_ON_DISABLED
                self._following_error = False
                self._error_register = 0
                self._send_emcy(0x0000)
            return
        if cw & Cw.FAULT_RESET:
            return
        new = self._transition(state, cw)
        if new is not state:
            self._enter(state, new)
        if self._state is DriveState.OPERATION_ENABLED:
            rising = cw & Cw.NEW_SET_POINT and not prev & Cw.NEW_SET_POINT
            if self._mode == 1:
                if rising and self._ack:
                    # the previous handshake is not over (bit 12 still set): a drive with a
                    # single set-point takes no new one, and the edge is gone when bit 12 falls
                    self._violation(
                        DriveRule.SET_POINT_WHILE_ACKNOWLEDGED,
                        f"set-point to {self._values[(0x607A, 0)]} ignored: bit 12 still "
                        "acknowledges the previous one",
                    )
                elif rising:
                    self._set_point(cw)
                elif not cw & Cw.NEW_SET_POINT and self._ack:
                    self._ack_falling = True  # bit 12 falls at the next cycle
            elif self._mode == 6 and rising:
                self._home()
            elif self._mode == 6 and not cw & Cw.NEW_SET_POINT:
                self._homing_until = None  # bit 4 fell before the end: homing interrupted
        elif cw & Cw.NEW_SET_POINT and not prev & Cw.NEW_SET_POINT and self._mode == 1:
            self._violation(
                DriveRule.SET_POINT_NOT_ENABLED,
                f"set-point to {self._values[(0x607A, 0)]} in {state.value}",
            )

    @staticmethod
    def _transition(state: DriveState, cw: int) -> DriveState:
        s = DriveState
        if not cw & Cw.ENABLE_VOLTAGE:  # disable voltage
            if state in (s.READY_TO_SWITCH_ON, s.SWITCHED_ON, s.OPERATION_ENABLED):
                return s.SWITCH_ON_DISABLED
            if state is s.QUICK_STOP_ACTIVE:
                return s.SWITCH_ON_DISABLED
            return state
        if not cw & Cw.QUICK_STOP:  # quick stop
            if state in (s.READY_TO_SWITCH_ON, s.SWITCHED_ON):
                return s.SWITCH_ON_DISABLED
            if state is s.OPERATION_ENABLED:
                return s.QUICK_STOP_ACTIVE
            return state
        if cw & 0x07 == 0x06:  # shutdown
            if state in (s.SWITCH_ON_DISABLED, s.SWITCHED_ON, s.OPERATION_ENABLED):
                return s.READY_TO_SWITCH_ON
            return state
        if cw & 0x0F == 0x07:  # switch on / disable operation
            if state in (s.READY_TO_SWITCH_ON, s.OPERATION_ENABLED):
                return s.SWITCHED_ON
            return state
        enable = cw & 0x0F == 0x0F  # enable operation (from READY TO SWITCH ON: switch on first)
        if enable and state in (s.READY_TO_SWITCH_ON, s.SWITCHED_ON, s.QUICK_STOP_ACTIVE):
            return s.OPERATION_ENABLED
        return state

    def _enter(self, old: DriveState, new: DriveState) -> None:
        self._state = new
        actual = self._actual()
        if new is DriveState.OPERATION_ENABLED and old is not DriveState.QUICK_STOP_ACTIVE:
            target = self._values[(0x607A, 0)]
            if abs(target - actual) > JUMP_COUNTS:
                self._violation(
                    DriveRule.ENABLE_WITH_JUMP,
                    f"enabled with target {target}, position actual {actual}",
                )
            # a compliant drive holds the head where it stands
            self._demand = float(actual)
            self._move_target = actual
            self._profile = None
            self._x_prev = self._mc_prev = 0
            self._ack = False
            self._ack_falling = False
            self._reached = True
            self._window_s = 0.0
            self._following_s = 0.0
            self._homing_until = None
            if not self.variant.keeps_homing_attained:
                self._homing_attained = self._homing_error = False
        elif new is DriveState.QUICK_STOP_ACTIVE:
            self._ack = False
            self._ack_falling = False
            self._stop_ramp(self._values[(0x6085, 0)])
        elif new is not DriveState.OPERATION_ENABLED:
            self._profile = None
            self._ack = False
            self._ack_falling = False
            self._reached = False
        if new is not DriveState.OPERATION_ENABLED:
            self._homing_until = None  # a homing under way is interrupted

    def _take_mode(self, mode: int) -> None:
        """The drive runs ``mode`` from now (0x6061 shows it): a homing under way is
        interrupted, and "homing attained" goes unless the drive keeps it."""
        self._mode_pending = None
        if mode == self._mode:
            return
        self._mode = mode
        self._ack = False
        self._ack_falling = False
        self._homing_until = None
        if not self.variant.keeps_homing_attained:
            self._homing_attained = self._homing_error = False

    def _stop_ramp(self, decel: int) -> None:
        profile = self._profile
        vel = profile.vel if profile is not None else 0.0
        stop_at = self._demand + math.copysign(vel * vel / (2.0 * max(decel, 1)), vel)
        self._profile = _Profile(self._demand, vel, round(stop_at), abs(vel), decel, decel)

    def _parameters_set(self) -> bool:
        """The master has loaded the profile (and the loop's record, on a drive with one)."""
        needed = [(0x6081, 0), (0x6083, 0), (0x6084, 0)]
        if self.variant.gain_record:
            needed += [(GAIN_RECORD, sub) for sub in _GAIN_SUBS.values()]
        return all(key in self._configured for key in needed)

    def _set_point(self, cw: int) -> None:
        target = self._values[(0x607A, 0)]
        if cw & Cw.RELATIVE:
            target += self._move_target
        if abs(target) > MOTION_LIMIT_COUNTS:
            self._violation(DriveRule.TARGET_BEYOND_LIMIT, f"set-point to {target}")
        if self._profile is not None:
            self._violation(
                DriveRule.SET_POINT_WHILE_MOVING,
                f"set-point to {target} while moving to {self._move_target}",
            )
        if not self._parameters_set():
            self._violation(DriveRule.MOVE_UNCONFIGURED, f"set-point to {target}")
        profile = self._profile
        vel = profile.vel if profile is not None else 0.0
        self._profile = _Profile(
            self._demand,
            vel,
            target,
            self._values[(0x6081, 0)],
            self._values[(0x6083, 0)],
            self._values[(0x6084, 0)],
        )
        self._move_target = target
        self._ack = True
        self._reached = False
        self._window_s = 0.0

    def _home(self) -> None:
        """Methods 35/37 started (bit 4's rising edge): in progress, and done at once or
        ``homing_s`` later (:meth:`_finish_homing`); nothing moves."""
        method = self._values[(0x6098, 0)]
        self._homing_attained = self._homing_error = False
        if method not in (35, 37):
            self._homing_error = True
            return
        if self.variant.homing_s > 0.0:
            self._homing_until = self._t + self.variant.homing_s
        else:
            self._finish_homing()

    def _finish_homing(self) -> None:
        """The present position becomes the home offset 0x607C: homing attained."""
        self._homing_until = None
        actual = self._actual()
        shift = self._values[(0x607C, 0)] - actual
        self._offset += shift
        self._demand += shift
        self._history.clear()  # the readings before were on the old zero
        self._move_target = self._actual()
        self._homing_attained = True

    def _fault(self, code: int, why: str) -> None:
        log.info("%s: fault 0x%04X (%s)", self.name, code, why)
        self._state = DriveState.FAULT
        self._profile = None
        self._ack = False
        self._ack_falling = False
        self._reached = False
        self._x_prev = self._mc_prev = 0
        self._homing_until = None
        self._error_register |= 0x01
        self._send_emcy(code)
        self._publish()

    def _send_emcy(self, code: int) -> None:
        self.emcy_sent.append(code)
        if not self._powered or self._cut:
            return
        try:
            self.node.emcy.send(code, self._error_register)
        except Exception as exc:  # the bus is closing
            log.debug("%s: EMCY not sent (%s)", self.name, exc)

    # -- touch probe ------------------------------------------------------------------------------
    def _touch_probe_function(self, value: int, old: int) -> None:
        self._tp_function = value
        if not value & 0x01:
            self._tp_stored = False
        elif not old & 0x01 or (value & 0x10 and not old & 0x10):
            self._tp_stored = False  # (re-)enabled: armed afresh

    def _touch_probe_status(self) -> int:
        return (self._tp_function & 0x01) | (0x02 if self._tp_stored else 0)

    def _touch_probe_edge(self) -> None:
        function = self._tp_function
        armed = function & 0x01 and function & 0x10 and (function >> 2) & 0x03 == 0x01
        if not armed or (self._tp_stored and not function & 0x02):
            return
        self._tp_stored = True
        self._tp_value = self._actual()

    # -- audit ------------------------------------------------------------------------------------
    @property
    def violations(self) -> list[Violation]:
        """A copy of this drive's broken rules (DriveRule), oldest first."""
        return self._own_audit.violations

    def _violation(self, rule: DriveRule, detail: str) -> None:
        detail = f"node {self.node_id}: {detail}"
        log.warning("%s: %s %s", self.name, rule.value, detail)
        self._own_audit.record(rule, detail)
        shared = _SHARED.get(rule)
        if shared is not None and self._audit is not None:
            self._audit.record(shared, f"CiA 402 {detail}")

"""``SimulatedBiris``: the whole target in one object, wired as on the robot.

It builds the far side of every window and line a driver uses (BIRIS memory through the coupler,
the Model 7600 with two HCTL-1000s and their motors, the Bit 3 coupler, interrupt levels 2 and 3)
and hands the driver's side over as :attr:`hardware`, a :class:`~biris_hw.BirisHardware`. The rig
also exposes what no driver can see: the true head azimuth, the fault panel and the audit.
"""

from __future__ import annotations

import ctypes
import math
import threading
import uuid
from collections.abc import Callable
from types import TracebackType
from typing import TYPE_CHECKING, TypeVar

import numpy as np
from numpy.typing import NDArray

from biris_hw.bus.base import BusWindow, StructView
from biris_hw.bus.memory import MemoryWindow
from biris_hw.devices import LEVEL2_VECTOR
from biris_hw.errors import BusError
from biris_hw.hardware import BirisHardware
from biris_hw.irq.eventfd import EventFdLine
from biris_hw.timebase import ScaledTime, TimeBase, VirtualTime
from regs import biexec
from regs.bit3 import Bit3Reg
from regs.hctl1000 import COUNTS_PER_REV
from regs.layout import BirisMemoryMap
from regs.tech80 import DEFAULT_IRQ_VECTOR, MOTION_WINDOW_SIZE, Axis, BoardReg
from sim.audit import Audit
from sim.bit3 import Bit3Coupler
from sim.clock import SimClock
from sim.faults import FaultPanel
from sim.irqgate import InterruptGate
from sim.motor import MotorPlant
from sim.odometry import DEFAULT_ODOMETRY, Odometry, OdometryParams
from sim.optics import BirisOptics
from sim.scene import Scene
from sim.supervisor import BirisSupervisor
from sim.tech80 import Model7600
from sim.trajectory import Pose, Trajectory

if TYPE_CHECKING:
    import canopen

    from biris_hw.axes.cia402 import Cia402Axes
    from sim.cia402 import SimulatedDrive
    from sim.vmusb import SimulatedVmUsb, VmUsbBackend
    from sim.wiener_crate import SimulatedCrate

__all__ = [
    "AXES",
    "CAN_BUS_OPTIONS",
    "CAN_NODES",
    "CRATE_ID",
    "TRANSPORTS",
    "USB_ROUND_TRIP_S",
    "VME_MAP",
    "VMUSB_SERIAL",
    "SimulatedBiris",
]

AXES = ("hctl1000", "canopen")
"""What drives pan and tilt: the Model 7600's HCTL-1000s, or two CiA 402 drives on a virtual
CAN bus (``axes="canopen"``)."""

CAN_NODES = {Axis.AZIMUTH: 2, Axis.ELEVATION: 3}
CRATE_ID = 1
"""The simulated crate's CAN id (``crate=True``)."""
"""The simulated drives' CANopen node ids."""

CAN_BUS_OPTIONS: dict[str, float] = {
    "heartbeat_period_s": 0.05,
    "heartbeat_timeout_s": 1.0,
    "sdo_timeout_s": 1.0,
    "state_timeout_s": 2.0,
}
"""The driver's CAN timing on the simulated bus (real seconds): looser than a robot's defaults,
because a test host shared with other test runs can stall a thread for a few hundred ms, and a
heartbeat or SDO answer that late is not a lost drive."""

TRANSPORTS = ("memory", "vmusb")

RUNAWAY_HW_S = 600.0
"""Hardware seconds a virtual rig lets pass while its driver waits with no deadline before it
calls the wait a deadlock: the video fields are always due, so "nothing is due" never comes,
and a test waiting for what will never happen would otherwise run the sensor's clock on for
ever (ten hardware minutes take a few seconds of CPU)."""

CLOCKS = ("scaled", "virtual")
"""``SimulatedBiris(clock=...)``: scaled real time (the default: a person watches) or virtual
time (hardware time moves only when nothing can run: tests)."""
"""How ``rig.hardware`` reaches the simulated target: in-process windows and eventfd lines, or
pyusb through a simulated Wiener VM-USB (``transport="vmusb"``)."""

USB_ROUND_TRIP_S = 250e-6
"""Default modelled cost of one USB transfer pair (OUT, then IN), hardware seconds: two
high-speed microframes (125 us each)."""

VMUSB_SERIAL = "VM0412"
"""The simulated VM-USB's serial number string."""

VME_MAP = {
    "biris": (0x0800_0000, 0x09, 32),
    "motion": (0x0000_7600, 0x29, 16),
    "coupler": (0x0000_C000, 0x29, 16),
}
"""Where the crate behind the simulated VM-USB puts each window: (VME base, address modifier,
address bits). BIRIS memory through the coupler's A32 window (user data; BLT for frames), the
Model 7600 and the coupler's node registers in A16 short I/O space."""

_TWO_PI_PER_COUNT = 2.0 * math.pi / COUNTS_PER_REV

_S = TypeVar("_S", bound=ctypes.Structure)


class _DriverMemoryWindow(MemoryWindow):
    """The driver's view of BIRIS memory: the same bytes as the supervisor's, plus a tap on
    COMMAND writes, so the audit sees every write (field-rate polling alone would miss a
    rewrite of the same code) and an idle supervisor wakes for it, and a catch-up before every
    read and before a write to COMMAND, so that a starved (or idle, sleeping) supervisor thread
    never shows the driver a BIRIS that lags behind the video fields.

    Every access crosses the Bit 3 coupler first (``remote``, :meth:`sim.bit3.Bit3Coupler.
    remote_access`): with the BIRIS crate powered off it times out and nothing is read or
    written."""

    def __init__(
        self,
        size: int,
        buffer: bytearray | memoryview,
        command_offset: int,
        on_command: _CommandTap,
        remote: Callable[[str, int, int], None],
    ) -> None:
        super().__init__(size, buffer=buffer)
        self._command_offset = command_offset
        self._on_command = on_command
        self._remote = remote

    def read(self, offset: int, n: int) -> bytes:
        self._remote("read", offset, n)
        self._on_command.catch_up()
        return super().read(offset, n)

    def read8(self, offset: int) -> int:
        self._remote("read", offset, 1)
        self._on_command.catch_up()
        return super().read8(offset)

    def read16(self, offset: int) -> int:
        self._remote("read", offset, 2)
        self._on_command.catch_up()
        return super().read16(offset)

    def read32(self, offset: int) -> int:
        self._remote("read", offset, 4)
        self._on_command.catch_up()
        return super().read32(offset)

    def _before_write(self, offset: int, n: int) -> bool:
        """Cross the coupler; for a write that touches COMMAND, run the fields due before it
        lands (an idle supervisor thread sleeps several fields: they must find COMMAND as it
        was). True if it touches COMMAND."""
        self._remote("write", offset, n)
        touches = offset < self._command_offset + 2 and self._command_offset < offset + n
        if touches:
            self._on_command.catch_up()
        return touches

    def write8(self, offset: int, value: int) -> None:
        touches = self._before_write(offset, 1)
        super().write8(offset, value)
        if touches:
            self._on_command.wake()

    def write16(self, offset: int, value: int) -> None:
        touches = self._before_write(offset, 2)
        super().write16(offset, value)
        if offset == self._command_offset:
            self._on_command(value)
        elif touches:
            self._on_command.wake()

    def write32(self, offset: int, value: int) -> None:
        touches = self._before_write(offset, 4)
        super().write32(offset, value)
        if touches:
            self._on_command.wake()

    def write(self, offset: int, data: bytes | bytearray | memoryview) -> None:
        raw = bytes(data)
        touches = self._before_write(offset, len(raw))
        super().write(offset, raw)
        if offset <= self._command_offset < offset + len(raw) - 1:
            at = self._command_offset - offset
            self._on_command(int.from_bytes(raw[at : at + 2], "big"))
        elif touches:
            self._on_command.wake()

    def view(self, struct_type: type[_S], offset: int = 0) -> StructView[_S]:
        """Not offered: a ctypes view would reach the memory without crossing the coupler."""
        raise BusError("BIRIS memory through the simulated coupler has no ctypes views")


class _CommandTap:
    def __init__(self) -> None:
        self.target: BirisSupervisor | None = None

    def __call__(self, value: int) -> None:
        if self.target is not None:
            self.target.note_command_write(value)

    def catch_up(self) -> None:
        if self.target is not None:
            self.target.catch_up()

    def wake(self) -> None:
        if self.target is not None:
            self.target.wake_idle()


class SimulatedBiris:
    """The simulated BIRIS target: ``with SimulatedBiris(scene=..., time_scale=20) as rig``.

    ``samples`` is 64 (2 fields per acquisition) or 128 (3 fields). Runs are reproducible from
    ``seed`` (thread scheduling aside). On exit every thread is joined and every descriptor closed.
    ``biris_buffer`` puts BIRIS memory in the caller's buffer (a shared-memory segment, so a
    driver in another process can reach it); by default it is private to the rig.
    ``initial_elevation_counts`` is where the tilt axis wakes (0, level, by default): the tilt's
    zero index is at level, so a driver that homes it must find it from there.
    ``initial_azimuth_counts`` (true counts from the zero index; seeded within half a revolution
    by default) must lie within the pan head's stops, +-(4096 + 256): start it near +-4096 to
    play a head left wound round by a previous driver.

    ``axes="canopen"`` replaces the Model 7600 by two CiA 402 drives (:data:`CAN_NODES`,
    :class:`sim.cia402.SimulatedDrive`) on a python-can ``virtual`` channel of the rig's own
    (:attr:`can_channel`), closing their loops around the same motor plants; the rest of the
    rig is unchanged. :attr:`hardware` then has no ``motion`` window: its ``axes`` are the
    driver's :class:`~biris_hw.axes.cia402.Cia402Axes` and ``level3`` their end-of-motion
    line. :attr:`drives` are the drives (their audits, ``emcy()``, ``lose_power()``); the
    fault panel's motor faults act on the pan drive's plant.

    ``transport="vmusb"`` puts the boards in a VME crate behind a simulated Wiener VM-USB
    (:data:`VME_MAP`): :attr:`hardware` is then made of the driver's ``vmusb`` windows and
    lines, found through pyusb and :attr:`usb_backend`, so every register access is a USB
    transfer and every interrupt an IRQ-stack buffer; :attr:`usb_device` is the device (its
    counters, its audit of protocol misuse, ``unplug()``). ``usb_round_trip_s`` sets the
    modelled cost of an OUT and IN pair in hardware seconds (default: the device's, two
    high-speed microframes).

    ``trajectory=`` (a :class:`~sim.trajectory.Trajectory`) drives the vehicle through the
    scene: the optics see from the head's true place at each exposure, :meth:`true_pose` is the
    truth and :attr:`odometry` what the base reports, with the drift and noise of ``odometry=``
    (an :class:`~sim.odometry.OdometryParams`). Without one the vehicle stands at the origin.

    ``crate=True`` adds the VME crate's own monitor: a simulated Wiener crate on a python-can
    ``virtual`` channel of the rig's own (:attr:`crate`, its fault panel; crate id
    :data:`CRATE_ID`), and the driver's :class:`~biris_hw.crate.CrateMonitor` as
    ``hardware.crate``, which a server polls every ``crate_poll_s`` real seconds into
    ``status().crate``.
    """

    def __init__(
        self,
        scene: Scene | None = None,
        samples: int = 64,
        time_scale: float = 1.0,
        seed: int = 0,
        *,
        noise: bool = True,
        initial_azimuth_counts: float | None = None,
        memory_map: BirisMemoryMap | None = None,
        biris_buffer: bytearray | memoryview | None = None,
        initial_elevation_counts: float = 0.0,
        transport: str = "memory",
        usb_round_trip_s: float | None = None,
        axes: str = "hctl1000",
        crate: bool = False,
        crate_poll_s: float = 0.05,
        clock: str = "scaled",
        stall_timeout: float | None = 60.0,
        trajectory: Trajectory | None = None,
        odometry: OdometryParams = DEFAULT_ODOMETRY,
    ) -> None:
        if clock not in CLOCKS:
            raise ValueError(f"clock must be one of {', '.join(CLOCKS)}, not {clock!r}")
        if clock == "virtual" and (transport != "memory" or axes != "hctl1000" or crate):
            raise ValueError(
                'clock="virtual" goes with the memory transport and the Model 7600 only: the '
                "VM-USB's pyusb reader and python-can's and canopen's threads wait outside the "
                "time base (docs/simulator.md), so those rigs run on scaled time"
            )
        if transport not in TRANSPORTS:
            raise ValueError(f"transport must be one of {', '.join(TRANSPORTS)}, not {transport!r}")
        if axes not in AXES:
            raise ValueError(f"axes must be one of {', '.join(AXES)}, not {axes!r}")
        if axes == "canopen" and transport != "memory":
            raise ValueError('axes="canopen" goes with the memory transport only')
        self.transport = transport
        self.axes = axes
        self.drives: dict[Axis, SimulatedDrive] = {}
        """The CiA 402 drives by axis (``axes="canopen"``): their audits, fault panels
        (``emcy``, ``lose_power``, ``stall``) and backdoors."""
        self.can_axes: Cia402Axes | None = None
        """The driver's side of the CAN bus (``axes="canopen"``): ``rig.hardware.axes``."""
        self.can_channel: str | None = None
        """The python-can ``virtual`` channel the drives are on: unique per rig, so that
        rigs in one process never hear each other (``axes="canopen"``)."""
        self._can_network: canopen.Network | None = None
        self._usb_round_trip_s = usb_round_trip_s
        self.usb_device: SimulatedVmUsb | None = None
        """The simulated VM-USB (``transport="vmusb"``): its counters and audit of the USB side."""
        self.usb_backend: VmUsbBackend | None = None
        """The pyusb backend the driver finds the VM-USB through (``transport="vmusb"``)."""
        self.unplugged_usb_devices: list[SimulatedVmUsb] = []
        """VM-USBs that :meth:`replug_usb` replaced (unplugged, kept for their counters and
        audits; closed with the rig)."""
        self.crate: SimulatedCrate | None = None
        """The VME crate's simulated Wiener monitor on CAN (``crate=True``): its state and
        fault panel (``fail_fan``, ``overheat``, ``power_off``, ``go_silent``)."""
        self.crate_channel: str | None = None
        """The python-can ``virtual`` channel the crate answers on (``crate=True``)."""
        self.scene = scene if scene is not None else Scene.room()
        self.trajectory = trajectory
        """The vehicle's path through the scene (docs/simulator.md, "A moving vehicle"); None:
        it stands at the origin facing +x."""
        self._exposure_t = 0.0
        self._initial_elevation = float(initial_elevation_counts)
        self.samples = samples
        self.seed = seed
        self.memory_map = memory_map if memory_map is not None else BirisMemoryMap(samples=samples)
        if self.memory_map.samples != samples:
            raise ValueError("memory_map.samples differs from samples")
        if biris_buffer is not None and len(biris_buffer) < self.memory_map.size:
            raise ValueError("biris_buffer is smaller than the BIRIS memory map")
        self.timebase: TimeBase = (
            VirtualTime(nominal_scale=time_scale, stall_timeout=stall_timeout, runaway=RUNAWAY_HW_S)
            if clock == "virtual"
            else ScaledTime(time_scale)
        )
        """What every thread of the rig, and of a server on :attr:`hardware`, waits through:
        scaled real time, or virtual time (``clock="virtual"``: hardware time moves only when
        every one of them waits, docs/simulator.md). The thread that makes a virtual rig
        drives it (:class:`~biris_hw.timebase.VirtualTime`, rule 4)."""
        self.clock = SimClock(time_scale, timebase=self.timebase)
        self.audit = Audit(self.clock.now)
        self.odometry = Odometry(
            trajectory if trajectory is not None else Trajectory.standing(),
            odometry,
            seed=seed,
            clock=self.clock.now,
            timebase=self.timebase,
        )
        """The vehicle's odometry as its base publishes it (50 Hz, hardware-clock stamps, the
        drift and noise of ``odometry``): ``rig.odometry.since(t)``, ``.wait(t)``, ``.latest()``."""
        self._seeds = np.random.SeedSequence(seed)
        """Spawns the generators: five for the rig, then one for each BIRIS that powers up again
        (:meth:`_remote_power`), so a run with power cycles is reproducible too."""
        rngs = [np.random.default_rng(s) for s in self._seeds.spawn(5)]
        self._closed = False
        self._started = False

        self._level2 = EventFdLine(timebase=self.timebase)
        self._level3 = EventFdLine(timebase=self.timebase)
        try:
            self._build(time_scale, samples, noise, initial_azimuth_counts, biris_buffer, rngs)
        except BaseException:
            self._level2.close()
            self._level3.close()
            raise
        if crate:
            try:
                self._add_crate(crate_poll_s)
            except BaseException:
                self.close()
                raise

    def _build(
        self,
        time_scale: float,
        samples: int,
        noise: bool,
        initial_azimuth_counts: float | None,
        biris_buffer: bytearray | memoryview | None,
        rngs: list[np.random.Generator],
    ) -> None:
        if self.transport == "vmusb":
            # VME interrupts go to the bridge, which runs the driver's IRQ stacks
            self.level2_gate = InterruptGate(lambda n: self._vme_irq(2, n), self.clock)
            self.level3_gate = InterruptGate(lambda n: self._vme_irq(3, n), self.clock)
        else:
            self.level2_gate = InterruptGate(self._level2.trigger, self.clock)
            self.level3_gate = InterruptGate(self._level3.trigger, self.clock)

        az_plant = MotorPlant(rngs[0], initial_azimuth_counts=initial_azimuth_counts)
        # the tilt wakes where it was left (level by default): a tilt head rests on its stops
        el_plant = MotorPlant(rngs[1], initial_azimuth_counts=self._initial_elevation)
        if self.axes == "canopen":
            self._make_drives(az_plant, el_plant)
            # the Model 7600 is not in this rig: the board object stays, idle, on plants of
            # its own, for what refers to it (the fault panel's coupler side, rig.board)
            az_plant = MotorPlant(np.random.default_rng(0), initial_azimuth_counts=0.0)
            el_plant = MotorPlant(np.random.default_rng(0), initial_azimuth_counts=0.0)
        self.board = Model7600(
            self.clock,
            rngs[2],
            raise_irq=lambda: self.level3_gate.raise_irq("motor"),
            audit=self.audit,
            azimuth_plant=az_plant,
            elevation_plant=el_plant,
        )
        self.coupler = Bit3Coupler(self.level2_gate, audit=self.audit)
        self.optics = BirisOptics(samples, rngs[3], noise=noise)

        self._memory = biris_buffer if biris_buffer is not None else bytearray(self.memory_map.size)
        self._memory_shared = biris_buffer is not None
        self._supervisor_window = MemoryWindow(self.memory_map.size, buffer=self._memory)
        self._tap = tap = _CommandTap()
        self._driver_window = _DriverMemoryWindow(
            self.memory_map.size,
            self._memory,
            self.memory_map.biexec_offset + biexec.OFF_COMMAND,
            tap,
            self.coupler.remote_access,
        )
        self.supervisor = self._make_supervisor(rngs[4])
        self.faults = FaultPanel(
            self.supervisor,
            self.board,
            self.coupler,
            self.level2_gate,
            self.level3_gate,
            pan_drive=self.drives.get(Axis.AZIMUTH),
            seed=self.seed,
            driver_windows=self._driver_windows,
            remote_power=self._remote_power,
        )
        self._motion_window: BusWindow = self.board.window()
        self._coupler_window: BusWindow = self.coupler.window()
        assert self._motion_window.size == MOTION_WINDOW_SIZE
        if self.transport == "vmusb":
            self.hardware = self._vmusb_hardware(time_scale)
            return
        if self.axes == "canopen":
            self.hardware = self._can_hardware(time_scale)
            return
        self.hardware = BirisHardware(
            biris=self._driver_window,
            motion=self._motion_window,
            coupler=self._coupler_window,
            level2=self._level2,
            level3=self._level3,
            biexec_offset=self.memory_map.biexec_offset,
            biris_base=self.memory_map.biris_base,
            clock=self.timebase,
            time_scale=time_scale,
            lag=self.lag_s,
        )

    def _make_supervisor(self, rng: np.random.Generator) -> BirisSupervisor:
        """BIRIS as it powers up (BIEXEC_COM clear, not booted), on the rig's memory and gate;
        the driver's COMMAND tap reports to it."""
        supervisor = BirisSupervisor(
            self._supervisor_window,
            self.memory_map,
            self.clock,
            self.level2_gate,
            self._acquire,
            self._exposure_azimuth,
            audit=self.audit,
            rng=rng,
            tilting=self._tilting,
            elevation_counts=self._encoder_elevation,
            true_elevation_counts=self._true_elevation,
            # a driver in another process writes COMMAND into the shared buffer itself, past
            # the tap that wakes an idle supervisor: BIRIS then looks at every field
            sleep_when_idle=not self._memory_shared,
        )
        self._tap.target = supervisor
        return supervisor

    # -- the BIRIS crate's power (the fault panel's remote_power_off/on) ----------------------
    def _remote_power(self, on: bool) -> BirisSupervisor | None:
        """Power the BIRIS crate off or on again; returns the BIRIS that powered up, if any.

        Off: the coupler reports NO_CONNECT and every driver access to BIRIS memory times out
        (:meth:`~sim.bit3.Bit3Coupler.remote_access`); BIRIS stops where it is (no command
        completes, nothing is acquired or raised). On: the coupler connects again and BIRIS
        powers up afresh -- a new :attr:`supervisor` (BIEXEC_COM clear, not booted, its RAM
        disk as at power-up), the old one stopped. Either does nothing if already so.

        The Model 7600 and the coupler's own node are in the host's crate and keep running;
        with ``transport="vmusb"`` so is the VM-USB, which answers an access across the
        powered-off coupler with a VME bus error. Other transports: see docs/faults.md.
        """
        if self._closed:
            raise RuntimeError("the simulator has been shut down")
        if not on:
            if self.coupler.remote_powered:
                self.coupler.remote_power_off()
                self.supervisor.hang()
            return None
        if self.coupler.remote_powered:
            return None
        old = self.supervisor
        old.stop()  # a participant may join it (a wait in the time base)
        self.supervisor = self._make_supervisor(np.random.default_rng(self._seeds.spawn(1)[0]))
        if self._started:
            self.supervisor.start()
        self.coupler.remote_power_on()
        return self.supervisor

    # -- the crate's monitor on CAN ------------------------------------------------------------
    def _add_crate(self, poll_s: float) -> None:
        """A Wiener crate monitor on a virtual channel of this rig's own, and the driver's
        :class:`~biris_hw.crate.CrateMonitor` on it in :attr:`hardware` (polled every
        ``poll_s`` real seconds by a server)."""
        from biris_hw.crate import CrateMonitor
        from sim.wiener_crate import SimulatedCrate

        self.crate_channel = f"biris-crate-{uuid.uuid4().hex}"
        self.crate = SimulatedCrate(self.crate_channel, CRATE_ID)
        self.hardware.crate = CrateMonitor.open(  # answers take about 1 ms on a virtual bus
            interface="virtual", channel=self.crate_channel, crate_id=CRATE_ID, timeout_s=0.05
        )
        self.hardware.crate_poll_s = poll_s

    # -- CiA 402 axes on a virtual CAN bus -------------------------------------------------------
    def _make_drives(self, az_plant: MotorPlant, el_plant: MotorPlant) -> None:
        """Pan and tilt as CiA 402 drives (canopen LocalNodes) on a virtual channel of this
        rig's own, both on one canopen network (the simulator's side of the bus)."""
        import canopen

        from biris_hw.axes.cia402 import NOTIFIER_CYCLE_S
        from sim.cia402 import SimulatedDrive
        from sim.hctl1000 import HEAD_LIMIT_COUNTS

        self.can_channel = f"biris-sim-{uuid.uuid4().hex}"
        network = canopen.Network()
        network.NOTIFIER_CYCLE = NOTIFIER_CYCLE_S
        network.NOTIFIER_SHUTDOWN_TIMEOUT = 4 * NOTIFIER_CYCLE_S
        network.connect(interface="virtual", channel=self.can_channel)
        self._can_network = network
        try:
            for axis, plant, name in (
                (Axis.AZIMUTH, az_plant, "pan drive"),
                (Axis.ELEVATION, el_plant, "tilt drive"),
            ):
                self.drives[axis] = SimulatedDrive(
                    network,
                    CAN_NODES[axis],
                    plant,
                    self.clock.now,
                    self.audit,
                    name=name,
                    head_limit=HEAD_LIMIT_COUNTS if axis is Axis.AZIMUTH else None,
                )
        except BaseException:
            self._close_drives()
            raise

    def _can_hardware(self, time_scale: float) -> BirisHardware:
        """BIRIS and the coupler in memory as usual; the axes are the driver's
        :class:`~biris_hw.axes.cia402.Cia402Axes` on the rig's channel, and level 3 is their
        end-of-motion line."""
        from biris_hw.axes.cia402 import Cia402Axes

        axes = Cia402Axes(
            pan_node=CAN_NODES[Axis.AZIMUTH],
            tilt_node=CAN_NODES[Axis.ELEVATION],
            clock=self.clock.now,
            time_scale=time_scale,
            heartbeat_period_s=CAN_BUS_OPTIONS["heartbeat_period_s"],
            heartbeat_timeout_s=CAN_BUS_OPTIONS["heartbeat_timeout_s"],
            sdo_timeout_s=CAN_BUS_OPTIONS["sdo_timeout_s"],
            state_timeout_s=CAN_BUS_OPTIONS["state_timeout_s"],
            interface="virtual",
            channel=self.can_channel,
        )
        self.can_axes = axes
        self._level3.close()  # the board's line: no board here
        return BirisHardware(
            biris=self._driver_window,
            motion=None,
            coupler=self._coupler_window,
            level2=self._level2,
            level3=axes.end_of_motion,
            biexec_offset=self.memory_map.biexec_offset,
            biris_base=self.memory_map.biris_base,
            clock=self.clock.now,
            time_scale=time_scale,
            lag=self.lag_s,
            axes=axes,
        )

    def _close_drives(self) -> None:
        for drive in self.drives.values():
            drive.close()
        if self._can_network is not None:
            self._can_network.disconnect()
            self._can_network = None

    @property
    def drive_violations(self) -> list[str]:
        """Every CiA 402 drive's own audit, as text (empty without drives, or when clean)."""
        return [str(v) for drive in self.drives.values() for v in drive.violations]

    # -- the VM-USB transport ----------------------------------------------------------------------
    def _vmusb_hardware(self, time_scale: float) -> BirisHardware:
        """The crate behind a simulated VM-USB: BIRIS memory (through the coupler), the Model
        7600 and the coupler's registers at :data:`VME_MAP`; the driver's windows and lines
        are the ``vmusb`` kinds, found through pyusb and :attr:`usb_backend`."""
        from biris_hw.bus.vmusb import VmUsbWindow
        from biris_hw.devices import prefetch_reads
        from biris_hw.irq.vmusb import VmUsbLine
        from sim.vmusb import SimulatedVmUsb, VmUsbBackend

        round_trip = self._usb_round_trip_s
        device = SimulatedVmUsb(
            serial=VMUSB_SERIAL,
            clock=self.clock.now,
            time_scale=time_scale,
            transfer_latency_s=USB_ROUND_TRIP_S / 2.0 if round_trip is None else round_trip / 2.0,
        )
        self.usb_device = device
        self.usb_backend = VmUsbBackend(device)
        far = {
            "biris": self._driver_window,
            "motion": self._motion_window,
            "coupler": self._coupler_window,
        }
        near: dict[str, BusWindow] = {}
        lines: list[VmUsbLine] = []
        try:
            for name, (base, am, bits) in VME_MAP.items():
                device.map(name, far[name], base, bits)
                near[name] = VmUsbWindow(
                    far[name].size, base=base, am=am, serial=VMUSB_SERIAL, backend=self.usb_backend
                )
            for level, vector in ((2, LEVEL2_VECTOR), (3, DEFAULT_IRQ_VECTOR)):
                reads = prefetch_reads(
                    level,
                    biris=near["biris"],
                    motion=near["motion"],
                    coupler=near["coupler"],
                    biexec_offset=self.memory_map.biexec_offset,
                )
                lines.append(
                    VmUsbLine(
                        level=level,
                        vector=vector,
                        reads=reads,
                        serial=VMUSB_SERIAL,
                        backend=self.usb_backend,
                    )
                )
        except BaseException:
            for line in lines:
                line.close()
            for window in near.values():
                window.close()
            device.close()
            raise
        # the eventfd lines of the memory transport are not used
        self._level2.close()
        self._level3.close()
        return BirisHardware(
            biris=near["biris"],
            motion=near["motion"],
            coupler=near["coupler"],
            level2=lines[0],
            level3=lines[1],
            biexec_offset=self.memory_map.biexec_offset,
            biris_base=self.memory_map.biris_base,
            clock=self.clock.now,
            time_scale=time_scale,
            lag=self.lag_s,
        )

    def unplug_usb(self) -> None:
        """The VM-USB's USB cable is pulled (``transport="vmusb"``): the device vanishes, every
        transfer fails, the driver's bridge is lost. The crate behind it keeps running."""
        self._usb_device().unplug()

    def replug_usb(self) -> SimulatedVmUsb:
        """The cable is plugged back in (after :meth:`unplug_usb`): the VM-USB enumerates anew
        on the same backend, with the same serial number, in power-on state (no stack, no ISV
        entry, data taking off), before the same crate, whose boards kept their state.
        :attr:`usb_device` becomes the new device (returned); the old one goes to
        :attr:`unplugged_usb_devices`. A VME interrupt the crate raises before the driver has
        armed the new device is dropped and audited there (``VMUSB_IRQ_UNSERVICED``), as any
        unarmed interrupt is."""
        from sim.vmusb import SimulatedVmUsb

        old = self._usb_device()
        if old.present:
            raise RuntimeError("the VM-USB is plugged in: unplug_usb() first")
        assert self.usb_backend is not None
        new = SimulatedVmUsb(
            serial=old.serial,
            clock=self.clock.now,
            time_scale=self.clock.time_scale,
            transfer_latency_s=old.transfer_latency_s,
        )
        far = {
            "biris": self._driver_window,
            "motion": self._motion_window,
            "coupler": self._coupler_window,
        }
        for name, (base, _, bits) in VME_MAP.items():
            new.map(name, far[name], base, bits)
        self.unplugged_usb_devices.append(old)
        self.usb_device = new
        self.usb_backend.add(new)
        return new

    def _usb_device(self) -> SimulatedVmUsb:
        if self.usb_device is None:
            raise RuntimeError('no VM-USB: the rig was made without transport="vmusb"')
        return self.usb_device

    def _driver_windows(self) -> list[BusWindow]:
        """The windows only the driver reads through (those of :attr:`hardware`; the VM-USB's
        when the transport is ``vmusb``): what the fault panel's slow reads slow. The
        simulator's own accesses use other objects (the supervisor's window, the device
        models, the far side of the bridge)."""
        hw = self.hardware
        return [w for w in (hw.biris, hw.motion, hw.coupler) if w is not None]

    def _vme_irq(self, level: int, count: int) -> None:
        """A VME interrupt of ``level``: the bridge answers its IACK with the vector the
        interrupter presents (the coupler's LEVEL2_VECTOR, the board's IRQ_VECTOR)."""
        device = self.usb_device
        if device is None:
            return
        if level == 2:
            vector = self._coupler_window.read8(Bit3Reg.LEVEL2_VECTOR)
        else:
            vector = self._motion_window.read8(BoardReg.IRQ_VECTOR)
        device.irq(level, vector, count)

    # -- what BIRIS sees -----------------------------------------------------------------------
    def _encoder_azimuth(self, t: float) -> float:
        """What BIRIS read from the motor controller at clock time ``t`` to tag an acquisition
        (its supervisor may get round to it late: the reading is the one of that moment). On
        CAN the drive's position actual at that moment."""
        if self.drives:
            return float(self.drives[Axis.AZIMUTH].position_at(t))
        return float(self.board.position_at(0, t))

    def _encoder_elevation(self, t: float) -> float:
        if self.drives:
            return float(self.drives[Axis.ELEVATION].position_at(t))
        return float(self.board.position_at(1, t))

    def _true_elevation(self, t: float) -> float:
        """The tilt the optics see at clock time ``t`` (counts from level): the encoder's
        reading then, moved by the encoder's offset from the truth (constant while it moves)."""
        if self.drives:
            drive = self.drives[Axis.ELEVATION]
            true, actual, _ = drive.pose()
            return float(drive.position_at(t)) + true - actual
        with self.board.lock:
            self.board.catch_up()
            plant, chip = self.board.plants[1], self.board.elevation
            offset = plant.true_azimuth_counts - chip.actual_position
            return float(self.board.position_at(1, t)) + offset

    def _tilting(self) -> bool:
        if self.drives:
            return abs(self.drives[Axis.ELEVATION].pose()[2]) > 1.0
        with self.board.lock:
            self.board.catch_up()
            return abs(self.board.plants[1].velocity_counts_per_s) > 1.0

    def _acquire(
        self, azimuth_rad: float, tilt_rad: float, lut_tilt_rad: float | None
    ) -> tuple[NDArray[np.int16], NDArray[np.int16]]:
        """The optics see the head where it truly is, whatever the encoder says.

        The supervisor reads the encoders first and calls this a moment later; on a scaled clock
        that moment is several counts of pan at full speed, so the pose is not re-read here.
        Instead the encoder readings are turned into the true pose they stood for, by the
        encoder's offset from the truth (its zero, and the fraction of a count), which does not
        change while the head moves.
        """
        if self.drives:
            az_true, az_actual, _ = self.drives[Axis.AZIMUTH].pose()
            el_true, el_actual, _ = self.drives[Axis.ELEVATION].pose()
            az_off, el_off = az_true - az_actual, el_true - el_actual
        else:
            with self.board.lock:
                self.board.catch_up()
                az_plant, el_plant = self.board.plants
                az_off = az_plant.true_azimuth_counts - self.board.azimuth.actual_position
                el_off = el_plant.true_azimuth_counts - self.board.elevation.actual_position
        true_az = azimuth_rad + az_off * _TWO_PI_PER_COUNT
        true_tilt = tilt_rad + el_off * _TWO_PI_PER_COUNT
        vehicle = None if self.trajectory is None else self.trajectory.pose(self._exposure_t)
        frame = self.optics.acquire(
            self.scene, true_az, true_tilt, lut_tilt_rad=lut_tilt_rad, vehicle_pose=vehicle
        )
        return frame.range_mm, frame.intensity

    def _exposure_azimuth(self, t: float) -> float:
        """The supervisor's encoder reading at mid-exposure, which it takes at the exposure's
        time ``t`` just before it calls :meth:`_acquire` (under its lock): ``t`` is kept for
        :meth:`_acquire` to place the vehicle where it was then."""
        self._exposure_t = t
        return self._encoder_azimuth(t)

    # -- backdoor --------------------------------------------------------------------------------
    def true_pose(self, t_hw: float) -> Pose:
        """(x_m, y_m, yaw_rad) of the vehicle in the scene at hardware time ``t_hw``, yaw in
        [-pi, pi): the truth the odometry drifts from."""
        if self.trajectory is None:
            return (0.0, 0.0, 0.0)
        return self.trajectory.pose(t_hw)

    @property
    def azimuth_counts(self) -> float:
        """The head's true azimuth in counts (0 = the zero index), read without side effects."""
        if self.drives:
            return float(self.drives[Axis.AZIMUTH].pose()[0])
        with self.board.lock:
            self.board.catch_up()
            return float(self.board.plants[0].true_azimuth_counts)

    @property
    def elevation_counts(self) -> float:
        """The head's true tilt in counts (0 = level, the tilt's zero index), positive up."""
        if self.drives:
            return float(self.drives[Axis.ELEVATION].pose()[0])
        with self.board.lock:
            self.board.catch_up()
            return float(self.board.plants[1].true_azimuth_counts)

    @property
    def time_scale(self) -> float:
        return self.clock.time_scale

    # -- lifecycle -------------------------------------------------------------------------------
    def start(self) -> SimulatedBiris:
        if self._closed:
            raise RuntimeError("the simulator has been shut down")
        if not self._started:
            self._started = True
            self.board.start()
            self.supervisor.start()
        return self

    def close(self) -> None:
        """Stop the simulator's threads, then close its lines and windows; idempotent."""
        if self._closed:
            return
        self._closed = True
        self.supervisor.stop()
        self.board.stop()
        self.faults.close()
        self.level2_gate.close()
        self.level3_gate.close()
        self.hardware.close()  # the driver's CAN bus first: the drives outlive its last frame
        self._close_drives()
        if self.crate is not None:
            self.crate.close()
        self._supervisor_window.close()
        if self.usb_device is not None:
            self.usb_device.close()
        for old in self.unplugged_usb_devices:
            old.close()

    def __enter__(self) -> SimulatedBiris:
        return self.start()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    # -- keeping up ------------------------------------------------------------------------------
    def lag_s(self) -> float:
        """How far behind its own clock the simulator runs, in hardware seconds (0 when stopped).

        The BIRIS supervisor's thread wakes at every video field (every
        :data:`~sim.supervisor.supervisor.IDLE_CHECK_FIELDS` while idle); :meth:`SimClock.lateness
        <sim.clock.SimClock.lateness>` averages how late those wakes come. A driver's reads
        catch the simulation up, so what it reads stays right, but interrupts come that late:
        beyond :data:`~sim.clock.LAG_WARNING_S` the host cannot keep up with
        :attr:`time_scale`, and the driver's hardware-time deadlines (settling, watchdogs, the
        BIRIS timeout) no longer mean what they would on the robot. Read-only.
        """
        if not self._started or self._closed:
            return 0.0
        return self.clock.lateness()

    @property
    def lag_bound_s(self) -> float:
        """:data:`~sim.clock.LAG_WARNING_S`: the :meth:`lag_s` beyond which :meth:`behind`."""
        from sim.clock import LAG_WARNING_S

        return LAG_WARNING_S

    def behind(self) -> bool:
        """True while :meth:`lag_s` exceeds :attr:`lag_bound_s`: the time scale is more than
        this host can simulate faithfully."""
        return self.lag_s() > self.lag_bound_s


_ = threading  # the rig's threads live in the board and the supervisor

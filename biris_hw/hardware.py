"""The hardware bundle a server drives: windows, interrupt lines, a clock (docs/design.md), and the
one driver object of each device on them (:class:`~biris_hw.devices.Devices`)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from os import PathLike
from typing import TYPE_CHECKING

from biris_hw.axes.base import AxisSet
from biris_hw.bus.base import BusWindow
from biris_hw.devices import Devices
from biris_hw.errors import BusError, HardwareFault
from biris_hw.irq.base import InterruptLine
from biris_hw.pan_reference import PanReference
from biris_hw.timebase import TimeBase, timebase_of

if TYPE_CHECKING:  # python-can is imported only when a crate monitor is made
    from biris_hw.crate import CrateMonitor

__all__ = ["BirisHardware"]


@dataclass
class BirisHardware:
    """Everything the BIRIS server touches, built by the simulator or from a target file.

    ``biris`` is BIRIS memory through the coupler, ``motion`` the Model 7600 board (None when
    ``axes``, CiA 402 drives say, replace it), ``coupler`` the Bit 3 registers; ``level2``
    carries BIRIS and coupler interrupts, ``level3`` the motor controller's. ``biexec_offset``
    is where BIEXEC_COM sits in ``biris``; ``biris_base`` is the BIRIS-side VME address at
    which ``biris`` starts, so that addresses BIRIS reports (such as Biris_range_ptr) become
    window offsets. ``clock`` returns hardware time in seconds.
    The bundle does not own what it holds: whoever built it closes it (:meth:`close`).

    ``devices`` is made with the bundle and is the only set of drivers over its windows: the
    server, its initialiser, ``status()`` and the CLI all use it (see :mod:`biris_hw.devices`).

    ``pan_reference`` is made with it too, once: what is known about the pan counter's relation
    to TRUE zero (:mod:`biris_hw.pan_reference`). Every server on this bundle shares it, so a
    reset or a new server on the same bundle homes to true zero, never to the nearest index.
    ``pan_journal`` is the file that carries it across driver *processes*: a target names one
    (docs/targets.md); None keeps it in memory, which suits an in-process simulator whose head
    dies with the process, and nothing else.
    """

    biris: BusWindow
    motion: BusWindow | None
    """The Model 7600 board; None when ``axes`` drives the axes instead."""
    coupler: BusWindow
    level2: InterruptLine
    level3: InterruptLine
    biexec_offset: int
    biris_base: int
    clock: Callable[[], float]
    time_scale: float = 1.0
    """Hardware seconds per real second: 1.0 on the target, the simulator's ``time_scale``
    otherwise (on virtual time, the scale the rig is nominally run at: a caller's timeout is read
    at it, see :meth:`TimeBase.timeout_hw <biris_hw.timebase.TimeBase.timeout_hw>`). Waits go
    through :attr:`timebase`, in hardware seconds."""
    pan_journal: str | PathLike[str] | None = None
    """The pan reference journal's path, or None to keep the reference in memory only."""
    axes: AxisSet | None = None
    """Axes not on the Model 7600 (CiA 402 drives over CAN: :class:`biris_hw.axes.cia402.
    Cia402Axes`), or None for the board's HCTL-1000s. ``level3`` is then the set's
    ``end_of_motion`` line. The bundle closes it with itself."""
    crate: CrateMonitor | None = None
    """The VME crate's own monitor over CAN (a Wiener crate's power, fans and temperatures:
    :mod:`biris_hw.crate`), or None. Read by the server every :attr:`crate_poll_s` and shown in
    ``status()``; the bundle closes it with itself."""
    crate_poll_s: float = 1.0
    """Real seconds between two readings of :attr:`crate`."""
    lag: Callable[[], float] | None = None
    """How far behind its own clock the hardware runs (hardware seconds): a simulator's
    (``SimulatedBiris.lag_s``), so that a fault met on a host that cannot keep up says so;
    None on the real target, whose clock is the host's."""
    pan_reference: PanReference = field(init=False, repr=False, compare=False)
    """The pan counter's relation to true zero, built here once (reads the journal if any)."""
    devices: Devices = field(init=False, repr=False, compare=False)
    """One driver per device over these windows, built here once (no register is touched)."""
    timebase: TimeBase = field(init=False, repr=False, compare=False)
    """What every thread of a server on this bundle waits through (:mod:`biris_hw.timebase`):
    the clock itself when it is a time base (a simulator's, scaled or virtual), else scaled time
    over ``clock`` at ``time_scale`` (the target's own clock)."""

    def __post_init__(self) -> None:
        self.timebase = timebase_of(self.clock, self.time_scale)
        self.pan_reference = PanReference(self.pan_journal)
        self.devices = Devices.over(
            biris=self.biris,
            biexec_offset=self.biexec_offset,
            motion=self.motion,
            coupler=self.coupler,
            clock=self.clock,
            time_scale=self.time_scale,
            pan_reference=self.pan_reference,
            axes=self.axes,
        )

    def to_offset(self, biris_address: int) -> int:
        """Window offset of a BIRIS-side VME address; ValueError when it is outside ``biris``."""
        offset = biris_address - self.biris_base
        if not 0 <= offset < self.biris.size:
            raise ValueError(
                f"BIRIS address 0x{biris_address:X} is outside the window "
                f"0x{self.biris_base:X}..0x{self.biris_base + self.biris.size - 1:X}"
            )
        return offset

    def relink(self) -> None:
        """Reopen every link to the target that was lost and can come back, keeping the same
        window, line and axis objects (the server and its drivers hold them); a server's reset
        calls it before it initialises (:mod:`biris_hw.server.initialiser`).

        Each window re-links what it reaches the bus through (:meth:`BusWindow.relink
        <biris_hw.bus.base.BusWindow.relink>`: a VM-USB found again by its serial number, its
        interrupt lines re-armed with it), then the axis set its drives (a CiA 402 drive whose
        heartbeat was lost: :meth:`~biris_hw.axes.cia402.Cia402Axes.relink`). Whatever is alive
        is left alone, so a reset after any other fault costs nothing here. A bundle reached
        some other way overrides it (:class:`biris_hw.simlink.RemoteHardware` reconnects to a
        simulator process that was restarted).

        Raises:
            HardwareFault: kind ``bus``, naming what is still missing and that its link must be
                restored (or, where that cannot help, that a new driver process is needed).
        """
        try:
            seen: list[BusWindow] = []
            for window in (self.biris, self.motion, self.coupler):
                if window is not None and not any(window is w for w in seen):
                    seen.append(window)
                    window.relink()
            if self.axes is not None:
                self.axes.relink()
        except HardwareFault:
            raise
        except BusError as exc:
            raise HardwareFault("bus", f"the target's link is still lost: {exc}") from exc

    def close(self) -> None:
        """Close the lines first (waking notifiers), then the windows, then the axis set and
        the crate monitor."""
        for line in (self.level2, self.level3):
            line.close()
        for window in (self.biris, self.motion, self.coupler):
            if window is not None:
                window.close()
        if self.axes is not None:
            self.axes.close()
        if self.crate is not None:
            self.crate.close()

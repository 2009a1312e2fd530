"""The server's tasks, in one table: what each is, what it waits on, what it sends, its thread.

The report's Harmony task structure (Fig. 4; "Tasks"): one administrator blocked on its inbox;
notifiers that wait on an interrupt and *send*; workers that report ready and wait for the
administrator's *reply* carrying their next order; ``_Biris_timeout`` as a timer. Here each task
is a unit of its own in the code (a function or class in :mod:`biris_hw.server.tasks`, the
routines in :mod:`biris_hw.server.isr`, the :class:`~biris_hw.server.admin.Administrator`, the
:class:`~biris_hw.server.initialiser.Initialiser`) and a row in :data:`TASKS`.

:class:`~biris_hw.server.server.BirisServer` starts its threads *from this table*, in its order:
a row whose ``thread`` is its own name gets a thread of that name; a row whose ``thread`` names
another row's runs inside that thread (the report's ISR "triggers" the task; here it calls it).
Rows that start ``PER_RESET`` are started by the administrator on each reset (the initialiser),
not with the server. A test compares the table with ``threading.enumerate()`` both ways.

**Supervision** (``restart``). Every thread the server starts from the table runs its body under
:class:`~biris_hw.server.tasks.Supervisor`, so no task dies of an exception. A failure is logged
with its traceback and reported to the administrator one-way as TaskFailed: a HardwareFault keeps
its own kind (a CiA 402 drive's EMCY raised by the level-3 routine is ``motor_stall``), kind
``bus`` for any other BusError (a window or interrupt line of a target that has gone),
``internal`` for anything else.
The thread then stays alive, under its name, and waits for the next reset
(``Restart.ON_RESET``), when it runs its body again. So a reset brings every task back, the
threads still match this table, and a task that keeps failing fails once per reset and never
spins. The administrator itself is restarted at once (``Restart.AT_ONCE``), since it is the task
that carries out a reset. The initialiser is not restarted (``Restart.NEVER``): it runs once per
reset, and a failure is its INIT_DONE's error.

The order is the creation order, Appendix B's for the report's eight tasks (its global indices,
``index``), then the tilt's future tasks, the watchdogs and the encoder reader, then the two
interrupt service routines (every notifier is already waiting on its logical line when they
start), then the administrator (everything it orders exists), then the initialiser.

**biris_data_notifier runs in level2_isr's thread.** Decided by measurement. Every-acquisition
latency: from the simulator raising the data interrupt to a client thread holding the Point (a
DATA connection with DeliveryPolicy.EVERY_ACQUISITION blocked in ready_for_data; 64 samples,
time_scale 1, continuous scan +-45 degrees, about 456 acquisitions per 20 s run, variants
interleaved, on a shared 2-vCPU machine), in microseconds, one figure per run:

=====================================================  ===============  ==================
variant                                                p50              p99
=====================================================  ===============  ==================
*with the administrator of 9ee12b3*
ISR thread, waits for the previous NEW_POINT's reply   341, 396         1307, 934
ISR thread, one-way post (chosen)                      305, 356         1212, 1629
own thread, one-way post                               406, 407         1461, 1966
own thread, synchronous send (Harmony's notifier)      424, 454         1852, 2003
*with the administrator being rewritten (components)*
ISR thread, one-way post (chosen)                      469, 463, 502    2415, 2635, 1145
own thread, one-way post                               518, 516, 551    1946, 1133, 1448
=====================================================  ===============  ==================

A thread of its own costs every acquisition one more wake-up and interpreter-lock hand-over: the
median is 50-100 us later in every pair of runs. The tails are dominated by the interpreter
lock and the machine (the order of the variants flips between runs). The own thread would
shorten the level-2 routine's service of a data interrupt (p50 about 45-57 us instead of
120-205 us: the frame reads move out), but BIRIS_CMD was demultiplexed as promptly either way
(sim raise to BIRIS_CMD raised, p50 47-124 us against 52-94 us): BIRIS_CMD ends a sequence, when
no frame read is pending. Throughput (the throughput benchmark's trial: 128 samples, 2 s
windows, administrator of 9ee12b3, 5 trials per variant and time_scale): no variant lost an
acquisition. Trials that kept the nominal rate at time_scale 128 (2557/s): waiting form 5/5,
one-way in the ISR thread 3/5 (the two others made 83 % and 90 % of it), own thread 5/5; at
181 (3616/s) all are saturated (1/5, 0/5, 2/5 kept it; mean measured 3132, 2970, 3000/s). A
one-way post per interrupt gives up the batching that waiting for the previous reply gave
under saturation; should the ceiling matter more than the latency, merging a NEW_POINT into one
still queued at the inbox's tail would restore it without ever waiting.

What the routine must never do is *wait for the administrator*, which the old form did (it
collected the previous NEW_POINT's reply before posting the next, holding the reader's lock):
every message drained from BIRIS memory is now posted one-way
(:meth:`biris_hw.ipc.Mailbox.post_oneway`), under the reader's lock so that the inbox's order is
the reader's, by this notifier and by the command and azimuth notifiers alike.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

__all__ = ["TASKS", "Restart", "Starts", "TaskKind", "TaskSpec", "task", "threads"]


class TaskKind(enum.Enum):
    """The report's kinds of task (plus the two routines and the initialiser)."""

    ISR = "interrupt service routine"
    """Waits on a physical interrupt level, decodes it and raises logical interrupts."""
    NOTIFIER = "notifier"
    """Waits on a logical interrupt and sends to the administrator."""
    WORKER = "worker"
    """Reports ready and waits for the administrator's reply, which carries its next order."""
    TIMER = "timer"
    """Sends to the administrator when an armed deadline passes."""
    ADMINISTRATOR = "administrator"
    """Waits on nothing but its inbox; replies, never sends, never touches a register."""
    INITIALISER = "initialiser"
    """_Create_server's start-up, again on every reset; orders moves and commands through the
    administrator."""


class Starts(enum.Enum):
    """When a task's thread is started."""

    WITH_SERVER = "with the server"
    PER_RESET = "on each reset"


class Restart(enum.Enum):
    """What the supervisor does once a task's body has failed (module notes, "Supervision")."""

    ON_RESET = "at the next reset"
    """Wait, alive, for the server's next reset, then run the body again."""
    AT_ONCE = "at once"
    """Run the body again at once, backing off while it keeps failing: for the administrator,
    which is the task that carries out a reset."""
    NEVER = "never"
    """Not restarted: the initialiser, whose failure is its INIT_DONE's error."""


@dataclass(frozen=True)
class TaskSpec:
    """One task of the server."""

    name: str
    """The task's name: the report's, lower case and without the leading underscore."""
    kind: TaskKind
    waits_on: str
    """What it blocks on."""
    sends: str
    """What it sends to the administrator (or raises, or writes)."""
    thread: str
    """The thread it runs on: its own (``thread == name``) or another row's."""
    why: str
    """Why it exists, and why on that thread."""
    report: str = ""
    """The report's name for it; empty when it is beyond the report."""
    index: str = ""
    """Its global index in the init record (Appendix B), for the report's eight tasks."""
    starts: Starts = Starts.WITH_SERVER
    restart: Restart = Restart.ON_RESET
    """What the supervisor does after the task has failed."""

    @property
    def own_thread(self) -> bool:
        """True when the task has a thread of its own (named after it)."""
        return self.thread == self.name


TASKS: tuple[TaskSpec, ...] = (
    TaskSpec(
        "biris_cmd_notifier",
        TaskKind.NOTIFIER,
        waits_on="BIRIS_CMD (logical, from level2_isr)",
        sends="NEW_POINT for what the sequence left unread (one-way), then BIRIS_CMD_COMPLETE "
        "with STATUS and PARAM; the reply is held until the next command is issued",
        thread="biris_cmd_notifier",
        why="A new BIRIS command must not be issued until BIRIS_CMD has been serviced; with "
        "AZ_SCAN_DONE it completes a scan. Its own thread: it blocks on the administrator.",
        report="_Biris_cmd_notifier",
        index="BIRIS_CMD_NOTIFIER",
    ),
    TaskSpec(
        "biris_cmd_transfer",
        TaskKind.WORKER,
        waits_on="the administrator's reply to CMD_TRANSFER_RDY (the next command)",
        sends="CMD_TRANSFER_RDY; writes PARAM, then COMMAND",
        thread="biris_cmd_transfer",
        why="Commands complete after tens of us to tens of ms (synchronised to vertical sync); "
        "a worker writes them so that the administrator never waits on BIRIS.",
        report="_Biris_cmd_transfer",
        index="BIRIS_CMD_TRANSFER",
    ),
    TaskSpec(
        "biris_data_notifier",
        TaskKind.NOTIFIER,
        waits_on="BIRIS_DATA_DEV (called by level2_isr for it)",
        sends="NEW_POINT with every acquisition completed up to ACQ_LINE-1; in continuous mode "
        "also CONTINUOUS_LIVE and SWEEP_DATA_DONE; all posted one-way, never waiting",
        thread="level2_isr",
        why="Every acquisition reaches the administrator. In level2_isr's thread by "
        "measurement (module notes): interrupt-to-client p50 305-356 us there against 406-407 "
        "us on a thread of its own (administrator of 9ee12b3), 463-502 against 516-551 us "
        "(administrator in rewrite): one wake-up less per acquisition; BIRIS_CMD demultiplexed "
        "as promptly either way; no loss either way. Posts one-way: the routine never waits "
        "for the administrator.",
        report="_Biris_data_notifier",
        index="BIRIS_DATA_NOTIFIER",
    ),
    TaskSpec(
        "biris_az_notifier",
        TaskKind.NOTIFIER,
        waits_on="MOTOR_END_OF_SCAN (logical, from level3_isr), then the head at rest "
        "(MotionAxis.wait_settled)",
        sends="in continuous mode the sweep's completed acquisitions (one-way), then AZ_SCAN_DONE "
        "with where the head stands, whether it settled, and which move ended",
        thread="biris_az_notifier",
        why="With BIRIS_CMD_COMPLETE it completes a scan. The chip's end of profile is not the "
        "motor's stop, so it polls the encoder; its own thread, since that takes milliseconds.",
        report="_Biris_az_notifier",
        index="BIRIS_AZ_NOTIFIER",
    ),
    TaskSpec(
        "az_scan_start",
        TaskKind.WORKER,
        waits_on="the administrator's reply to AZ_READY (a destination, or motor parameters)",
        sends="AZ_READY (with the previous order's error, if any); starts the trapezoid",
        thread="az_scan_start",
        why="Starts each azimuth motion by writing to the HCTL-1000, so the administrator never "
        "touches a register.",
        report="_az_scan_start",
        index="AZ_SCAN_START",
    ),
    TaskSpec(
        "biris_timeout",
        TaskKind.TIMER,
        waits_on="its deadline: 4 s of hardware time, armed by the administrator with each BIRIS "
        "command and re-armed by each acquisition",
        sends="BIRIS_TIMEOUT_ERR",
        thread="biris_timeout",
        why="A BIRIS that stops answering is a fault, not a hang. One long-lived task armed and "
        "disarmed, where the report created and destroyed one per command.",
        report="_Biris_timeout",
        index="BIRIS_TIMEOUT",
    ),
    TaskSpec(
        "biris_parity_err",
        TaskKind.NOTIFIER,
        waits_on="BIT3_PERR (logical, from level2_isr)",
        sends="BIRIS_PARITY_ERR",
        thread="biris_parity_err",
        why="A parity error on the bus coupler is a fatal hardware failure.",
        report="_Biris_parity_err",
        index="BIRIS_PAR_ERROR",
    ),
    TaskSpec(
        "biris_bus_err",
        TaskKind.NOTIFIER,
        waits_on="BIT3_BERR (logical, from level2_isr)",
        sends="BIRIS_BUS_ERR",
        thread="biris_bus_err",
        why="A failed bus cycle on the BIRIS chassis is a fatal hardware failure.",
        report="_Biris_bus_err",
        index="BIRIS_BUS_ERROR",
    ),
    TaskSpec(
        "el_scan_notifier",
        TaskKind.NOTIFIER,
        waits_on="ELEVATION_END_OF_SCAN (logical, from level3_isr), then the tilt at rest",
        sends="EL_SCAN_DONE with where the tilt stands, whether it settled, and which move ended",
        thread="el_scan_notifier",
        why="The report's future tilt task, as biris_az_notifier for the elevation axis.",
        report="_el_scan_notifier",
    ),
    TaskSpec(
        "el_scan_start",
        TaskKind.WORKER,
        waits_on="the administrator's reply to EL_READY (a tilt destination, or parameters)",
        sends="EL_READY; starts the tilt's trapezoid",
        thread="el_scan_start",
        why="The report's future tilt task, as az_scan_start for the elevation axis.",
        report="_el_scan_start",
    ),
    TaskSpec(
        "az_watchdog",
        TaskKind.TIMER,
        waits_on="its deadline, armed by the administrator with each azimuth motion",
        sends="MotorWatchdogErr (azimuth)",
        thread="az_watchdog",
        why="Beyond the report: a motion whose end never comes (a stalled motor) is a fault, "
        "not a hang.",
    ),
    TaskSpec(
        "el_watchdog",
        TaskKind.TIMER,
        waits_on="its deadline, armed by the administrator with each tilt",
        sends="MotorWatchdogErr (elevation)",
        thread="el_watchdog",
        why="Beyond the report: as az_watchdog, for the tilt.",
    ),
    TaskSpec(
        "encoder_reader",
        TaskKind.WORKER,
        waits_on="the administrator's reply to ENCODER_READING (the order to read again)",
        sends="ENCODER_READING with both axes' encoder positions (None for one it cannot read)",
        thread="encoder_reader",
        why="Beyond the report: status() says where the head is now, and the administrator "
        "never touches a register, so a worker reads the encoders when a status wants a "
        "fresher reading than the one held (at most 10 times a hardware second while an axis "
        "moves, once a second at rest: biris_hw.server.encoders). Its own thread: a reading "
        "crosses the bus (a USB round trip, a CAN SDO) and no status waits behind a scan.",
    ),
    TaskSpec(
        "level2_isr",
        TaskKind.ISR,
        waits_on="physical level 2 (BIRIS and the Bit 3 coupler) and its stop eventfd",
        sends="raises BIT3_PERR, BIT3_BERR (LOCAL_STATUS first), then by COMMAND BIRIS_CMD, or "
        "BIRIS_DATA_DEV by running biris_data_notifier",
        thread="level2_isr",
        why="Several logical interrupts share the physical level; the report's interrupt "
        "service routine demultiplexes them. Never waits on the administrator.",
        report="interrupt service routine (level 2)",
    ),
    TaskSpec(
        "level3_isr",
        TaskKind.ISR,
        waits_on="physical level 3 (the Model 7600) and its stop eventfd",
        sends="acknowledges IRQ_STATUS, then raises MOTOR_END_OF_SCAN and ELEVATION_END_OF_SCAN",
        thread="level3_isr",
        why="The motor board's end-of-profile interrupts, one logical line per axis.",
        report="interrupt service routine (level 3)",
    ),
    TaskSpec(
        "biris_server",
        TaskKind.ADMINISTRATOR,
        waits_on="its inbox (clients, notifiers, workers, timers, the initialiser)",
        sends="nothing: replies (a DATA connection's READY_FOR_DATA when a buffer completes; a "
        "worker's ready with its next order)",
        thread="biris_server",
        why="The report's BIRIS server: one case per message, the only owner of the server's "
        "state, so nothing in it needs a lock.",
        report="the BIRIS server",
        restart=Restart.AT_ONCE,
    ),
    TaskSpec(
        "biris_init",
        TaskKind.INITIALISER,
        waits_on="the administrator's replies to InitMove and InitCommand; encoder polls",
        sends="InitMove, InitCommand, then INIT_DONE",
        thread="biris_init",
        why="_Create_server's start-up (home both axes, boot BIRIS, learn its memory map), run "
        "again by every reset; a task of its own so that the administrator never waits on it.",
        report="_Create_server start-up",
        starts=Starts.PER_RESET,
        restart=Restart.NEVER,
    ),
)
"""Every task of the server, in creation order."""


def task(name: str) -> TaskSpec:
    """The row named ``name``; KeyError if there is none."""
    for spec in TASKS:
        if spec.name == name:
            return spec
    raise KeyError(name)


def threads(starts: Starts | None = None) -> tuple[str, ...]:
    """The names of the threads the table declares (those started ``starts``, or all), in
    creation order."""
    return tuple(
        spec.thread
        for spec in TASKS
        if spec.own_thread and (starts is None or spec.starts is starts)
    )

"""The task table (biris_hw.server.task_table) against the threads a server really runs, and the
rule that the level-2 interrupt service routine never waits on the administrator."""

from __future__ import annotations

import threading
from collections.abc import Iterator

import numpy as np
import pytest

from biris_hw import BirisInitRecord
from biris_hw.bus.memory import MemoryWindow
from biris_hw.devices import BirisLink
from biris_hw.ipc import Mailbox
from biris_hw.irq import EventFdLine
from biris_hw.server import BirisServer, tasks
from biris_hw.server.acquisition import Drained
from biris_hw.server.isr import Level2Demux, Logical
from biris_hw.server.messages import (
    Acquisition,
    AzScanDone,
    BirisCmdComplete,
    NewPoint,
    TransferOrder,
)
from biris_hw.server.task_table import TASKS, Starts, TaskKind, task, threads
from regs.biexec import OFF_COMMAND, BiCommand
from regs.bit3 import BIT3_SPACE, Bit3Reg, LocalStatus
from sim.rig import SimulatedBiris

WAIT = 5.0
"""Timeout for things that should happen almost at once; only reached when a test fails."""

BIEXEC = 0x100


# -- the table on its own ------------------------------------------------------------------------


def test_every_task_of_the_report_has_its_row() -> None:
    reported = {spec.report for spec in TASKS}
    for name in (
        "_Biris_cmd_notifier",
        "_Biris_cmd_transfer",
        "_Biris_data_notifier",
        "_Biris_az_notifier",
        "_az_scan_start",
        "_Biris_timeout",
        "_Biris_parity_err",
        "_Biris_bus_err",
        "_el_scan_notifier",
        "_el_scan_start",
    ):
        assert name in reported
        assert task(name.lstrip("_").lower()).report == name  # the report's name, lower case
    assert [spec.kind for spec in TASKS].count(TaskKind.ADMINISTRATOR) == 1


def test_the_reports_eight_tasks_are_created_in_appendix_b_order() -> None:
    # Appendix B's global indices as the record initialises them (Appendix A declares the bus
    # error index before the parity one; the record actually used has them this way round)
    appendix_b = (
        "BIRIS_CMD_NOTIFIER",
        "BIRIS_CMD_TRANSFER",
        "BIRIS_DATA_NOTIFIER",
        "BIRIS_AZ_NOTIFIER",
        "AZ_SCAN_START",
        "BIRIS_TIMEOUT",
        "BIRIS_PAR_ERROR",
        "BIRIS_BUS_ERROR",
    )
    assert tuple(spec.index for spec in TASKS if spec.index) == appendix_b
    assert [spec.name for spec in TASKS[:8]] == [
        "biris_cmd_notifier",
        "biris_cmd_transfer",
        "biris_data_notifier",
        "biris_az_notifier",
        "az_scan_start",
        "biris_timeout",
        "biris_parity_err",
        "biris_bus_err",
    ]


def test_every_row_runs_on_a_declared_thread() -> None:
    names = [spec.name for spec in TASKS]
    assert len(names) == len(set(names))
    own = {spec.name for spec in TASKS if spec.own_thread}
    for spec in TASKS:
        assert spec.thread in own, f"{spec.name} runs on {spec.thread}, which no row starts"
        assert spec.waits_on and spec.sends and spec.why
        if not spec.own_thread:  # a guest starts with its host
            assert task(spec.thread).starts is spec.starts
    assert threads() == tuple(spec.name for spec in TASKS if spec.own_thread)
    assert threads(Starts.PER_RESET) == ("biris_init",)
    assert task("biris_data_notifier").thread == "level2_isr"


# -- the table against a running server ---------------------------------------------------------


@pytest.fixture
def started(monkeypatch: pytest.MonkeyPatch) -> Iterator[list[str]]:
    """The names of the threads started while the fixture is in use, in order."""
    names: list[str] = []
    real_start = threading.Thread.start

    def start(thread: threading.Thread) -> None:
        names.append(thread.name)
        real_start(thread)

    monkeypatch.setattr(threading.Thread, "start", start)
    yield names


def _join(name: str) -> None:
    for thread in threading.enumerate():
        if thread.name == name:
            thread.join(WAIT)
            assert not thread.is_alive()


def test_the_server_runs_exactly_the_tables_threads(
    rig: SimulatedBiris, started: list[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    before = set(threading.enumerate())
    with BirisServer(rig.hardware, BirisInitRecord()) as server:
        monkeypatch.undo()  # stop recording: what follows starts no server thread
        # everything the table declares was started, once, in its order, and nothing else
        assert started == list(threads())
        _join(task("biris_init").thread)  # it reported INIT_DONE; it may still be returning
        running = [t.name for t in set(threading.enumerate()) - before]
        assert sorted(running) == sorted(threads(Starts.WITH_SERVER))  # both directions
        assert all(t.daemon for t in set(threading.enumerate()) - before)
        server.reset()  # the administrator starts the initialiser again: the table's thread
        _join(task("biris_init").thread)
        running = [t.name for t in set(threading.enumerate()) - before]
        assert sorted(running) == sorted(threads(Starts.WITH_SERVER))
    assert set(threading.enumerate()) - before == set()


def test_biris_data_notifier_runs_in_its_declared_thread(
    rig: SimulatedBiris, monkeypatch: pytest.MonkeyPatch
) -> None:
    ran_in: set[str] = set()
    notify = tasks.BirisDataNotifier.__call__

    def spy(self: tasks.BirisDataNotifier, count: int = 1) -> bool:
        ran_in.add(threading.current_thread().name)
        return notify(self, count)

    monkeypatch.setattr(tasks.BirisDataNotifier, "__call__", spy)
    with BirisServer(rig.hardware, BirisInitRecord()) as server:
        conn = server.open()
        conn.single_scan(to_deg=20.0)
        conn.wait_idle(timeout=30.0)
        conn.close()
        assert server.level2.counts[Logical.BIRIS_DATA_DEV] > 0
        assert server.level2.line(Logical.BIRIS_DATA_DEV).wait(0) == 0  # handed over, not raised
    assert ran_in == {task("biris_data_notifier").thread}


# -- the level-2 routine never waits on the administrator ------------------------------------------


def _acq(index: int) -> Acquisition:
    profile = np.zeros(4, np.int16)
    profile.setflags(write=False)
    return Acquisition(1, index, 0, 0, profile, profile, float(index), 0)


class FakeReader:
    """An acquisition reader with one new acquisition at every drain."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.drained = 0

    def drain(self, final: bool = False, ran: bool = True) -> Drained:
        assert self.lock.locked()
        self.drained += 1
        return Drained((_acq(self.drained),), 0, final)

    drain_sequence = drain


def test_an_administrator_that_never_answers_does_not_hold_up_the_routine() -> None:
    inbox = Mailbox("BIRISSERV")  # nobody receives: every sender would wait for ever
    reader = FakeReader()
    with (
        EventFdLine() as physical,
        MemoryWindow(BIT3_SPACE) as coupler,
        MemoryWindow(0x1000) as biris,
        Level2Demux(physical, coupler, biris, BIEXEC) as demux,
    ):
        demux.attach_data_notifier(tasks.BirisDataNotifier(inbox, reader))  # type: ignore[arg-type]
        biris.write16(BIEXEC + OFF_COMMAND, BiCommand.BI_ACQUIRE)  # data interrupts
        for _ in range(5):
            physical.trigger()
        coupler.write8(Bit3Reg.LOCAL_STATUS, LocalStatus.PARITY_ERROR)
        physical.trigger()
        assert demux.line(Logical.BIT3_PERR).wait(WAIT) == 1  # serviced behind the data
        coupler.write8(Bit3Reg.LOCAL_STATUS, 0)
        biris.write16(BIEXEC + OFF_COMMAND, 0)
        physical.trigger()
        assert demux.line(Logical.BIRIS_CMD).wait(WAIT) == 1
    assert reader.drained >= 1 and inbox.queued == reader.drained  # all posted, none answered
    points = [inbox.receive(timeout=0).message for _ in range(inbox.queued)]
    assert all(isinstance(p, NewPoint) for p in points)
    assert [p.acquisitions[0].index for p in points] == list(range(1, reader.drained + 1))  # type: ignore[attr-defined]


def test_the_command_notifier_never_waits_on_the_administrator_holding_the_readers_lock() -> None:
    inbox = Mailbox("BIRISSERV")
    reader = FakeReader()
    ledger = tasks.CommandLedger()
    ledger.outstanding = TransferOrder(int(BiCommand.BI_ACQUIRE), "3", 1, 3, token=7)
    flags: list[bool] = []
    with EventFdLine() as line, MemoryWindow(0x1000) as biris:
        notifier = threading.Thread(
            target=tasks.biris_cmd_notifier,
            args=(line, inbox, BirisLink(biris, BIEXEC), reader, ledger, flags.append),
        )
        notifier.start()
        line.trigger()  # COMMAND is 0: the command completed
        first = inbox.receive(timeout=WAIT)  # NEW_POINT, posted one-way under the lock
        assert isinstance(first.message, NewPoint) and first.oneway
        done = inbox.receive(timeout=WAIT)  # BIRIS_CMD_COMPLETE: the notifier now waits
        assert isinstance(done.message, BirisCmdComplete) and done.message.token == 7
        assert done.waiting and not first.waiting
        # the administrator has answered nothing, and the reader's lock is free
        assert reader.lock.acquire(timeout=WAIT)
        reader.lock.release()
        done.reply(None)
        inbox.close()
        line.close()
        notifier.join(WAIT)
        assert not notifier.is_alive()
    assert flags == []


# -- the axis notifier reports where the move ended ------------------------------------------------


class FakeAxis:
    """An axis that stops where it is told, settled or not; while it settles, the next move is
    recorded, as az_scan_start would once the administrator had ordered it."""

    def __init__(self, position: int, settles: bool, moves: tasks.MoveLedger) -> None:
        self.position = position
        self.settles = settles
        self.moves = moves

    def wait_settled(self, stop: threading.Event) -> bool:
        self.moves.token = 5  # a move started meanwhile must not lend the ended one its name
        return self.settles

    def actual_position(self) -> int:
        return self.position


@pytest.mark.parametrize("settles", [True, False])
def test_the_end_of_a_move_says_where_the_head_stands_whether_it_settled_and_which_move(
    settles: bool,
) -> None:
    inbox = Mailbox("BIRISSERV")
    moves = tasks.MoveLedger()
    axis = FakeAxis(position=37, settles=settles, moves=moves)
    stop = threading.Event()
    with EventFdLine() as line:
        notifier = threading.Thread(
            target=tasks.biris_az_notifier,
            args=(line, inbox, axis, stop, None, moves),
        )
        notifier.start()
        moves.token = 4  # az_scan_start records the move it starts
        line.trigger()  # its end of profile
        done = inbox.receive(timeout=WAIT)
        # never "done" alone: where the head stands and whether it settled, for the
        # administrator to compare with the destination (review defect 2)
        assert done.message == AzScanDone(position=37, settled=settles, token=4)
        done.reply(None)
        inbox.close()
        line.close()
        notifier.join(WAIT)
        assert not notifier.is_alive()

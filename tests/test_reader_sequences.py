"""The reader uses only frames written in the current BI_ACQUIRE sequence (issue 21).

BIEXEC_COM is shared by every sequence: between BI_ACQUIRE's write and the vertical sync at
which BIRIS sees it, ACQ_LINE still reads the previous sequence's -128. A data interrupt the
host delivers late can wake the reader then; taken at its word, that -128 made a scan of the
previous scan's rows (a recording's CCW #1 held CW #1's profiles). The reader trusts ACQ_LINE
only once it knows it is this sequence's: -1 or an acquisition index seen since the write, or
COMMAND read back 0 (BIRIS completed the command, which it does only after the sequence), or
the command notifier's final drain after a successful completion.
"""

from __future__ import annotations

import ctypes

import numpy as np

from biris_hw.bus.memory import MemoryWindow
from biris_hw.server.acquisition import AcquisitionReader
from regs.biexec import ACQ_LINE_END, ACQ_LINE_STARTUP, BiCommand, BiexecCom
from regs.layout import FRAME_DTYPE, FrameAddressing

SAMPLES = 4
PERIOD = 2 / 59.94
N = 6


class _Link:
    """BIEXEC_COM as the test sets it: ACQ_LINE and COMMAND."""

    def __init__(self) -> None:
        self.line = ACQ_LINE_END  # the previous sequence ended
        self.cmd = 0  # and its command completed
        self.window = MemoryWindow(ctypes.sizeof(BiexecCom))
        self.base = 0

    def acq_line(self) -> int:
        return self.line

    def command(self) -> int:
        return self.cmd

    def set_flags(self, *, data_int: bool) -> None:
        pass


def _reader() -> tuple[AcquisitionReader, _Link, MemoryWindow, FrameAddressing]:
    frame = 2 * (SAMPLES + 1)
    addr = FrameAddressing(0x40, frame, 0x40 + 2 * N * frame)
    window = MemoryWindow(addr.azimuth_offset + 4 * N)
    link = _Link()
    reader = AcquisitionReader(window, link, lambda: 1.0, 2000)  # type: ignore[arg-type]
    reader.configure(addr, SAMPLES, PERIOD)
    return reader, link, window, addr


def _frames(window: MemoryWindow, addr: FrameAddressing, closest: int) -> None:
    """Every frame holds ``closest`` in element 0: which sequence wrote it."""
    for k in range(N):
        values = np.full(SAMPLES + 1, closest, dtype=FRAME_DTYPE)
        window.write(addr.range_frame(k), values.tobytes())


def _drain(reader: AcquisitionReader, *, final: bool = False, ran: bool = True) -> list[int]:
    with reader.lock:
        drained = reader.drain_sequence(final=final, ran=ran) if final else reader.drain()
    return [acq.closest_mm for acq in drained.acquisitions]


def test_a_late_interrupt_before_biris_sees_the_command_reads_nothing_of_the_last_sequence() -> (
    None
):
    reader, link, window, addr = _reader()
    _frames(window, addr, 111)  # the previous sequence's frames
    reader.begin(2, N)
    assert _drain(reader) == []  # not even written: everything is the previous sequence's
    link.cmd = int(BiCommand.BI_ACQUIRE)
    reader.written()
    assert _drain(reader) == []  # written, not seen: -128 is still the previous one's
    link.line = ACQ_LINE_STARTUP  # BIRIS saw the command: its start-up
    assert _drain(reader) == []
    _frames(window, addr, 222)  # this sequence writes its frames
    link.line = 3
    assert _drain(reader) == [222, 222, 222]
    link.line = ACQ_LINE_END  # after -1 was seen, -128 is this sequence's end
    assert _drain(reader) == [222, 222, 222]


def test_a_sequence_never_seen_running_is_read_once_biris_has_completed_it() -> None:
    """Every interrupt of a short sequence delivered late, after its end: COMMAND read back 0
    says BIRIS completed this command, so the -128 is this sequence's."""
    reader, link, window, addr = _reader()
    reader.begin(2, N)
    link.cmd = int(BiCommand.BI_ACQUIRE)
    reader.written()
    _frames(window, addr, 222)
    link.cmd = 0  # completed (ACQ_LINE went -1, 0..5, -128 while nobody looked)
    assert _drain(reader) == [222] * N


def test_the_final_drain_after_a_refused_acquire_reads_nothing() -> None:
    """BIRIS refused the BI_ACQUIRE (a bad STATUS): it made nothing, and the -128 and the frames
    are the previous sequence's."""
    reader, _link, window, addr = _reader()
    _frames(window, addr, 111)
    reader.begin(2, N)
    reader.written()
    with reader.lock:
        drained = reader.drain_sequence(final=True, ran=False)
    assert drained.acquisitions == () and drained.finished and drained.lost == 0


def test_the_final_drain_after_a_completed_acquire_reads_the_rest() -> None:
    reader, link, window, addr = _reader()
    reader.begin(2, N)
    link.cmd = int(BiCommand.BI_ACQUIRE)
    reader.written()
    link.line = 2
    _frames(window, addr, 222)
    assert len(_drain(reader)) == 2
    link.line, link.cmd = ACQ_LINE_END, 0
    assert _drain(reader, final=True) == [222] * (N - 2)

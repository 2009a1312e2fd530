"""Reading completed acquisitions out of BIRIS memory, by ACQ_LINE rather than by interrupt.

BIRIS asserts its data interrupt *during* acquisition k, so the interrupt means k-1 is complete and
frame k still holds garbage. Interrupts can also arrive coalesced, or not at all; so the reader
never counts them. Each time it is woken it looks at ACQ_LINE and reads every acquisition from the
last one it delivered up to ACQ_LINE-1 (all of them once ACQ_LINE reads -128). An acquisition is
therefore lost only if its frame was overwritten first, and then it is counted, never silent.

Both the data notifier and the command notifier drain through one reader, under its lock, and
send what they drained before releasing the lock: the administrator's inbox is FIFO, so every
acquisition of a sequence reaches it before BIRIS_CMD_COMPLETE does.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from biris_hw.bus.base import BusWindow
from biris_hw.server.devices import BirisLink
from biris_hw.server.messages import Acquisition
from regs.biexec import ACQ_LINE_END, ACQ_LINE_STARTUP
from regs.layout import AZIMUTH_DTYPE, FRAME_DTYPE, FrameAddressing

__all__ = ["AcquisitionReader", "Drained"]


@dataclass(frozen=True)
class Drained:
    acquisitions: tuple[Acquisition, ...]
    lost: int
    finished: bool


class AcquisitionReader:
    """Catch-up reader for one acquisition sequence at a time."""

    def __init__(
        self,
        window: BusWindow,
        link: BirisLink,
        clock: Callable[[], float],
        max_range: int,
    ) -> None:
        self.lock = threading.Lock()
        self._window = window
        self._link = link
        self._clock = clock
        self._max_range = max_range
        self._addr: FrameAddressing | None = None
        self._samples = 0
        self._period = 0.0
        self._active = False
        self._seq_id = 0
        self._n = 0
        self._next = 0
        self.spurious = 0

    def configure(self, addressing: FrameAddressing, samples: int, period_s: float) -> None:
        """Where the frames are, as learned from BIRIS at initialisation."""
        with self.lock:
            self._addr = addressing
            self._samples = samples
            self._period = period_s

    @property
    def samples(self) -> int:
        return self._samples

    def begin(self, seq_id: int, n: int) -> None:
        """A BI_ACQUIRE of ``n`` acquisitions is about to be written; call before COMMAND."""
        with self.lock:
            self._active = True
            self._seq_id = seq_id
            self._n = n
            self._next = 0

    def abandon(self) -> None:
        with self.lock:
            self._active = False

    def drain(self, final: bool = False) -> Drained:
        """Read every acquisition completed since the last drain. Hold ``self.lock``.

        ``final`` is set by the command notifier: BIRIS has finished the sequence, so whatever
        ACQ_LINE says, nothing more will complete.
        """
        if not self._active or self._addr is None:
            if not final:
                self.spurious += 1
            return Drained((), 0, False)
        line = self._link.acq_line()
        now = self._clock()
        if line == ACQ_LINE_END:
            last, ref = self._n - 1, float(self._n)
        elif line >= 0:
            last, ref = min(line - 1, self._n - 1), float(line)
        elif line == ACQ_LINE_STARTUP:
            last, ref = -1, 0.0
        else:  # garbage in ACQ_LINE: read nothing now, the end of the sequence will tell
            last, ref = -1, 0.0
        out: list[Acquisition] = []
        for k in range(self._next, last + 1):
            out.append(self._read(k, now - (ref - k - 0.5) * self._period))
        self._next = max(self._next, last + 1)
        finished = line == ACQ_LINE_END or final
        lost = 0
        if finished:
            lost = max(0, self._n - self._next) if final else 0
            self._active = False
        return Drained(tuple(out), lost, finished)

    def _read(self, k: int, t: float) -> Acquisition:
        assert self._addr is not None
        count = self._samples + 1
        raw = self._window.read(self._addr.range_frame(k), count * 2)
        rng = np.frombuffer(raw, dtype=FRAME_DTYPE, count=count).astype(np.int16)
        raw_i = self._window.read(self._addr.intensity_frame(k), count * 2)
        inten = np.frombuffer(raw_i, dtype=FRAME_DTYPE, count=count).astype(np.int16)
        azimuth = int(
            np.frombuffer(self._window.read(self._addr.azimuth_entry(k), 4), dtype=AZIMUTH_DTYPE)[0]
        )
        profile = rng[1:].copy()
        bad = (profile > self._max_range) | (profile < 0)
        discarded = int(np.count_nonzero(bad & (profile != 0)))
        profile[bad] = 0
        closest = int(rng[0])
        if closest > self._max_range or closest < 0:
            closest = 0
        profile.setflags(write=False)
        intensity = inten[1:].copy()
        intensity.setflags(write=False)
        return Acquisition(
            seq_id=self._seq_id,
            index=k,
            azimuth=azimuth,
            closest_mm=closest,
            profile=profile,
            intensity=intensity,
            t=t,
            discarded=discarded,
        )

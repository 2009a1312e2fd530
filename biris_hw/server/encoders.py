"""The encoder readings a status carries, and when the encoder reader is sent to read again.

``status()`` says where the head is now (``azimuth_live``, ``elevation_live``). The
administrator never touches a register, so the ``encoder_reader`` worker reads both encoders
when it is told to (:func:`biris_hw.server.tasks.encoder_reader`), and this component decides
when that is: only when a status is asked for, and only when the reading held is too old for
it. A reading is fresh for :data:`MOVING_PERIOD_S` of hardware time while an axis moves (or
moved when it was taken), :data:`REST_PERIOD_S` while both stand still; a motion ordered or
ended since makes it stale at once. So however often status is asked for, the encoders are read
at most 10 times a hardware second during a motion and once a second at rest, and a status
asked just after a move ends sees where the head came to rest. A status that needs a fresh
reading waits for it (a bus round trip), as it used to wait for the read in its own thread.

Only the administrator thread calls this; nothing here blocks.
"""

from __future__ import annotations

from biris_hw.ipc import Envelope
from biris_hw.server.messages import EncoderReading, ReadEncoders

__all__ = ["MOVING_PERIOD_S", "REST_PERIOD_S", "Encoders"]

MOVING_PERIOD_S = 0.1
"""Hardware seconds a reading taken while an axis moves stays fresh: a status watched during a
scan follows the head at 10 readings a second."""

REST_PERIOD_S = 1.0
"""Hardware seconds a reading taken with both axes at rest stays fresh (while no motion is
ordered): a head pushed off its position is seen within a second."""


class Encoders:
    """The latest encoder reading, the reader worker parked on its last report, and the status
    requests waiting for a reading."""

    def __init__(self) -> None:
        self.azimuth: int | None = None
        self.elevation: int | None = None
        self.worker: Envelope | None = None
        """The encoder reader, parked on its last ENCODER_READING."""
        self.reading = False
        """An order to read is out: the worker is reading."""
        self.waiters: list[Envelope] = []
        """Status requests that wait for the reading under way."""
        self._motions = 0
        self._taken_at: float | None = None
        self._taken_motions = -1
        self._taken_moving = True
        self._ordered_at = 0.0
        self._ordered_motions = -1
        self._ordered_moving = True

    def moved(self) -> None:
        """A motion was ordered or ended (or a reset began): the reading held is stale."""
        self._motions += 1

    def fresh(self, now: float, moving: bool) -> bool:
        """Whether the reading held may go into a status asked for at ``now``."""
        if self._taken_at is None or self._taken_motions != self._motions:
            return False
        period = MOVING_PERIOD_S if moving or self._taken_moving else REST_PERIOD_S
        return now - self._taken_at < period

    @property
    def available(self) -> bool:
        """A reading can be had: the worker is parked, or reading already."""
        return self.worker is not None or self.reading

    def want(self, env: Envelope, now: float, moving: bool) -> None:
        """``env`` (a status request) waits for a reading; the worker is told to read unless it
        is reading already."""
        self.waiters.append(env)
        worker = self.worker
        if self.reading or worker is None:
            return
        self.worker = None
        self.reading = True
        self._ordered_at = now
        self._ordered_motions = self._motions
        self._ordered_moving = moving
        worker.reply(ReadEncoders())

    def report(self, env: Envelope, msg: EncoderReading) -> list[Envelope]:
        """ENCODER_READING: the worker parks again; returns the status requests to answer now.

        A reading is dated from its order (it is at least that recent)."""
        self.worker = env
        if not self.reading:
            return []  # the worker's first report, or one a failure left behind: nothing read
        self.reading = False
        if msg.read:
            self.azimuth, self.elevation = msg.azimuth, msg.elevation
            self._taken_at = self._ordered_at
            self._taken_motions = self._ordered_motions
            self._taken_moving = self._ordered_moving
        waiters, self.waiters = self.waiters, []
        return waiters

    def worker_gone(self) -> list[Envelope]:
        """The worker failed (it waits for a reset): returns the status requests to answer with
        what is held, since no reading will come."""
        self.worker = None
        self.reading = False
        waiters, self.waiters = self.waiters, []
        return waiters

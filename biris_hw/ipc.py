"""Harmony's Send/Receive/Reply between threads (docs/design.md).

The server is an *administrator*: it blocks only on its one inbox, never sends and never sleeps.
Everything that wants its attention (clients, notifiers, workers) sends to that inbox and stays
blocked until the administrator replies. This rendezvous is the whole synchronisation story of the
report, so the module keeps its semantics exact rather than offering a general queue:

* ``send`` is synchronous: the sender is SEND-blocked until the message is received, then
  REPLY-blocked until it is answered. There is no buffering beyond the senders themselves.
* ``reply`` never blocks, and may happen much later and from another thread (a parked
  READY_FOR_DATA is answered when a buffer completes; a worker is "dispatched" by replying).
* Stopping a task must not strand anyone: ``close`` releases every sender still waiting, queued
  or parked, with :class:`TaskStopped` (Harmony: destroying a task closes its connections).
* A sender that gives up (timeout) takes its message back, so the administrator never acts on a
  request whose client has stopped listening; if it was already received, the late reply is
  dropped and :meth:`Envelope.reply` says so by returning False.
* One exception to the rendezvous, for an interrupt service routine, which must never wait on
  the administrator: :meth:`Mailbox.post_oneway` queues a report nobody waits to have answered.
  It is still queued in order with every send, and still answered by the receiver (whose reply
  is then dropped, and a failure logged), so the administrator's side is unchanged.

Waiting is on a per-envelope lock (a one-shot signal) and, for the receiver, on a doorbell (one
more lock, released by the send that finds it waiting): no polling, and a reply or a send costs
one short critical section. The doorbell is a bare lock rather than a ``threading.Condition``
because the administrator is woken for every message, and a condition's wait and notify run
several times the Python code, which on a machine whose caches have gone cold between two
messages is much of the cost of a hop.

On virtual time (:class:`~biris_hw.timebase.VirtualTime`, issue 22) a bare lock will not do: the
time base must know who waits on what, or it would take a sender blocked on its envelope for a
running thread and never move time on (nor tell a deadlock). ``Mailbox(name, timebase)`` with a
virtual time base is therefore a mailbox whose every wait goes through the time base: each
envelope settles an event of the time base, and the doorbell is a condition of the time base on
the mailbox's lock. Both hand the wake over before the settling call returns, as virtual time
requires, and label their waits (``"reply from 'BIRISSERV'"``, ``"inbox 'BIRISSERV'"``) for the
deadlock message. The semantics above are the same in both kinds; a caller's timeout is read
through :meth:`~biris_hw.timebase.TimeBase.timeout_hw`. With no time base, or a scaled one, whose
waits are real waits anyway, a mailbox is the bare-lock one.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque

from biris_hw.errors import BirisError, ConnectionClosed
from biris_hw.timebase import HwCondition, HwEvent, TimeBase

__all__ = ["Envelope", "Mailbox", "ReplyError", "TaskStopped", "Ticket"]

log = logging.getLogger(__name__)

# Envelope states. Only the mailbox lock moves an envelope between them, which is what makes a
# reply racing a timeout or a close come out one way or the other, never both.
_QUEUED = 0  # sender SEND-blocked
_RECEIVED = 1  # sender REPLY-blocked
_ANSWERED = 2  # reply() or fail() delivered
_RELEASED = 3  # the mailbox was closed under the sender
_WITHDRAWN = 4  # the sender timed out (or was interrupted) and took the message back

_STATE_NAMES = ("queued", "received", "answered", "released", "withdrawn")


class TaskStopped(ConnectionClosed):
    """The task that owns a mailbox stopped; a send to it can never be answered."""


class ReplyError(BirisError, RuntimeError):
    """An envelope was answered twice, or before it was received: a bug in the receiving task."""


class Envelope:
    """One sent message, as the receiver holds it until it answers.

    Made by :class:`Mailbox`; the receiver gets it from :meth:`Mailbox.receive`, may keep it
    (park it) as long as it likes, and answers exactly once with :meth:`reply` or :meth:`fail`.
    """

    __slots__ = (
        "_answered",
        "_error",
        "_mailbox",
        "_signal",
        "_state",
        "_value",
        "message",
        "sender",
    )

    def __init__(self, message: object, mailbox: Mailbox, oneway: bool = False) -> None:
        self.message = message
        """What was sent."""
        self.sender = threading.current_thread().name
        """Name of the sending thread, for logs: Harmony's receiver always knows who sent."""
        self._mailbox = mailbox
        self._state = _QUEUED
        self._answered = False
        self._value: object = None
        self._error: BaseException | None = None
        # A plain lock used as a one-shot signal: held from birth, released once when the
        # envelope settles. Cheaper than an Event, and a timed acquire is the sender's wait.
        # A one-way envelope has nobody to signal.
        self._signal: threading.Lock | None = None
        if not oneway:
            self._signal = threading.Lock()
            self._signal.acquire()

    @property
    def waiting(self) -> bool:
        """True while the sender is REPLY-blocked on this envelope.

        False once answered, once the sender timed out, and once the mailbox closed: an
        administrator can drop parked envelopes whose sender has gone. Always False for a
        one-way post (:meth:`Mailbox.post_oneway`), whose sender never waits.
        """
        return self._state == _RECEIVED and self._signal is not None

    @property
    def oneway(self) -> bool:
        """True for a message posted with :meth:`Mailbox.post_oneway`: the reply goes nowhere."""
        return self._signal is None

    def reply(self, value: object = None) -> bool:
        """Release the sender, whose ``send`` returns ``value``; never blocks.

        Returns False when nobody is listening (the sender timed out, the mailbox was closed, or
        the message was posted one-way); the value is then discarded. Answering twice raises
        :class:`ReplyError`.
        """
        return self._answer(value, None)

    def fail(self, exc: BaseException) -> bool:
        """Release the sender, whose ``send`` raises ``exc``; otherwise exactly like :meth:`reply`.

        This is how a RequestError or HardwareFault reaches a client: the error is raised in the
        client's thread, where the request was made.
        """
        if not isinstance(exc, BaseException):
            raise TypeError(f"fail() needs an exception instance, not {type(exc).__name__}")
        answered = self._answer(None, exc)
        if self._signal is None:
            log.debug("%r refused, and nobody waits for the answer: %r", self, exc)
        return answered

    def _answer(self, value: object, error: BaseException | None) -> bool:
        mailbox = self._mailbox
        with mailbox._lock:
            if self._answered:
                raise ReplyError(f"{self!r} was already answered")
            if self._state == _QUEUED:
                raise ReplyError(f"{self!r} has not been received")
            self._answered = True
            if self._state != _RECEIVED:
                return False
            mailbox._held.discard(self)
            self._settle(_ANSWERED, value, error)
            return self._signal is not None

    def _settle(self, state: int, value: object, error: BaseException | None) -> None:
        """Final state and result, then wake the sender. Caller holds the mailbox lock."""
        self._state = state
        self._value = value
        self._error = error
        if self._signal is not None:
            self._signal.release()

    def _withdraw_locked(self) -> None:
        """The sender gives up: take the message back. Caller holds the mailbox lock."""
        if self._state == _QUEUED:
            self._mailbox._queue.remove(self)
        elif self._state == _RECEIVED:
            self._mailbox._held.discard(self)
        else:
            return
        self._settle(
            _WITHDRAWN, None, TimeoutError(f"no reply from {self._mailbox.name!r} in time")
        )

    def _await(self, timeout: float | None) -> object:
        """The sender's half of send(): block until settled, withdrawing on timeout."""
        signal = self._signal
        assert signal is not None, "a one-way post has no answer to wait for"
        try:
            settled = signal.acquire(True, -1 if timeout is None else max(timeout, 0.0))
        except BaseException:
            # Interrupted (KeyboardInterrupt in the main thread): do not leave a request behind
            # that the administrator would act on for a caller that has gone.
            with self._mailbox._lock:
                self._withdraw_locked()
            raise
        if settled:
            signal.release()  # leave the signal open: a second wait returns at once
        else:
            with self._mailbox._lock:
                self._withdraw_locked()  # no-op if a reply won the race: then use it
        if self._error is not None:
            raise self._error
        return self._value

    def __repr__(self) -> str:
        return (
            f"<Envelope {self.message!r} from {self.sender!r} to {self._mailbox.name!r}: "
            f"{_STATE_NAMES[self._state]}>"
        )


class Ticket:
    """The sender's side of a message queued with :meth:`Mailbox.post`.

    ``mailbox.send(m, t)`` is exactly ``mailbox.post(m).wait(t)``: splitting the two lets a thread
    know its message is queued before it blocks (tests rely on that to be deterministic).
    """

    __slots__ = ("_envelope",)

    def __init__(self, envelope: Envelope) -> None:
        self._envelope = envelope

    @property
    def message(self) -> object:
        """What was posted."""
        return self._envelope.message

    @property
    def done(self) -> bool:
        """True once :meth:`wait` would not block: answered, released by close, or withdrawn."""
        return self._envelope._state > _RECEIVED

    def wait(self, timeout: float | None = None) -> object:
        """The reply; raises what the receiver failed with, TaskStopped, or TimeoutError.

        On timeout the message is withdrawn (or, if already received, its reply will be dropped)
        and every later wait raises the same TimeoutError at once.
        """
        return self._envelope._await(timeout)


class Mailbox:
    """A task's inbox: any number of senders, one receiving task (the owner).

    ``name`` is for messages and logs, like a Harmony server's registered name. ``timebase`` is
    the time base of the rig the mailbox serves: with a virtual one, every wait of a sender or
    a receiver is a wait in its domain (module notes); with None or a scaled one, waits are on
    bare locks. Timeouts are the caller's seconds either way.
    """

    def __new__(cls, name: str, timebase: TimeBase | None = None) -> Mailbox:
        if cls is Mailbox and timebase is not None and timebase.virtual:
            cls = _VirtualMailbox
        return super().__new__(cls)

    def __init__(self, name: str, timebase: TimeBase | None = None) -> None:
        self.name = name
        self.timebase = timebase
        """The time base given, if any (its waits are used only when it is virtual)."""
        self._lock = threading.Lock()
        # Released ("rung") when there is news for a blocked receiver; ``_rung`` says so, so a
        # second sender never releases it twice. A ring nobody took is harmless: the receiver
        # that next finds it looks at the queue and waits again.
        self._doorbell = threading.Lock()
        self._doorbell.acquire()
        self._rung = False
        self._queue: deque[Envelope] = deque()  # senders SEND-blocked, in order of sending
        self._held: set[Envelope] = set()  # received, not answered: REPLY-blocked senders
        self._receiving = 0  # receivers blocked in receive(): only they need the doorbell
        self._closed = False
        self._reason: BaseException | None = None

    # -- sender side ---------------------------------------------------------------------------

    def send(self, message: object, timeout: float | None = None) -> object:
        """Send and block until answered; return the reply value.

        Raises what the receiver passed to :meth:`Envelope.fail`, :class:`TaskStopped` (or the
        close reason) if the mailbox is or becomes closed, and TimeoutError after ``timeout``
        seconds, having withdrawn the message.
        """
        return self._post(message)._await(timeout)

    def post(self, message: object) -> Ticket:
        """Queue ``message`` without blocking; :meth:`Ticket.wait` is the rest of :meth:`send`."""
        return Ticket(self._post(message))

    def post_oneway(self, message: object) -> None:
        """Queue ``message`` and never wait for its answer: for an interrupt service routine.

        Ordered with every other message exactly as :meth:`post` is (so a task that posts under
        a lock of its own puts its messages in the inbox in that lock's order). The receiver
        answers it as any other; the reply is dropped, a failure is logged (debug), and
        :meth:`Envelope.reply` returns False. Raises :class:`TaskStopped` (or the close reason)
        if the mailbox is closed.
        """
        self._post(message, oneway=True)

    def _post(self, message: object, oneway: bool = False) -> Envelope:
        envelope = Envelope(message, self, oneway)
        with self._lock:
            if self._closed:
                raise self._stopped()
            self._queue.append(envelope)
            if self._receiving and not self._rung:
                self._rung = True
                self._doorbell.release()
        return envelope

    # -- receiver side -------------------------------------------------------------------------

    def receive(self, timeout: float | None = None) -> Envelope:
        """The oldest message; blocks until one arrives.

        Raises :class:`TaskStopped` (or the close reason) once the mailbox is closed and
        TimeoutError after ``timeout`` seconds without a message.
        """
        lock = self._lock
        with lock:
            if self._queue or self._closed:
                return self._take_locked()
            self._receiving += 1
        deadline = None if timeout is None else time.monotonic() + max(0.0, timeout)
        left = False
        try:
            while True:
                wait = -1.0 if deadline is None else max(0.0, deadline - time.monotonic())
                rang = self._doorbell.acquire(True, wait)
                with lock:
                    if rang:
                        self._rung = False
                    news = bool(self._queue) or self._closed
                    if not news and (rang or deadline is None or time.monotonic() < deadline):
                        continue  # a ring meant for an earlier wait, or another receiver's
                    self._receiving -= 1
                    left = True
                    if not news:
                        raise TimeoutError(f"no message for {self.name!r} in {timeout} s")
                    if self._receiving and (self._closed or len(self._queue) > 1):
                        self._ring_locked()  # news left for another receiver
                    return self._take_locked()
        finally:
            if not left:  # interrupted while waiting
                with lock:
                    self._receiving -= 1

    def _ring_locked(self) -> None:
        """Wake a blocked receiver (caller holds the lock and knows one waits)."""
        if not self._rung:
            self._rung = True
            self._doorbell.release()

    def try_receive(self) -> Envelope | None:
        """The oldest message, or None at once if there is none (Harmony's _Try_receive)."""
        with self._lock:
            if not self._queue and not self._closed:
                return None
            return self._take_locked()

    def _take_locked(self) -> Envelope:
        if self._closed:
            raise self._stopped()
        envelope = self._queue.popleft()
        envelope._state = _RECEIVED
        self._held.add(envelope)
        return envelope

    # -- lifetime ------------------------------------------------------------------------------

    def close(self, reason: BaseException | None = None) -> None:
        """Stop the mailbox: every waiting sender, queued or parked, raises; idempotent.

        Senders raise ``reason`` if given (a HardwareFault that stopped the server, say),
        otherwise a :class:`TaskStopped`. Later sends and receives raise the same way, and a
        late reply to a released envelope returns False. The first close's reason sticks.
        """
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._reason = reason
            released = [*self._queue, *self._held]
            self._queue.clear()
            self._held.clear()
            for envelope in released:
                envelope._settle(_RELEASED, None, self._stopped())
            if self._receiving:
                self._ring_locked()  # each receiver that wakes passes the ring on

    @property
    def closed(self) -> bool:
        """True once :meth:`close` has been called."""
        return self._closed

    @property
    def queued(self) -> int:
        """Messages sent but not yet received (senders SEND-blocked), for logs and tests."""
        return len(self._queue)

    @property
    def held(self) -> int:
        """Messages received but not yet answered (senders REPLY-blocked, parked included)."""
        return len(self._held)

    @property
    def receivers(self) -> int:
        """Threads blocked in :meth:`receive` right now, for logs and tests."""
        return self._receiving

    def _stopped(self) -> BaseException:
        """What a sender or receiver raises on a closed mailbox. Caller holds the lock."""
        if self._reason is not None:
            return self._reason
        return TaskStopped(f"task {self.name!r} has stopped")

    def __repr__(self) -> str:
        state = "closed" if self._closed else f"{self.queued} queued, {self.held} held"
        return f"<Mailbox {self.name!r}: {state}>"


# -- on virtual time ------------------------------------------------------------------------------


class _VirtualEnvelope(Envelope):
    """An envelope whose sender waits in the domain of a virtual time base: on an event of the
    time base, set when the envelope settles. The inherited signal lock still marks an envelope
    somebody waits for (:attr:`Envelope.waiting`, :attr:`Envelope.oneway`); nobody waits on it."""

    __slots__ = ("_event",)

    def __init__(self, message: object, mailbox: _VirtualMailbox, oneway: bool = False) -> None:
        super().__init__(message, mailbox, oneway)
        self._event: HwEvent | None = None if oneway else mailbox._timebase_v.Event()

    def _settle(self, state: int, value: object, error: BaseException | None) -> None:
        super()._settle(state, value, error)
        if self._event is not None:
            self._event.set()  # hands the wake over before the settling call returns

    def _await(self, timeout: float | None) -> object:
        event = self._event
        assert event is not None, "a one-way post has no answer to wait for"
        mailbox = self._mailbox
        timebase = mailbox.timebase
        assert timebase is not None
        timeout_hw = None if timeout is None else timebase.timeout_hw(max(timeout, 0.0))
        try:
            settled = event.wait(timeout_hw, what=f"reply from {mailbox.name!r}")
        except BaseException:
            # Interrupted, or a deadlock of the domain: the caller has gone, take it back.
            with mailbox._lock:
                self._withdraw_locked()
            raise
        if not settled:
            with mailbox._lock:
                self._withdraw_locked()  # no-op if a reply won the race: then use it
        if self._error is not None:
            raise self._error
        return self._value


class _VirtualMailbox(Mailbox):
    """The mailbox of a rig on virtual time (module notes): its receivers wait on a condition
    of the time base on the mailbox's lock, its senders on their envelopes' events.

    Made by ``Mailbox(name, timebase)`` for a virtual ``timebase``.
    """

    def __init__(self, name: str, timebase: TimeBase | None = None) -> None:
        super().__init__(name, timebase)
        assert timebase is not None and timebase.virtual
        self._timebase_v = timebase
        self._news: HwCondition = timebase.Condition(self._lock)

    def _post(self, message: object, oneway: bool = False) -> Envelope:
        envelope = _VirtualEnvelope(message, self, oneway)
        with self._lock:
            if self._closed:
                raise self._stopped()
            self._queue.append(envelope)
            if self._receiving:
                self._news.notify()  # one message, one receiver
        return envelope

    def receive(self, timeout: float | None = None) -> Envelope:
        with self._lock:
            if self._queue or self._closed:
                return self._take_locked()
            timeout_hw = None if timeout is None else self._timebase_v.timeout_hw(max(0.0, timeout))
            self._receiving += 1
            try:
                news = self._news.wait_for(self._has_news, timeout_hw, what=f"inbox {self.name!r}")
            finally:
                self._receiving -= 1  # also when interrupted, or the domain deadlocked
            if not news:
                raise TimeoutError(f"no message for {self.name!r} in {timeout} s")
            if self._receiving and len(self._queue) > 1:
                self._news.notify()  # news left for another receiver
            return self._take_locked()

    def _has_news(self) -> bool:
        return bool(self._queue) or self._closed

    def _ring_locked(self) -> None:
        """Wake every blocked receiver: only :meth:`close` rings outside :meth:`_post`."""
        self._news.notify_all()

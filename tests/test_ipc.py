"""Send/Receive/Reply: the rendezvous the whole server is built on (biris_hw.ipc)."""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from biris_hw.errors import ConnectionClosed, HardwareFault, RequestError
from biris_hw.ipc import Envelope, Mailbox, ReplyError, TaskStopped
from biris_hw.timebase import HwThread, ScaledTime, VirtualTime, VirtualTimeDeadlock

WAIT = 5.0  # generous bound on every blocking call, so a bug fails instead of hanging


@pytest.fixture(params=["bare", "virtual"])
def mailbox(request: pytest.FixtureRequest) -> Mailbox:
    """A mailbox for one thread's use: the bare-lock one, and one whose waits go through a
    virtual time base (the test's thread is its driver), so every semantics checked with it
    holds on both."""
    if request.param == "bare":
        return Mailbox("server")
    return Mailbox("server", VirtualTime(stall_timeout=WAIT))


class Sender(threading.Thread):
    """A thread that makes one send() and records how it ended."""

    def __init__(self, mailbox: Mailbox, message: object, timeout: float | None = WAIT) -> None:
        super().__init__(daemon=True)
        self.mailbox = mailbox
        self.message = message
        self.timeout = timeout
        self.result: object = None
        self.error: BaseException | None = None
        self.before_return: Callable[[], None] = lambda: None

    def run(self) -> None:
        try:
            self.result = self.mailbox.send(self.message, timeout=self.timeout)
        except BaseException as exc:
            self.error = exc
        self.before_return()

    def finish(self) -> Sender:
        self.join(WAIT)
        assert not self.is_alive(), "sender still blocked"
        return self


def test_send_blocks_until_the_reply() -> None:
    mailbox = Mailbox("server")
    log: list[str] = []
    replying = threading.Event()
    sender = Sender(mailbox, "ping")

    def returned() -> None:
        # Runs in the sender after send() returned: the receiver must have begun replying.
        assert replying.is_set()
        log.append("returned")

    sender.before_return = returned
    sender.start()
    envelope = mailbox.receive(timeout=WAIT)
    log.append("received")
    assert envelope.message == "ping"
    assert envelope.waiting and sender.is_alive()  # REPLY-blocked: received, not answered
    assert mailbox.queued == 0 and mailbox.held == 1
    replying.set()
    log.append("replying")
    assert envelope.reply("pong") is True
    sender.finish()
    assert log == ["received", "replying", "returned"]
    assert sender.result == "pong" and sender.error is None
    assert not envelope.waiting and mailbox.held == 0


def test_post_is_send_blocked_until_received(mailbox: Mailbox) -> None:
    ticket = mailbox.post("hello")
    assert mailbox.queued == 1 and not ticket.done  # SEND-blocked
    envelope = mailbox.receive(timeout=WAIT)
    assert mailbox.queued == 0 and mailbox.held == 1 and not ticket.done  # REPLY-blocked
    envelope.reply(42)
    assert ticket.done
    assert ticket.wait(timeout=0) == 42
    assert ticket.wait() == 42  # a second wait returns at once


def test_reply_never_blocks_even_before_the_sender_waits(mailbox: Mailbox) -> None:
    # One thread plays both sides: if reply() waited for the sender to collect, this would hang.
    ticket = mailbox.post("request")
    envelope = mailbox.receive(timeout=WAIT)
    assert envelope.reply("answer") is True
    assert ticket.wait(timeout=WAIT) == "answer"


def test_messages_arrive_in_order_of_sending(mailbox: Mailbox) -> None:
    tickets = [mailbox.post(i) for i in range(5)]
    envelopes = [mailbox.receive(timeout=WAIT) for _ in range(5)]
    assert [e.message for e in envelopes] == [0, 1, 2, 3, 4]
    for envelope in envelopes:
        envelope.reply(envelope.message)
    assert [t.wait(0) for t in tickets] == [0, 1, 2, 3, 4]


def test_deferred_reply_from_another_thread() -> None:
    mailbox = Mailbox("server")
    sender = Sender(mailbox, "READY_FOR_DATA")
    sender.start()
    parked = mailbox.receive(timeout=WAIT)  # the administrator parks it and goes on receiving
    other = Sender(mailbox, "NEW_POINT")
    other.start()
    mailbox.receive(timeout=WAIT).reply("ok")
    other.finish()
    assert sender.is_alive() and parked.waiting

    replier = threading.Thread(target=parked.reply, args=("buffer",))
    replier.start()
    replier.join(WAIT)
    sender.finish()
    assert sender.result == "buffer"


def test_fail_raises_the_exception_in_the_sender() -> None:
    mailbox = Mailbox("server")
    sender = Sender(mailbox, "BIRIS_SINGLE_SCAN_RQST")
    sender.start()
    error = RequestError("destination is not a number")
    assert mailbox.receive(timeout=WAIT).fail(error) is True
    sender.finish()
    assert sender.error is error


def test_fail_needs_an_exception(mailbox: Mailbox) -> None:
    mailbox.post("x")
    envelope = mailbox.receive(timeout=WAIT)
    with pytest.raises(TypeError):
        envelope.fail("not an exception")  # type: ignore[arg-type]
    assert envelope.reply() is True  # the failed attempt did not count as an answer


@pytest.mark.parametrize(
    ("first", "second"),
    [("reply", "reply"), ("reply", "fail"), ("fail", "reply"), ("fail", "fail")],
)
def test_answering_twice_raises(mailbox: Mailbox, first: str, second: str) -> None:
    ticket = mailbox.post("x")
    envelope = mailbox.receive(timeout=WAIT)

    def answer(how: str) -> bool:
        return envelope.reply(1) if how == "reply" else envelope.fail(RequestError("no"))

    answer(first)
    with pytest.raises(ReplyError):
        answer(second)
    if first == "reply":
        assert ticket.wait(0) == 1
    else:
        with pytest.raises(RequestError):
            ticket.wait(0)


def test_close_releases_queued_received_and_parked_senders() -> None:
    mailbox = Mailbox("server")
    parked = Sender(mailbox, "READY_FOR_DATA")  # received, kept for a later buffer
    parked.start()
    parked_envelope = mailbox.receive(timeout=WAIT)
    working = Sender(mailbox, "REQUEST_POINT")  # received, being worked on
    working.start()
    working_envelope = mailbox.receive(timeout=WAIT)
    queued = [mailbox.post(i) for i in range(3)]  # never received
    assert mailbox.queued == 3 and mailbox.held == 2

    mailbox.close()

    for sender in (parked.finish(), working.finish()):
        assert isinstance(sender.error, TaskStopped)
    for ticket in queued:
        assert ticket.done
        with pytest.raises(TaskStopped):
            ticket.wait(0)
    # Late answers are dropped, not errors: the administrator may still be unwinding.
    assert parked_envelope.reply("late") is False
    assert working_envelope.fail(RequestError("late")) is False
    assert not parked_envelope.waiting
    assert mailbox.queued == 0 and mailbox.held == 0


def test_task_stopped_is_a_connection_closed() -> None:
    assert issubclass(TaskStopped, ConnectionClosed)


def test_close_wakes_a_sender_blocked_in_send_and_a_blocked_receiver() -> None:
    mailbox = Mailbox("server")
    sender = Sender(mailbox, "x", timeout=None)
    sender.start()
    mailbox.receive(timeout=WAIT)  # the sender is now REPLY-blocked with no timeout
    receiver_error: list[BaseException] = []
    receiving = threading.Event()

    def receive() -> None:
        receiving.set()
        try:
            mailbox.receive()
        except BaseException as exc:
            receiver_error.append(exc)

    receiver = threading.Thread(target=receive, daemon=True)
    receiver.start()
    assert receiving.wait(WAIT)
    mailbox.close()
    receiver.join(WAIT)
    assert isinstance(sender.finish().error, TaskStopped)
    assert len(receiver_error) == 1 and isinstance(receiver_error[0], TaskStopped)


def test_close_with_a_reason_raises_it_in_senders(mailbox: Mailbox) -> None:
    ticket = mailbox.post("x")
    fault = HardwareFault("bus", "bus error on the BIRIS chassis")
    mailbox.close(fault)
    with pytest.raises(HardwareFault) as info:
        ticket.wait(0)
    assert info.value is fault
    with pytest.raises(HardwareFault):
        mailbox.send("y")


def test_after_close_send_and_receive_raise_at_once(mailbox: Mailbox) -> None:
    mailbox.close()
    mailbox.close()  # idempotent
    assert mailbox.closed
    with pytest.raises(TaskStopped):
        mailbox.send("x")  # no timeout: would hang if it queued
    with pytest.raises(TaskStopped):
        mailbox.post("x")
    with pytest.raises(TaskStopped):
        mailbox.receive()
    with pytest.raises(TaskStopped):
        mailbox.try_receive()


def test_try_receive_does_not_block(mailbox: Mailbox) -> None:
    assert mailbox.try_receive() is None
    ticket = mailbox.post("x")
    envelope = mailbox.try_receive()
    assert envelope is not None and envelope.message == "x"
    envelope.reply()
    assert ticket.wait(0) is None


def test_receive_timeout(mailbox: Mailbox) -> None:
    with pytest.raises(TimeoutError):
        mailbox.receive(timeout=0.01)


def test_send_timeout_withdraws_an_unreceived_message(mailbox: Mailbox) -> None:
    with pytest.raises(TimeoutError):
        mailbox.send("too late", timeout=0.01)
    assert mailbox.queued == 0
    assert mailbox.try_receive() is None  # the receiver never sees it


def test_ticket_timeout_withdraws_and_sticks(mailbox: Mailbox) -> None:
    ticket = mailbox.post("x")
    with pytest.raises(TimeoutError):
        ticket.wait(0)
    assert ticket.done and mailbox.queued == 0
    with pytest.raises(TimeoutError):
        ticket.wait()  # no timeout: would hang if the withdrawal did not settle the ticket


def test_late_reply_after_a_send_timeout_is_discarded(mailbox: Mailbox) -> None:
    ticket = mailbox.post("x")
    envelope = mailbox.receive(timeout=WAIT)
    with pytest.raises(TimeoutError):
        ticket.wait(0.01)  # gives up while REPLY-blocked
    assert not envelope.waiting and mailbox.held == 0
    assert envelope.reply("late") is False
    with pytest.raises(ReplyError):
        envelope.reply("again")


def test_withdrawn_message_leaves_later_ones_in_place(mailbox: Mailbox) -> None:
    first = mailbox.post("first")
    second = mailbox.post("second")
    with pytest.raises(TimeoutError):
        first.wait(0)
    envelope = mailbox.receive(timeout=WAIT)
    assert envelope.message == "second"
    envelope.reply("ok")
    assert second.wait(0) == "ok"


@settings(max_examples=20, deadline=None)
@given(order=st.permutations(range(6)))
def test_concurrent_senders_each_get_their_own_reply(order: list[int]) -> None:
    mailbox = Mailbox("server")
    start = threading.Barrier(len(order))

    class Racer(Sender):
        def run(self) -> None:
            start.wait(WAIT)  # all send at once, in no particular order
            super().run()

    senders = [Racer(mailbox, i) for i in range(len(order))]
    for sender in senders:
        sender.start()
    received = {}
    for _ in senders:
        envelope = mailbox.receive(timeout=WAIT)
        received[envelope.message] = envelope
    for i in order:  # answer in an arbitrary order, all deferred
        received[i].reply(("reply to", i))
    for i, sender in enumerate(senders):
        sender.finish()
        assert sender.error is None
        assert sender.result == ("reply to", i)


def test_many_senders_one_receiver_thread() -> None:
    mailbox = Mailbox("server")
    n = 200

    def serve() -> None:
        try:
            while True:
                envelope = mailbox.receive()
                assert isinstance(envelope.message, int)
                envelope.reply(envelope.message * 2)
        except TaskStopped:
            pass

    server = threading.Thread(target=serve, daemon=True)
    server.start()
    results: dict[int, object] = {}
    lock = threading.Lock()

    def client(base: int) -> None:
        for i in range(base, n, 4):
            value = mailbox.send(i, timeout=WAIT)
            with lock:
                results[i] = value

    clients = [threading.Thread(target=client, args=(k,)) for k in range(4)]
    for thread in clients:
        thread.start()
    for thread in clients:
        thread.join(WAIT)
    mailbox.close()
    server.join(WAIT)
    assert not server.is_alive()
    assert results == {i: 2 * i for i in range(n)}


def test_envelope_and_mailbox_repr() -> None:
    @dataclass(frozen=True)
    class NewPoint:
        acq: int

    mailbox = Mailbox("BIRISSERV:")
    mailbox.post(NewPoint(3))
    envelope = mailbox.receive(timeout=WAIT)
    assert isinstance(envelope, Envelope)
    assert isinstance(envelope.message, NewPoint)
    assert envelope.sender == threading.current_thread().name
    assert "NewPoint(acq=3)" in repr(envelope) and "received" in repr(envelope)
    assert "1 held" in repr(mailbox)
    envelope.reply()


# -- one-way posts (an interrupt service routine's NEW_POINT) ------------------------------------


def test_a_oneway_post_is_queued_in_order_and_nobody_waits_for_its_answer(mailbox: Mailbox) -> None:
    first = mailbox.post("CMD_TRANSFER_RDY")
    mailbox.post_oneway("NEW_POINT")  # returns at once: there is nothing to wait on
    last = mailbox.post("BIRIS_CMD_COMPLETE")
    envelopes = [mailbox.receive(timeout=0) for _ in range(3)]
    assert [e.message for e in envelopes] == ["CMD_TRANSFER_RDY", "NEW_POINT", "BIRIS_CMD_COMPLETE"]
    oneway = envelopes[1]
    assert oneway.oneway and not envelopes[0].oneway
    assert not oneway.waiting and envelopes[0].waiting  # received, but nobody is REPLY-blocked
    assert mailbox.held == 3
    assert oneway.reply(None) is False  # answered as any other; the answer goes nowhere
    with pytest.raises(ReplyError):
        oneway.reply(None)
    assert mailbox.held == 2
    for envelope in (envelopes[0], envelopes[2]):
        envelope.reply("ok")
    assert first.wait(0) == last.wait(0) == "ok"


def test_a_refused_oneway_post_is_logged_not_raised(
    mailbox: Mailbox, caplog: pytest.LogCaptureFixture
) -> None:
    mailbox.post_oneway("NEW_POINT")
    with caplog.at_level("DEBUG", logger="biris_hw.ipc"):
        assert mailbox.receive(timeout=0).fail(RequestError("stale")) is False
    assert "stale" in caplog.text and mailbox.held == 0


def test_a_oneway_post_to_a_stopped_task_raises_and_close_releases_queued_ones(
    mailbox: Mailbox,
) -> None:
    mailbox.post_oneway("NEW_POINT")
    received = mailbox.receive(timeout=0)
    mailbox.post_oneway("NEW_POINT 2")
    mailbox.close()
    assert mailbox.queued == 0 and mailbox.held == 0
    assert received.reply(None) is False
    with pytest.raises(TaskStopped):
        mailbox.post_oneway("NEW_POINT 3")


def test_a_oneway_post_rings_a_blocked_receiver() -> None:
    mailbox = Mailbox("server")
    got: list[object] = []
    receiver = threading.Thread(target=lambda: got.append(mailbox.receive(WAIT).message))
    receiver.start()
    mailbox.post_oneway("NEW_POINT")  # whether or not the receiver blocked yet, it gets it
    receiver.join(WAIT)
    assert got == ["NEW_POINT"]


# -- on virtual time -------------------------------------------------------------------------------
# The test's thread is the driver of the domain: time moves only while it waits in it, so every
# instant below is exact. A stall_timeout turns a wait that the domain cannot see (a bare lock)
# into a failure naming who is stuck, instead of a hang.


def virtual(nominal_scale: float = 1.0) -> VirtualTime:
    return VirtualTime(stall_timeout=WAIT, nominal_scale=nominal_scale)


def serve_forever(tb: VirtualTime, mailbox: Mailbox, service_s: float) -> HwThread:
    """A receiver thread of ``tb`` that answers each message with (message, time of reply)
    after ``service_s`` hardware seconds, until the mailbox is closed."""

    def serve() -> None:
        while True:
            try:
                envelope = mailbox.receive()
            except TaskStopped:
                return
            tb.sleep(service_s, what="service")
            envelope.reply((envelope.message, tb.now()))

    thread = tb.Thread(serve, name="server", daemon=True)
    thread.start()
    return thread


def test_a_mailbox_is_bare_unless_its_time_base_is_virtual() -> None:
    assert type(Mailbox("server")) is Mailbox
    assert type(Mailbox("server", ScaledTime(100.0))) is Mailbox
    on_virtual = Mailbox("server", VirtualTime())
    assert isinstance(on_virtual, Mailbox) and type(on_virtual) is not Mailbox


def test_virtual_sends_are_answered_in_hardware_time() -> None:
    tb = virtual()
    mailbox = Mailbox("server", tb)
    server = serve_forever(tb, mailbox, 0.5)
    assert mailbox.send("a", timeout=WAIT) == ("a", 0.5)
    assert mailbox.send("b") == ("b", 1.0)
    tickets = [mailbox.post("c"), mailbox.post("d")]
    mailbox.post_oneway("e")  # answered in turn; nobody waits for that answer
    assert [ticket.wait() for ticket in tickets] == [("c", 1.5), ("d", 2.0)]
    assert mailbox.send("f") == ("f", 3.0)  # after "e"'s service
    mailbox.close()
    assert tb.join_thread(server)  # released by close: no time passes
    assert tb.now() == 3.0 and tb.deadlock is None


def test_many_virtual_senders_each_get_their_own_reply_at_their_turn() -> None:
    tb = virtual()
    mailbox = Mailbox("server", tb)
    server = serve_forever(tb, mailbox, 1.0)
    results: dict[int, object] = {}

    def client(i: int) -> None:
        tb.sleep(0.25 * i)  # they send in this order
        results[i] = mailbox.send(i)

    clients = [tb.Thread(client, name=f"client-{i}", args=(i,), daemon=True) for i in range(4)]
    for thread in clients:
        thread.start()
    for thread in clients:
        assert tb.join_thread(thread)
    mailbox.close()
    assert tb.join_thread(server)
    assert results == {i: (i, 1.0 + i) for i in range(4)}  # served one after another


def test_two_virtual_receivers_each_get_one_of_two_messages() -> None:
    tb = virtual()
    mailbox = Mailbox("server", tb)
    got: list[object] = []

    def receive() -> None:
        envelope = mailbox.receive(timeout=WAIT)
        got.append((envelope.message, tb.now()))
        envelope.reply()

    receivers = [tb.Thread(receive, name=f"receiver-{i}", daemon=True) for i in range(2)]
    for thread in receivers:
        thread.start()
    tb.sleep(1.0)  # returns only once both receivers wait
    assert mailbox.receivers == 2
    tickets = [mailbox.post("a"), mailbox.post("b")]
    assert [ticket.wait() for ticket in tickets] == [None, None]
    for thread in receivers:
        assert tb.join_thread(thread)
    assert sorted(got) == [("a", 1.0), ("b", 1.0)]  # type: ignore[type-var]
    assert mailbox.receivers == 0 and tb.now() == 1.0


def test_a_virtual_send_nobody_answers_times_out_after_exactly_its_timeout() -> None:
    tb = virtual(nominal_scale=10.0)  # a caller's second is 10 hardware seconds
    mailbox = Mailbox("server", tb)
    tb.sleep(1.0 / 3.0)
    t0 = tb.now()
    with pytest.raises(TimeoutError):
        mailbox.send("nobody receives", timeout=0.25)
    assert tb.now() == t0 + tb.timeout_hw(0.25)
    assert mailbox.queued == 0  # withdrawn

    parked: list[Envelope] = []

    def park() -> None:  # receives and never answers
        parked.append(mailbox.receive())

    receiver = tb.Thread(park, name="parker", daemon=True)
    receiver.start()
    t1 = tb.now()
    with pytest.raises(TimeoutError):
        mailbox.send("received, never answered", timeout=0.5)
    assert tb.now() == t1 + tb.timeout_hw(0.5)
    assert tb.join_thread(receiver)
    assert mailbox.held == 0 and parked[0].reply("late") is False

    t2 = tb.now()
    with pytest.raises(TimeoutError):
        mailbox.receive(timeout=0.1)
    assert tb.now() == t2 + tb.timeout_hw(0.1)
    with pytest.raises(TimeoutError):
        mailbox.receive(timeout=0)  # a look: no time passes
    assert tb.now() == t2 + tb.timeout_hw(0.1)


def test_close_releases_virtual_senders_and_receivers_at_the_instant_of_closing() -> None:
    tb = virtual()
    mailbox = Mailbox("server", tb)
    ended: dict[str, tuple[str, float]] = {}
    held: list[Envelope] = []

    def sender() -> None:
        try:
            mailbox.send("x")  # no timeout
        except BaseException as exc:
            ended["sender"] = (type(exc).__name__, tb.now())

    def receiver() -> None:
        held.append(mailbox.receive())  # takes "x": its sender is now REPLY-blocked
        try:
            mailbox.receive()
        except BaseException as exc:
            ended["receiver"] = (type(exc).__name__, tb.now())

    threads = [
        tb.Thread(sender, name="sender", daemon=True),
        tb.Thread(receiver, name="receiver", daemon=True),
    ]
    for thread in threads:
        thread.start()
    tb.sleep(2.0)  # both wait all the while: nothing else is due
    assert (mailbox.queued, mailbox.held, mailbox.receivers) == (0, 1, 1)
    mailbox.close()
    for thread in threads:
        assert tb.join_thread(thread)
    assert ended == {"sender": ("TaskStopped", 2.0), "receiver": ("TaskStopped", 2.0)}
    assert held[0].reply("late") is False


def test_close_with_a_reason_releases_a_virtual_sender_with_it() -> None:
    tb = virtual()
    mailbox = Mailbox("server", tb)
    fault = HardwareFault("bus", "bus error on the BIRIS chassis")
    errors: list[BaseException] = []

    def send() -> None:
        try:
            mailbox.send("x", timeout=WAIT)
        except BaseException as exc:
            errors.append(exc)

    sender = tb.Thread(send, name="sender", daemon=True)
    sender.start()
    tb.sleep(1.0)
    mailbox.close(fault)
    assert tb.join_thread(sender)
    assert errors == [fault] and tb.now() == 1.0


def test_a_virtual_send_nobody_can_receive_is_a_deadlock_not_a_hang() -> None:
    tb = virtual()
    mailbox = Mailbox("server", tb)
    with pytest.raises(VirtualTimeDeadlock, match="reply from 'server'") as info:
        mailbox.send("nobody receives")  # no timeout, and nobody else in the domain
    assert [wait.what for wait in info.value.waits] == ["reply from 'server'"]
    assert mailbox.queued == 0  # taken back: the caller has gone
    with pytest.raises(VirtualTimeDeadlock, match="inbox 'server'"):
        mailbox.receive()
    assert mailbox.receivers == 0 and tb.deadlock is not None


def test_an_interrupted_virtual_wait_withdraws_the_message() -> None:
    tb = virtual()
    mailbox = Mailbox("server", tb)

    def interrupt(_t: float) -> None:  # runs in the driver, which found the domain idle
        raise KeyboardInterrupt

    remove = tb.on_advance(interrupt)
    ticket = mailbox.post("x")
    with pytest.raises(KeyboardInterrupt):
        ticket.wait(1.0)
    assert ticket.done and mailbox.queued == 0
    with pytest.raises(TimeoutError):
        ticket.wait()  # withdrawn: settled for good
    with pytest.raises(KeyboardInterrupt):
        mailbox.receive(timeout=1.0)
    assert mailbox.receivers == 0
    remove()

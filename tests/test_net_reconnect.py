"""Remote clients ride out the network, and end with their process.

A service that cannot be reached -- stopped and restarted, behind a router that is killed and
restarted, across a partition longer than Zenoh's lease -- is a ConnectionLost for the calls
made meanwhile (never a RequestError, never the final ConnectionClosed); once it is back the
client's connections are reopened by themselves, what a reader missed is counted exactly
(the scans' ``seq``), and ``biris watch --connect`` carries on (or, past its bound, fails
naming the span). An unclosed client neither keeps its process alive nor outlives its last
reference.

The services here run on :class:`tests.netns.TickingSensor` (a scan every 20 ms, numbered per
direction), so every scan made is either read, missed or dropped, and the test can count.
Sessions use a short Zenoh lease and quick reconnection (:func:`tests.netns.zenoh_options`).
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import io
import json
import subprocess
import sys
import textwrap
import threading
import time
from collections.abc import Iterator
from typing import Any

import pytest
import zenoh

from biris_hw.data import ConnectionKind, DeliveryPolicy, Direction
from biris_hw.errors import ConnectionClosed, ConnectionLost, RequestError
from biris_hw.io.net import RemoteSensor, Service, connect, remote, serve
from biris_hw.io.net.keys import Keys
from biris_hw.io.net.reconnect import Missed
from biris_hw.io.net.zconfig import make_config
from tests.conftest import WAIT, until
from tests.net_helpers import ROOT, endpoint, free_port, warm_up_zenoh
from tests.netns import (
    Partition,
    Reader,
    TickingSensor,
    accounted,
    make_scan,
    router_process,
    unavailable,
    zenoh_options,
)

BACK_WITHIN_S = 10.0
"""Longest a reader may wait for data once the fault is over: Zenoh's reconnection (every
0.5 s here), the token's return, the reopen. Measured 0.6-1.5 s on loopback; the rest is
room for a loaded host."""

CONTROLLERS = {"op": "pw"}

ENDS_WITHIN_S = 15.0
"""Longest an unclosed client may take to end its process with its link dead: a close request
given up after 1 s, Zenoh's close waited for 2 s at most (its own bound is 10 s), interpreter
shutdown. Measured about 3 s (without the bounds: 11.6 s; before the exit hook: never)."""

LEASE_MS = 1000
"""Zenoh's lease in these tests: a cut link is noticed after about this long (10 s by
default)."""


PAUSE_S = 0.25
"""The pause of a call made while the service is lost, here (1 s by default): a reader's loop
asks again sooner, and a test that waits out a few pauses is quicker."""


@pytest.fixture(scope="module", autouse=True)
def _zenoh_runtime() -> None:
    warm_up_zenoh()


@pytest.fixture(autouse=True)
def _short_pause(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(remote, "LOST_PAUSE_S", PAUSE_S)


@contextlib.contextmanager
def _service(
    where: str, name: str = "rc0", *, connect_to: str | None = None
) -> Iterator[tuple[Service, TickingSensor]]:
    """A service on a ticking sensor, listening on ``where`` (or, with ``connect_to``, a
    client of the router there)."""
    sensor = TickingSensor()
    if connect_to is None:
        serving = serve(
            sensor,  # type: ignore[arg-type]
            name=name,
            listen=[where],
            controllers=CONTROLLERS,
            multicast=False,
            options=zenoh_options(LEASE_MS),
        )
    else:
        serving = serve(
            sensor,  # type: ignore[arg-type]
            name=name,
            connect=[connect_to],
            controllers=CONTROLLERS,
            multicast=False,
            options=zenoh_options(LEASE_MS, "client"),
        )
    with serving as svc:
        sensor.start()
        try:
            yield svc, sensor
        finally:
            sensor.close()


def _connect(where: str, name: str = "rc0", **options: Any) -> RemoteSensor:
    mode = options.pop("mode", None)
    return connect(name, [where], multicast=False, options=zenoh_options(LEASE_MS, mode), **options)


# -- what is counted -----------------------------------------------------------------------------


def test_missed_counts_the_gaps_across_an_outage_and_nothing_else() -> None:
    missed = Missed()
    cw, ccw = Direction.CW, Direction.CCW
    assert missed.saw(make_scan(cw, 1, 0.0), 0) is None
    assert missed.saw(make_scan(cw, 3, 0.0), 0) is None  # no outage: the server's to count
    assert missed.saw(make_scan(ccw, 1, 0.0), 0) is None
    missed.mark(0)
    assert missed.saw(make_scan(cw, 9, 0.0), 0) == (5, "5 cw scans (within seq 4-8)")
    assert missed.saw(make_scan(cw, 11, 0.0), 0) is None  # compared once, after the outage
    assert missed.saw(make_scan(ccw, 2, 0.0), 0) is None  # no gap that way
    missed.mark(2)
    assert missed.saw(make_scan(cw, 15, 0.0), 4) == (1, "1 cw scan (within seq 12-14)")
    missed.mark(4)
    assert missed.saw(make_scan(cw, 1, 0.0), 4) is None  # a sensor that started again
    assert missed.count == 6


# -- what a caller sees --------------------------------------------------------------------------


class _Impostor:
    """A bare Zenoh peer that declares a service's token and queryable and answers only what
    it is told to: the rest is held unanswered, so Zenoh itself answers ``Timeout``."""

    def __init__(self, name: str) -> None:
        self.where = endpoint(free_port())
        self.keys = Keys(name)
        self.answer = False
        self.held: list[zenoh.Query] = []
        self.session = zenoh.open(make_config(listen=[self.where]))
        self.queryable = self.session.declare_queryable(self.keys.rpcs, self._on_query)
        self.token: Any = self.session.liveliness().declare_token(self.keys.service_token)

    def _on_query(self, query: zenoh.Query) -> None:
        if str(query.key_expr).endswith("/status"):  # what a client asks as it connects
            denied = {"error": "AccessDenied", "message": "not for impostors"}
            query.reply_err(json.dumps(denied).encode())
            return
        if not self.answer:
            self.held.append(query)
            return
        body = {"conn": "t" * 22, "ident": 7, "kind": "NORMAL", "policy": "latest", "depth": 1}
        query.reply(str(query.key_expr), json.dumps(body).encode())

    def close(self) -> None:
        self.held.clear()
        self.session.close()  # type: ignore[no-untyped-call]


def test_a_zenoh_timeout_is_connection_lost_never_request_error(
    monkeypatch: pytest.MonkeyPatch, no_leaks: None
) -> None:
    """Zenoh's own ``Timeout`` reply (a partition shorter than the lease) is not the
    service's refusal: ConnectionLost, the outage recorded; the next answer ends it."""
    monkeypatch.setattr(remote, "REPLY_MARGIN_S", 0.2)
    impostor = _Impostor("imp")
    try:
        with connect("imp", [impostor.where], multicast=False) as client:
            with pytest.raises(ConnectionLost, match="Timeout") as caught:
                client.open()
            assert not isinstance(caught.value, RequestError)
            assert client.lost and len(client.outages) == 1
            assert client.outages[0].back_at is None
            impostor.answer = True
            assert client.open().ident == 7
            outage = client.outages[0]
            assert (client.lost, outage.back_at is not None) == (False, True)  # over
    finally:
        impostor.close()


@pytest.mark.parametrize("reconnect", [True, False], ids=["reconnect", "final"])
def test_a_service_whose_token_goes_is_lost_or_gone_as_asked(
    reconnect: bool, no_leaks: None
) -> None:
    """The token withdrawn: ConnectionLost (after at most the pause) while the client expects
    it back; with ``reconnect=False`` the old rule, ConnectionClosed."""
    impostor = _Impostor("imp")
    impostor.answer = True
    try:
        with connect("imp", [impostor.where], multicast=False, reconnect=reconnect) as client:
            conn = client.open()
            impostor.token.undeclare()
            until(lambda: client.gone, what="the token seen to go")
            started = time.monotonic()
            with pytest.raises(ConnectionLost if reconnect else ConnectionClosed):
                conn.stop_scan()
            took = time.monotonic() - started
            if reconnect:  # a call made while it is lost waits the pause for its return
                assert PAUSE_S <= took < PAUSE_S + WAIT
            else:
                assert took < PAUSE_S
            assert client.lost  # either way: it cannot be reached now
            conn.close()  # closed here: final, whatever the link
            with pytest.raises(ConnectionClosed):
                conn.stop_scan()
    finally:
        impostor.close()


# -- a service that restarts ---------------------------------------------------------------------


@pytest.mark.realtime  # the service's sensor scans on its own thread, in real time
def test_a_restarted_service_is_ridden_out_and_its_connections_reopened(no_leaks: None) -> None:
    where = endpoint(free_port())
    with _service(where):
        client = _connect(where, user="op", password="pw")
        reader = Reader(client)
        control = client.open()
        control.stop_scan()
        reader.wait(lambda: reader.count() >= 3, WAIT, "scans")
    try:
        reader.wait(lambda: bool(reader.lost), WAIT, "ConnectionLost")
        with _service(where):
            reader.wait(lambda: bool(reader.again), BACK_WITHIN_S, "scans again")
            control.stop_scan()  # reopened too, and with the controller's credentials
        summary = reader.summary()
        assert summary["wrong"] == [], summary
        assert summary["reopened"] == 1 and control.reopened == 1
        assert client.reopened == 2 and len(client.outages) >= 1
        assert client.restarts == 1  # a new Zenoh session answers: a new instance
        assert summary["missed"] == 0  # its sensor numbers afresh: nothing is known
    finally:
        reader.stop()
        client.close()


# -- a router killed and restarted ---------------------------------------------------------------


@pytest.mark.realtime
def test_a_reader_rides_out_a_router_restart_and_counts_what_it_missed(no_leaks: None) -> None:
    """Service and reader are clients of a router, which is SIGKILLed and, once the service
    has released the reader's connection, started again on the same endpoint."""
    where = endpoint(free_port())
    with router_process(where) as router, _service("", connect_to=where) as (svc, sensor):
        client = _connect(where, mode="client")
        try:
            published: list[int] = []
            subscription = client.subscribe("scan", lambda scan: published.append(scan.seq))
            reader = Reader(client)
            reader.wait(lambda: reader.count() >= 10, WAIT, "scans")
            router.kill()
            reader.wait(lambda: bool(reader.lost), WAIT, "ConnectionLost")
            until(lambda: client.client not in svc.clients(), what="the reader released")
            with router_process(where):
                restarted = time.monotonic()
                reader.wait(lambda: bool(reader.again), BACK_WITHIN_S, "scans again")
                back_s = reader.again[0] - restarted
                heard = len(published)
                until(lambda: len(published) > heard, what="publications again")
                with reader.cond:  # a scan each way after the return, so each gap is closed
                    after = {d: len(reader.got[d]) + 1 for d in Direction}
                reader.wait(
                    lambda: all(len(reader.got[d]) > after[d] for d in Direction),
                    WAIT,
                    "scans both ways",
                )
                sensor.stop()
                with sensor.cond:
                    made = dict(sensor.made)
                reader.wait(
                    lambda: all(r.got[d][-1] == made[d] for r in [reader] for d in Direction),
                    WAIT,
                    "every scan made",
                )
            summary = reader.summary()
            reader.stop()
            assert summary["wrong"] == [], summary  # ConnectionLost only: no RequestError
            assert summary["ordered"] and summary["reopened"] == 1
            assert summary["missed"] > 0 and client.missed == summary["missed"]
            made_between, accounted_for = accounted(summary)
            assert made_between == accounted_for, summary  # read + missed + dropped: all
            assert subscription.dropped > 0  # the publications' counters jumped
            assert back_s < BACK_WITHIN_S
        finally:
            client.close()


# -- a partition -----------------------------------------------------------------------------------


@pytest.mark.slow  # the fast tier keeps a cheaper test of the same (make test-slow runs this)
@pytest.mark.realtime
def test_a_partition_longer_than_the_lease_is_lost_then_data_again() -> None:
    """Service in one network namespace, reader in another, the veth between them taken down
    for longer than the lease (the service releases the reader), then up again."""
    reason = unavailable()
    if reason is not None:
        pytest.skip(reason)
    lease = ["--lease-ms", str(LEASE_MS)]
    with Partition() as net:
        service = net.start(0, ["serve", "--listen", net.endpoint(0), *lease])
        reader = net.start(1, ["read", "--endpoint", net.endpoint(0), *lease])  # waits for it
        service.expect("ready")
        reader.expect("ready")
        cut = time.monotonic()
        net.cut()
        lost = reader.expect_json("lost", WAIT)
        lost_after = time.monotonic() - cut
        service.expect("released", WAIT)  # the lease ran out on the service's side too
        net.mend()
        mended = time.monotonic()
        reader.expect("again", BACK_WITHIN_S)
        back_s = time.monotonic() - mended
        reader.send("quit")
        summary = reader.expect_json("summary")
    assert net.leftovers() == []
    assert "cannot be reached" in lost["message"]
    assert summary["wrong"] == [], summary  # never a RequestError
    assert summary["ordered"] and summary["reopened"] >= 1 and summary["missed"] > 0
    made_between, accounted_for = accounted(summary)
    assert made_between == accounted_for, summary
    assert lost_after < LEASE_MS / 1000 + WAIT
    assert back_s < BACK_WITHIN_S


@pytest.mark.slow  # two processes and a dead link: about 7 s
def test_an_unclosed_client_ends_its_process_across_a_dead_link() -> None:
    """The worst case for leaving: the link is cut without a word (nothing tells either side
    before the lease runs out), and the client never closes; the process still ends."""
    reason = unavailable()
    if reason is not None:
        pytest.skip(reason)
    with Partition() as net:
        service = net.start(0, ["serve", "--listen", net.endpoint(0)])  # Zenoh's 10 s lease
        client = net.start(1, ["linger", "--endpoint", net.endpoint(0)])
        service.expect("ready")
        client.expect("ready")
        net.cut()
        client.send("leave")
        left = time.monotonic()
        assert client.proc.wait(timeout=ENDS_WITHIN_S) == 0
        ended_s = time.monotonic() - left
        service.kill()  # its own close would wait out Zenoh's 10 s for the vanished peer
    assert net.leftovers() == []
    assert ended_s < ENDS_WITHIN_S


# -- biris watch --connect -----------------------------------------------------------------------


class _Stderr(io.StringIO):
    """stderr for a command running on another thread: written there, read here."""

    def __init__(self) -> None:
        super().__init__()
        self.lock = threading.Lock()

    def write(self, text: str) -> int:
        with self.lock:
            return super().write(text)

    def text(self) -> str:
        with self.lock:
            return self.getvalue()


def _watch_args(where: str, *more: str) -> argparse.Namespace:
    from biris_hw.commands import watch

    parser = argparse.ArgumentParser()
    watch.add_arguments(parser)
    args = parser.parse_args(["--connect", "rc0", "--endpoint", where, "--interval", "0.1", *more])
    args.command = "watch"
    return args


@pytest.mark.realtime
def test_watch_connect_carries_on_through_a_service_restart(
    monkeypatch: pytest.MonkeyPatch, no_leaks: None
) -> None:
    from biris_hw.commands import watch

    where = endpoint(free_port())
    err = _Stderr()
    monkeypatch.setattr(sys, "stderr", err)
    out = io.StringIO()
    stop = threading.Event()
    result: list[int] = []
    with _service(where):
        thread = threading.Thread(
            target=lambda: result.append(watch.run(_watch_args(where), out, stop))
        )
        thread.start()
        until(lambda: "state=scanning" in out.getvalue(), what="a status shown")
    try:
        until(lambda: "link to the service is lost" in err.text(), what="the loss said")
        with _service(where):
            until(lambda: "is back after" in err.text(), timeout=BACK_WITHIN_S, what="back")
            stop.set()
            thread.join(WAIT)
    finally:
        stop.set()
        thread.join(WAIT)
    assert result == [0], err.text()


def test_watch_connect_gives_up_past_its_bound_naming_the_span(
    monkeypatch: pytest.MonkeyPatch, no_leaks: None
) -> None:
    from biris_hw.commands import watch

    monkeypatch.setattr(watch, "RIDE_OUT_S", 0.5)
    where = endpoint(free_port())
    err = _Stderr()
    monkeypatch.setattr(sys, "stderr", err)
    out = io.StringIO()
    with _service(where):
        args = _watch_args(where)
        result: list[int] = []
        thread = threading.Thread(target=lambda: result.append(watch.run(args, out)))
        thread.start()
        until(lambda: "state=scanning" in out.getvalue(), what="a status shown")
    thread.join(WAIT)
    assert result == [1], err.text()
    said = err.text()
    assert "could not be reached for" in said and "no status from" in said, said


# -- clients end with their process ------------------------------------------------------------

_UNCLOSED = textwrap.dedent(
    """
    import sys
    from biris_hw.io.net import connect
    r = connect("rc0", [sys.argv[1]], multicast=False)
    r.open()
    print(r.status().state.value, flush=True)
    """
)

EXIT_WITHIN_S = 20.0
"""Longest the script may take, interpreter start and imports included (about 1.5 s measured;
before, it never ended by itself)."""


@pytest.mark.realtime
def test_an_unclosed_client_lets_its_process_end(no_leaks: None) -> None:
    where = endpoint(free_port())
    with _service(where) as (svc, _):
        started = time.monotonic()
        ran = subprocess.run(
            [sys.executable, "-c", _UNCLOSED, where],
            cwd=ROOT,
            capture_output=True,
            text=True,
            timeout=EXIT_WITHIN_S,
        )
        took = time.monotonic() - started
        assert ran.returncode == 0, ran.stderr
        assert ran.stdout.strip() == "scanning"
        until(lambda: svc.clients() == {}, what="the client seen to leave")
    assert took < EXIT_WITHIN_S


@pytest.mark.realtime
def test_an_unclosed_client_is_closed_when_collected(no_leaks: None) -> None:
    """No reference left: the collector closes its session (its Zenoh threads end, which
    ``no_leaks`` checks) and the service releases its connections."""
    where = endpoint(free_port())
    with _service(where) as (svc, _):
        client = _connect(where)
        client.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_BUFFER)
        ident = client.client
        until(lambda: svc.clients().get(ident) == 1, what="the client's connection")
        del client
        gc.collect()
        until(lambda: ident not in svc.clients(), what="the collected client released")

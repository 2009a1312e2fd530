"""The service driven by a client written from ``docs/wire-format.md`` alone.

The client is the page's own: its two Python blocks ("A minimal client"), run as written, with
plain ``zenoh`` and rosbags' CDR decoder fed the definitions of ``ros/biris_msgs/msg``, and
nothing of ``biris_hw.io.net``'s client. Against a recording served on loopback (the sensor
whose data are known, and no clock to wait on: it plays when the first DATA connection opens,
as ``biris serve --replay`` does), these tests hold the page to what it promises a stranger:
the example's output, the reply encodings (JSON ``null`` and CDR told apart by the encoding),
the defaults of ``open`` and of ``timeout``, the status's attachment, the publications'
encoding and counter, the error replies with their ``class``, and Zenoh's own ``Timeout``,
which is not the service's JSON.
"""

from __future__ import annotations

import contextlib
import io
import re
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from biris_hw.data import Scan
from biris_hw.io.net import serve
from biris_hw.io.record import write_scans
from biris_hw.io.record.replay import ReplayServer
from tests.conftest import until
from tests.net_helpers import endpoint, free_port, warm_up_zenoh
from tests.test_record_support import synthetic_scans

ROOT = Path(__file__).resolve().parent.parent
PAGE = ROOT / "docs" / "wire-format.md"
NAME = "stranger"
WAIT = 10.0
SPEED = 100.0


@pytest.fixture(scope="module", autouse=True)
def _zenoh_runtime() -> None:
    warm_up_zenoh()


def _client_blocks() -> tuple[str, str]:
    """The page's client (definitions, then its use), from the section "A minimal client"."""
    section = PAGE.read_text(encoding="utf-8").split("## A minimal client", 1)[1]
    section = section.split("\n## ", 1)[0]
    blocks = re.findall(r"```python\n(.*?)```", section, re.S)
    assert len(blocks) == 2, "the page's client is two Python blocks"
    return blocks[0], blocks[1]


def _aimed(block: str, where: str) -> str:
    """The client's block with its three settings pointed at the service under test."""
    settings = {
        "NAME": repr(NAME),
        "ENDPOINT": repr(where),
        "MSG_DIR": f"Path({str(ROOT / 'ros' / 'biris_msgs' / 'msg')!r})",
    }
    for name, value in settings.items():
        block, found = re.subn(rf"^{name} = .*$", f"{name} = {value}", block, flags=re.M)
        assert found == 1, f"the page's client sets {name} once"
    return block


class Served:
    """A recording of 4 scans served as ``stranger`` on loopback, not playing yet."""

    def __init__(self, where: str, scans: list[Scan], replay: ReplayServer, service: Any):
        self.where = where
        self.scans = scans
        self.replay = replay
        self.service = service


@pytest.fixture
def served(tmp_path: Path) -> Iterator[Served]:
    scans = synthetic_scans(4)
    path = write_scans(tmp_path / "run.mcap", scans)
    where = endpoint(free_port())
    with (
        ReplayServer(path, speed=SPEED, autostart=False) as replay,
        serve(replay, name=NAME, listen=[where], multicast=False, playback=True) as service,
    ):
        yield Served(where, scans, replay, service)


@contextlib.contextmanager
def playing_on_first_data(served: Served) -> Iterator[None]:
    """The recording plays once a client opens a DATA connection, as with ``biris serve
    --replay`` (which starts it on the same event)."""
    done = threading.Event()

    def play() -> None:
        while not done.is_set():
            if served.service.data_opened.wait(0.05):
                served.replay.start()
                return

    player = threading.Thread(target=play, daemon=True)
    player.start()
    try:
        yield
    finally:
        done.set()
        player.join(WAIT)


@pytest.fixture
def client(served: Served) -> Iterator[dict[str, Any]]:
    """The page's first block run: its names (``rpc``, ``decode``, ``session``...)."""
    names: dict[str, Any] = {"__name__": "stranger"}
    exec(compile(_aimed(_client_blocks()[0], served.where), str(PAGE), "exec"), names)
    try:
        yield names
    finally:
        with contextlib.suppress(Exception):  # the example closes them itself
            names["token"].undeclare()
        with contextlib.suppress(Exception):
            names["session"].close()


def test_the_pages_example_runs_as_written(client: dict[str, Any], served: Served) -> None:
    scans = served.scans
    printed = io.StringIO()
    with playing_on_first_data(served), contextlib.redirect_stdout(printed):
        exec(compile(_client_blocks()[1], str(PAGE), "exec"), client)
    state, clock = printed.getvalue().splitlines()[0].split()
    assert state == "idle" and float(clock) == 0.0  # nothing played before the DATA open
    first = scans[0]
    n_acq, samples = first.range_mm.shape
    assert printed.getvalue().splitlines()[1] == (
        f"{int(first.direction)} {n_acq} {samples} dropped so far: 0"
    )


def test_a_stranger_gets_what_the_page_promises(client: dict[str, Any], served: Served) -> None:
    rpc, session = client["rpc"], client["session"]
    service_error, unreachable = client["ServiceError"], client["Unreachable"]
    scans = served.scans

    def refused(op: str, **fields: Any) -> dict[str, Any]:
        """The service's error reply to ``op``: its JSON object."""
        with pytest.raises(service_error) as caught:
            rpc(op, **fields)
        body: dict[str, Any] = caught.value.body
        return body

    # status: a CDR Status, told by its encoding; the clock (and with info, what a client asks
    # once)
    status, info = rpc("status", info=True)
    assert type(status).__name__ == "biris_msgs__msg__Status" and status.state == "idle"
    assert info["playback"] is True and info["clock"] == 0.0

    # open's defaults: NORMAL, latest, the policy's depth; JSON null before the first datum
    opened, _ = rpc("open")
    assert (opened["kind"], opened["policy"], opened["depth"]) == ("NORMAL", "latest", 1)
    normal = opened["conn"]
    assert re.fullmatch(r"[A-Za-z0-9_-]{22}", normal)
    assert rpc("request_point", conn=normal) == (None, None)  # JSON null, not a message
    assert rpc("request_scan_data", conn=normal, direction=0) == (None, None)
    points, _ = rpc("open", kind="DATA", policy="every_acquisition")
    assert points["depth"] == 256
    probe, _ = rpc("open", kind="DATA", policy="every_buffer")
    assert probe["depth"] == 8
    assert refused("ready_for_data", conn=points["conn"], timeout=0)["error"] == "TimeoutError"

    # Zenoh's own error when the query's timeout runs out first: not JSON, not the service's
    client["REPLY_S"] = 0.2
    try:
        with pytest.raises(unreachable, match="Timeout"):
            rpc("ready_for_data", conn=probe["conn"], timeout=None)  # held up to 5 s
    finally:
        client["REPLY_S"] = 5.0

    # publications: the encoding names the type, an 8-byte counter from 1 per key
    heard: list[tuple[str, str, bytes, bytes]] = []
    got_scan = threading.Event()

    def on_sample(sample: Any) -> None:
        key = str(sample.key_expr)
        attachment = sample.attachment.to_bytes() if sample.attachment is not None else b""
        heard.append((key, str(sample.encoding), attachment, sample.payload.to_bytes()))
        if "/scan/" in key:
            got_scan.set()

    subscriber = session.declare_subscriber(f"biris/{NAME}/**", on_sample)
    try:
        data, _ = rpc("open", kind="DATA", policy="every_buffer", depth=16)
        served.replay.start()
        # a timeout left out is null: held (up to 5 s) until a scan comes
        scan, extra = rpc("ready_for_data", held_s=5.0, conn=data["conn"])
        assert extra == {"dropped": 0}
        assert type(scan).__name__ == "biris_msgs__msg__Scan"
        sent = scans[0]
        assert (scan.direction, scan.seq) == (int(sent.direction), sent.seq)
        assert (scan.n_acq, scan.samples) == sent.range_mm.shape
        assert np.array_equal(scan.range_mm.reshape(sent.range_mm.shape), sent.range_mm)
        assert np.array_equal(scan.t, sent.t) and scan.header.frame_id == "biris"
        latest, _ = rpc("request_scan_data", conn=normal, direction=int(sent.direction))
        assert type(latest).__name__ == "biris_msgs__msg__Scan"
        assert got_scan.wait(WAIT)
    finally:
        subscriber.undeclare()
    key, encoding, attachment, payload = next(h for h in heard if "/scan/" in h[0])
    assert key in (f"biris/{NAME}/scan/cw", f"biris/{NAME}/scan/ccw")
    assert encoding == "application/cdr;biris_msgs/msg/Scan"
    assert len(attachment) == 8 and int.from_bytes(attachment, "little") >= 1
    assert client["decode"](payload, encoding).n_acq == scans[0].range_mm.shape[0]

    # the service's error replies: JSON, by error and class
    assert refused("no_such_op")["error"] == "BadRequest"
    assert refused("request_point", conn="short")["error"] == "BadRequest"
    gone = refused("request_point", conn="A" * 22)
    assert (gone["error"], gone["class"]) == ("ConnectionClosed", "UnknownConnection")
    assert refused("open", kind="SIDEWAYS")["error"] == "RequestError"
    assert refused("wait_idle", conn=normal, timeout=-1)["error"] == "RequestError"
    moved = refused("home", conn=normal)  # a recording refuses motion, whoever asks
    assert (moved["error"], moved["class"]) == ("RequestError", "ReplayRefused")
    until(lambda: served.replay.finished, WAIT, "the recording played to its end")
    ended = refused("ready_for_data", conn=points["conn"], timeout=1.0)
    assert (ended["error"], ended["class"]) == ("ConnectionClosed", "EndOfRecording")

    # close: JSON null; the token is then unknown
    assert rpc("close", conn=normal) == (None, None)
    assert refused("request_point", conn=normal)["error"] == "ConnectionClosed"

    # a service nobody serves: the query ends with no reply at all
    client["NAME"] = "nobody"
    try:
        with pytest.raises(unreachable, match="no service"):
            rpc("status", held_s=-4.5)  # a 0.5 s query: nothing will answer anyway
    finally:
        client["NAME"] = NAME


def test_the_page_names_what_the_stranger_relies_on() -> None:
    """What the tests above found is written down where a stranger looks."""
    page = PAGE.read_text(encoding="utf-8")
    for text in (
        "`application/json`",
        "`application/cdr;biris_msgs/msg/<Type>`",
        "`Timeout`",
        '`kind` `"NORMAL"`, `policy` `"latest"`',
        "**connections one client holds** | **32**",
        "ros/biris_msgs",
        "`UnknownConnection`",
    ):
        assert text in page, text

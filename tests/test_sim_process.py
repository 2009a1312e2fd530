"""The simulator as a process (``python -m sim.process``), a driver attached to it from this one,
and the pieces that make that work: the remote window, the slice window, the handshake."""

from __future__ import annotations

import argparse
import contextlib
import errno
import io
import json
import os
import select
import signal
import socket
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Iterator
from multiprocessing import resource_tracker
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from biris_hw import BirisInitRecord, Direction
from biris_hw.bus import open_window
from biris_hw.bus.memory import MemoryWindow
from biris_hw.bus.remote import (
    MAX_PACKET,
    MAX_TRANSFER,
    Handshake,
    Region,
    RemoteLink,
    RemoteWindow,
    SliceWindow,
    default_socket_path,
    refusal,
    serve_request,
)
from biris_hw.errors import BusError
from biris_hw.server import BirisServer
from biris_hw.simlink import attach
from regs.biexec import OFF_STATUS, BiexecCom
from regs.layout import TargetImage, frame_size_for
from sim import process
from tests.conftest import until

WAIT = 30.0
"""Generous real-time bound for anything that takes well under a second."""


@pytest.fixture(scope="module", autouse=True)
def _tracker_running() -> None:
    """Before 3.13 attaching to a segment starts this process's resource tracker, whose pipe
    would otherwise count as a descriptor leaked by the first test that attaches."""
    if sys.version_info < (3, 13):
        resource_tracker.ensure_running()


def _unique(tag: str) -> str:
    return f"biris-test-{tag}-{os.getpid()}-{uuid.uuid4().hex[:8]}"


# -- the simulator process -------------------------------------------------------------------------


class SimProcess:
    """``python -m sim.process`` in a child, up to its ``ready`` line."""

    def __init__(self, name: str, *options: str) -> None:
        self.name = name
        self.socket_path = default_socket_path(name)
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "sim.process", "--shm", name, *options],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
        )

    def wait_ready(self, timeout: float = WAIT) -> str:
        assert self.proc.stdout is not None
        fd = self.proc.stdout.fileno()
        deadline = time.monotonic() + timeout
        got = b""
        while b"\n" not in got:
            remaining = deadline - time.monotonic()
            readable, _, _ = select.select([fd], [], [], max(0.0, remaining))
            if not readable:
                pytest.fail(f"no ready line within {timeout} s")
            chunk = os.read(fd, 4096)
            if not chunk:
                _, err = self.proc.communicate(timeout=WAIT)
                pytest.fail(f"the simulator exited before it was ready: {err.decode()}")
            got += chunk
        return got.decode().splitlines()[0]

    def interrupt(self, timeout: float = WAIT) -> tuple[int, str, str]:
        """Ctrl-C, then (exit status, rest of stdout, stderr)."""
        self.proc.send_signal(signal.SIGINT)
        out, err = self.proc.communicate(timeout=timeout)
        return self.proc.returncode, out.decode(), err.decode()

    def kill(self) -> None:
        """After a failed test: a killed simulator cannot tidy up, so tidy up for it."""
        if self.proc.poll() is not None:
            self.proc.communicate(timeout=WAIT)
            return
        self.proc.kill()
        self.proc.communicate(timeout=WAIT)
        for leftover in (self.socket_path, f"/dev/shm/{self.name}"):
            with contextlib.suppress(FileNotFoundError):
                os.unlink(leftover)


@pytest.fixture
def sim_process(no_leaks: None) -> Iterator[SimProcess]:
    sim = SimProcess(_unique("proc"), "--time-scale", "20", "--scene", "circle:2.0", "--seed", "3")
    try:
        yield sim
    finally:
        sim.kill()


def _dump(name: str) -> dict[str, Any]:
    """``biris regdump --shm NAME --json``, as its CLI half runs it."""
    from biris_hw import regdump

    parser = argparse.ArgumentParser()
    regdump.add_arguments(parser)
    out = io.StringIO()
    assert regdump.run(parser.parse_args(["--shm", name, "--json"]), out) == 0
    data: dict[str, Any] = json.loads(out.getvalue())
    return data


def _azimuth_mirrored_near(name: str, dest: int, timeout: float) -> dict[str, Any]:
    """Poll the register mirror (refreshed every 20 ms) until it shows the head at ``dest``."""
    last: list[dict[str, Any]] = []

    def near() -> bool:
        last[:] = [_dump(name)]
        return abs(last[0]["hctl_azimuth"]["actual_position"]["counts"] - dest) <= 3

    until(near, timeout, f"the mirror to show the azimuth near {dest}")
    return last[0]


def test_a_driver_in_another_process_scans_and_regdump_watches(sim_process: SimProcess) -> None:
    sim = sim_process
    assert sim.wait_ready() == f"ready {sim.name} {sim.socket_path}"
    hw = attach(sim.name, timeout=WAIT)
    try:
        assert hw.time_scale == 20.0
        with BirisServer(hw, BirisInitRecord()) as server:  # homes and boots across processes
            booted = _dump(sim.name)["biexec"]
            assert booted["registers"]["COMMAND"]["value"] == 0
            assert booted["registers"]["STATUS"]["value"] == 0
            assert booted["PARAM"]["text"] == str(frame_size_for(64))  # last boot answer

            conn = server.open()
            # across processes the interrupts come later than a server that has seen no scan
            # allows for; it learns the start delay from each scan (README "What a scan covers"),
            # so the scan judged here is the second
            start = conn.single_scan(-30.0)
            conn.wait_idle(timeout=WAIT)
            standing_before = server.status()["counters"]["constant_azimuth"]
            dest = conn.single_scan(30.0)
            conn.wait_idle(timeout=WAIT)
            scan = conn.request_scan_data(Direction.CCW)
            assert scan is not None and scan.dropped == 0
            if scan.partial:  # a host too loaded for the processes' latency: cut, and marked
                assert scan.partial_reason and scan.span == (start, dest)
            else:
                assert scan.n_acq > 0
                valid = scan.range_mm[scan.range_mm > 0]
                assert valid.size > 0.9 * scan.range_mm.size
                assert np.all(np.abs(valid.astype(np.int64) - 2000) < 200)
                step = (dest - start) / scan.n_acq  # within 1.5 acquisitions of the destination
                assert abs(int(scan.azimuth[-1]) - dest) <= 1.5 * step

            with pytest.raises(BusError, match="already has a driver attached") as refused:
                attach(sim.name, timeout=WAIT)
            assert refused.value.errno == errno.EBUSY

            dump = _azimuth_mirrored_near(sim.name, dest, timeout=WAIT)
            standing = (
                server.status()["counters"]["constant_azimuth"] - standing_before
            )  # BIRIS made them too
            assert dump["biexec"]["PARAM"]["text"] == str(scan.n_acq + standing)
            assert dump["biexec"]["registers"]["ACQ_LINE"]["value"] == -128
            assert abs(dump["frames"]["last_frame"]["closest_mm"] - 2000) < 200
            assert dump["coupler"]["connected"] is True
    finally:
        hw.close()

    # The place is free again at once, and the first driver's hang-up left no stray interrupt.
    again = attach(sim.name, timeout=WAIT)
    try:
        assert again.level2.wait(0) == 0 and again.level3.wait(0) == 0
        assert again.clock() == pytest.approx(hw.clock(), abs=1.0)
    finally:
        again.close()

    status, out, err = sim.interrupt()
    assert status == 0, err
    assert "Traceback" not in err
    assert "audit clean" in err, err
    assert out == ""
    assert not os.path.exists(f"/dev/shm/{sim.name}")
    assert not os.path.exists(sim.socket_path)


def test_a_simulator_refuses_a_name_or_socket_in_use(
    sim_process: SimProcess, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    sim = sim_process
    sim.wait_ready()
    assert process.main(["--shm", _unique("other"), "--socket", sim.socket_path]) == 2
    assert "in use: another simulator is listening" in capsys.readouterr().err
    other_socket = str(tmp_path / "other.sock")
    assert process.main(["--shm", sim.name, "--socket", other_socket]) == 2
    assert f"shared memory {sim.name!r} already exists" in capsys.readouterr().err
    assert not os.path.exists(other_socket)
    status, _, err = sim.interrupt()
    assert status == 0, err


def test_duration_ends_the_simulator_and_cleans_up(
    no_leaks: None, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    name, path = _unique("dur"), str(tmp_path / "sim.sock")
    status = process.main(["--shm", name, "--socket", path, "--duration", "0.2"])
    assert status == 0
    captured = capsys.readouterr()
    assert captured.out == f"ready {name} {path}\n"
    assert "audit clean" in captured.err
    assert not os.path.exists(f"/dev/shm/{name}") and not os.path.exists(path)


def test_a_stale_socket_file_is_taken_over(
    no_leaks: None, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = str(tmp_path / "stale.sock")
    with socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET) as dead:
        dead.bind(path)  # bound, never listening: what a killed simulator leaves
    name = _unique("stale")
    assert process.main(["--shm", name, "--socket", path, "--duration", "0.05"]) == 0
    assert not os.path.exists(path)
    capsys.readouterr()


# -- attach errors ---------------------------------------------------------------------------------


def test_attach_without_a_simulator(no_leaks: None, tmp_path: Path) -> None:
    with pytest.raises(BusError, match="biris sim --shm nobody") as exc:
        attach("nobody", socket_path=str(tmp_path / "none.sock"), timeout=1.0)
    assert exc.value.errno == errno.ENOENT


class FakeSimulator:
    """Accepts one connection and sends ``packet`` (with ``fds``), to test the driver's checks."""

    def __init__(self, path: str, packet: bytes, fds: list[int]) -> None:
        self.listener = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        self.listener.bind(path)
        self.listener.listen(1)
        self.thread = threading.Thread(target=self._serve, args=(packet, fds))
        self.thread.start()

    def _serve(self, packet: bytes, fds: list[int]) -> None:
        conn, _ = self.listener.accept()
        with conn:
            socket.send_fds(conn, [packet], fds)
            conn.recv(16)  # until the driver hangs up

    def close(self) -> None:
        self.thread.join(timeout=WAIT)
        self.listener.close()


def _handshake(shm: str, **changes: Any) -> Handshake:
    image = TargetImage()
    values: dict[str, Any] = {
        "shm": shm,
        "pid": 1,
        "time_scale": 1.0,
        "t0": 0.0,
        "samples": 64,
        "biris_base": image.biris.biris_base,
        "biexec_offset": image.biris.biexec_offset,
        "range_offset": image.biris.range_offset,
        "max_acquisitions": image.biris.max_acquisitions,
        "image_size": image.size,
        "coupler_offset": image.coupler.offset,
        "coupler_size": image.coupler.size,
        "motion_offset": image.motion.offset,
        "motion_size": image.motion.size,
        "biris_offset": image.biris_region.offset,
        "biris_size": image.biris_region.size,
    }
    values.update(changes)
    return Handshake(**values)


@pytest.mark.parametrize(
    ("packet", "n_fds", "match", "code"),
    [
        (b'{"protocol": "slit-sim/9"}', 0, "handshake mismatch: the peer speaks", errno.EPROTO),
        (refusal("busy, go away"), 0, "refused: busy, go away", errno.EBUSY),
        (_handshake("someone-else").encode(), 2, "serves shared memory", errno.EPROTO),
        (_handshake("me", motion_size=0x80).encode(), 2, "sizes", errno.EPROTO),
        (_handshake("me").encode(), 1, "descriptor", errno.EPROTO),
        (_handshake("me").encode(), 2, "no segment of that name", errno.ENOENT),
    ],
    ids=["protocol", "refused", "name", "layout", "fds", "no-segment"],
)
def test_attach_refuses_a_mismatched_simulator(
    no_leaks: None, tmp_path: Path, packet: bytes, n_fds: int, match: str, code: int
) -> None:
    path = str(tmp_path / "fake.sock")
    lines = [os.eventfd(0, os.EFD_CLOEXEC) for _ in range(n_fds)]
    fake = FakeSimulator(path, packet, lines)
    try:
        with pytest.raises(BusError, match=match) as exc:
            attach("me", socket_path=path, timeout=WAIT)
        assert exc.value.errno == code
    finally:
        fake.close()
        for fd in lines:
            os.close(fd)


def test_handshake_round_trip_and_type_checks() -> None:
    hello = _handshake("x", t0=12.5, time_scale=20)
    assert Handshake.decode(hello.encode()) == hello
    broken = json.loads(hello.encode())
    broken["samples"] = "64"
    with pytest.raises(BusError, match="'samples' has the wrong type"):
        Handshake.decode(json.dumps(broken).encode())
    del broken["samples"]
    with pytest.raises(BusError, match="no 'samples'"):
        Handshake.decode(json.dumps(broken).encode())
    with pytest.raises(BusError, match="did not send JSON"):
        Handshake.decode(b"\xff")


# -- the remote window against an in-process server -----------------------------------------------


class WindowServer:
    """The serving half of the protocol over a socket pair, on a thread, for a memory window."""

    def __init__(self, window: MemoryWindow, *, mute: bool = False) -> None:
        self.window = window
        self.client, self._end = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        self.requests = 0
        self.received = threading.Event()
        self._mute = mute
        self._thread = threading.Thread(target=self._run)
        self._thread.start()

    def _run(self) -> None:
        while True:
            try:
                packet = self._end.recv(MAX_PACKET)
            except OSError:
                return
            if not packet:
                return
            self.requests += 1
            self.received.set()
            if not self._mute:
                self._end.send(serve_request(packet, {Region.MOTION: self.window}))

    def hang_up(self) -> None:
        """The simulator goes away."""
        self._end.shutdown(socket.SHUT_RDWR)
        self._thread.join(timeout=WAIT)
        self._end.close()

    def close(self) -> None:
        self.client.close()
        self._thread.join(timeout=WAIT)
        self._end.close()


@pytest.fixture
def served(no_leaks: None) -> Iterator[tuple[WindowServer, RemoteLink]]:
    server = WindowServer(MemoryWindow(0x2000))
    link = RemoteLink(server.client, timeout=WAIT)
    try:
        yield server, link
    finally:
        link.close()
        server.close()


def test_remote_window_round_trips(served: tuple[WindowServer, RemoteLink]) -> None:
    server, link = served
    window = open_window("remote", link=link, region="motion", size=0x2000)
    assert isinstance(window, RemoteWindow) and window.kind == "remote"
    window.write8(0x14, 0xAB)
    assert server.window.read8(0x14) == 0xAB
    window.write32(0x20, 0x12345678)
    assert window.read16(0x22) == 0x5678 and window.read32(0x20) == 0x12345678
    big = bytes(range(256)) * 24  # more than one request's worth
    assert len(big) > MAX_TRANSFER
    before = server.requests
    window.write(0x100, big)
    assert server.requests - before == 2
    assert window.read(0x100, len(big)) == big
    before = server.requests
    with pytest.raises(BusError, match="outside"):
        window.read8(0x2000)  # refused here, never sent
    with pytest.raises(BusError, match="misaligned"):
        window.read16(0x21)
    assert server.requests == before
    window.close()
    with pytest.raises(BusError, match="closed"):
        window.read8(0)


def test_remote_window_reports_the_devices_refusal(
    served: tuple[WindowServer, RemoteLink],
) -> None:
    _, link = served
    too_big = RemoteWindow(link, Region.MOTION, 0x4000)  # larger than the device behind it
    with pytest.raises(BusError, match=r"motion: .*outside") as exc:
        too_big.read8(0x3000)
    assert exc.value.errno == errno.EIO
    assert too_big.read8(0x10) == 0  # the link survives a refused access
    absent = RemoteWindow(link, Region.COUPLER, 0x20)
    with pytest.raises(BusError, match="no region 2") as exc:
        absent.read8(0)
    assert exc.value.errno == errno.ENXIO


def test_lost_connection_is_a_bus_error(served: tuple[WindowServer, RemoteLink]) -> None:
    server, link = served
    window = RemoteWindow(link, Region.MOTION, 0x100)
    window.write8(1, 7)
    server.hang_up()
    with pytest.raises(BusError, match="connection lost") as exc:
        window.read8(1)
    assert exc.value.errno == errno.ECONNRESET
    with pytest.raises(BusError, match="connection lost"):  # and stays lost
        window.write8(1, 8)


def test_a_silent_simulator_times_out(no_leaks: None) -> None:
    server = WindowServer(MemoryWindow(0x100), mute=True)
    link = RemoteLink(server.client, timeout=0.2)
    try:
        window = RemoteWindow(link, Region.MOTION, 0x100)
        with pytest.raises(BusError, match="no reply within") as exc:
            window.read8(0)
        assert exc.value.errno == errno.ETIMEDOUT
        with pytest.raises(BusError, match="no reply within"):
            window.read8(0)  # a late reply could be mistaken for the next one: stay broken
    finally:
        link.close()
        server.close()


def test_closing_the_link_wakes_a_blocked_access(no_leaks: None) -> None:
    server = WindowServer(MemoryWindow(0x100), mute=True)
    link = RemoteLink(server.client, timeout=WAIT)
    window = RemoteWindow(link, Region.MOTION, 0x100)
    errors: list[BaseException] = []

    def access() -> None:
        try:
            window.read8(0)
        except BusError as exc:
            errors.append(exc)

    reader = threading.Thread(target=access)
    reader.start()
    assert server.received.wait(WAIT)  # the request is on the wire, its reply never comes
    link.close()
    reader.join(timeout=WAIT)
    server.close()
    assert not reader.is_alive() and len(errors) == 1
    assert "closed" in str(errors[0])


# -- the slice window ------------------------------------------------------------------------------


def test_slice_window_forwards_at_width_and_owns_its_parent() -> None:
    parent = MemoryWindow(0x100)
    part = SliceWindow(parent, 0x40, 0x20)
    part.write16(0x2, 0xBEEF)
    assert parent.read16(0x42) == 0xBEEF
    part.write(0x1E, b"\x01\x02")
    assert parent.read(0x5E, 2) == b"\x01\x02"
    with pytest.raises(BusError, match="outside"):
        part.read8(0x20)
    with pytest.raises(BusError, match="does not fit"):
        SliceWindow(parent, 0xF0, 0x20)
    with pytest.raises(BusError, match="aligned"):
        SliceWindow(parent, 0x2, 0x10)
    part.close()
    assert parent.closed


def test_slice_window_views_are_the_parents() -> None:
    parent = MemoryWindow(0x1000)
    part = SliceWindow(parent, 0x100, 0x200)
    com = part.view(BiexecCom, 0x10)
    com.STATUS = -3
    assert parent.read16(0x110 + OFF_STATUS) == 0xFFFD
    kept = SliceWindow(parent, 0x0, 0x10, owns_parent=False)
    kept.close()
    assert not parent.closed
    part.close()
    with pytest.raises(BusError, match="closed"):
        _ = com.STATUS

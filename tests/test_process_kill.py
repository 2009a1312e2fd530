"""Killing processes (issue 11): ``biris sim`` killed under a driver, and a driver killed under
``biris sim``, with SIGKILL, mid-scan.

(a) The simulator process dies during continuous scanning while this process's server has
    callers blocked (LATEST and EVERY_ACQUISITION DATA clients, a ``wait_idle``): every one of
    them gets ``HardwareFault("bus")`` within a bound, the state reads ``fault:bus``, a reset
    says ``bus`` too (the link is gone, not the motor or the firmware), and closing leaves no
    thread behind.

(b) A driver process dies during a 720 degree scan, so the simulator runs on: the chip finishes
    its profile (the head ends a revolution from true zero) and BIRIS its long BI_ACQUIRE. A new
    driver process then attaches at once: it must wait for the busy BIRIS before its first
    command (no CMD_WHILE_BUSY), find TRUE zero although the head stands a revolution round
    (from the pan journal both processes keep in ``$BIRIS_STATE_DIR``), and scan. Across
    processes the true head is out of sight, so the proof is the simulator's own audit, printed
    at its exit: a zero one revolution off would send the +-90 degree scans into a mechanical
    stop (HEAD_BEYOND_LIMIT, and a motor_stall fault in the driver).

Every simulator gets a unique shared-memory name and a socket in the test's temporary
directory (loopback only); whatever a killed process leaves is removed in ``finally``.

This file is also the driver program of (b): ``python tests/test_process_kill.py driver NAME
SOCKET MODE`` (see :func:`_driver_main`).
"""

from __future__ import annotations

import contextlib
import json
import os
import select
import signal
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from biris_hw import BirisInitRecord, ConnectionKind, DeliveryPolicy, Direction
from biris_hw.errors import HardwareFault
from biris_hw.pan_reference import JOURNAL_ENV
from biris_hw.server import BirisServer
from biris_hw.simlink import attach
from regs.biexec import OFF_COMMAND
from tests.conftest import until
from tests.test_relink import needs_relink_first

ROOT = Path(__file__).resolve().parent.parent

WAIT = 30.0
"""Real seconds for anything that takes a few at most; reached only when a test fails."""

TOLD_WALL_S = 2.0
"""Real seconds from the simulator's death to every blocked caller holding HardwareFault("bus"):
the socket's hang-up wakes the interrupt lines at once (measured in milliseconds)."""


# -- processes -------------------------------------------------------------------------------------


def _biris() -> list[str]:
    """The ``biris`` command of this environment (its console script, else the module)."""
    script = Path(sys.executable).with_name("biris")
    if script.exists():
        return [str(script)]
    return [sys.executable, "-c", "import sys; from biris_hw.cli import main; sys.exit(main())"]


class Process:
    """A child process whose stdout is read line by line, bounded."""

    def __init__(self, argv: list[str], env: dict[str, str], *, stdin: bool = False) -> None:
        self.proc = subprocess.Popen(
            argv,
            stdin=subprocess.PIPE if stdin else None,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            env=env,
            cwd=ROOT,
        )
        self.lines: list[str] = []
        self._buffer = b""

    def wait_for(self, prefix: str, timeout: float = WAIT) -> str:
        """The first stdout line that starts with ``prefix``; fails the test after ``timeout``."""
        assert self.proc.stdout is not None
        fd = self.proc.stdout.fileno()
        deadline = time.monotonic() + timeout
        while True:
            for line in self.lines:
                if line.startswith(prefix):
                    return line
            left = deadline - time.monotonic()
            readable, _, _ = select.select([fd], [], [], max(0.0, left))
            if not readable:
                self.kill()
                pytest.fail(f"no {prefix!r} line within {timeout:g} s; got {self.lines}")
            chunk = os.read(fd, 65536)
            if not chunk:
                err = self.finish()[1]
                pytest.fail(f"{self.proc.args!r} exited before {prefix!r}: {self.lines}\n{err}")
            self._buffer += chunk
            *done, self._buffer = self._buffer.split(b"\n")
            self.lines.extend(line.decode() for line in done)

    def tell(self, line: str) -> None:
        """Write ``line`` to the process's stdin (made with ``stdin=True``)."""
        assert self.proc.stdin is not None
        self.proc.stdin.write(line.encode() + b"\n")
        self.proc.stdin.flush()

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGKILL)

    def finish(self, timeout: float = WAIT) -> tuple[int, str]:
        """Wait for the exit; (status, stderr). Stdout lines are added to :attr:`lines`."""
        try:
            out, err = self.proc.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.kill()
            out, err = self.proc.communicate(timeout=WAIT)
        text = (self._buffer + out).decode()
        self._buffer = b""
        self.lines.extend(line for line in text.splitlines() if line)
        return self.proc.returncode, err.decode()


class Simulator(Process):
    """``biris sim`` on a unique shared-memory name and a socket of the test's own (or the
    ``name`` of one that was killed: started again in its place)."""

    def __init__(
        self,
        tmp: Path,
        env: dict[str, str],
        time_scale: float,
        *,
        name: str | None = None,
        samples: int = 64,
    ) -> None:
        self.name = name or f"biris-test-kill-{os.getpid()}-{uuid.uuid4().hex[:8]}"
        self.socket = str(tmp / "sim.sock")
        super().__init__(
            [
                *_biris(),
                *("sim", "--shm", self.name, "--socket", self.socket, "--samples", str(samples)),
                *("--time-scale", f"{time_scale:g}", "--scene", "circle:2.0", "--seed", "3"),
            ],
            env,
        )
        try:
            self.wait_for("ready")
        except BaseException:
            self.tidy()
            raise

    def stop(self) -> tuple[int, str]:
        """Ctrl-C: the simulator reports its audit on stderr and tidies up."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
        return self.finish()

    def tidy(self) -> None:
        """Reap it and remove what a killed simulator could not."""
        self.kill()
        self.finish()
        for leftover in (self.socket, f"/dev/shm/{self.name}"):
            with contextlib.suppress(FileNotFoundError):
                os.unlink(leftover)


@pytest.fixture
def env(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> dict[str, str]:
    """Children's environment: the pan journal in the test's own state directory (this process
    uses the same one), the checkout importable."""
    state = tmp_path / "state"
    state.mkdir()
    monkeypatch.setenv(JOURNAL_ENV, str(state))
    out = dict(os.environ)
    out["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), out.get("PYTHONPATH")]))
    return out


@pytest.fixture(scope="module", autouse=True)
def _tracker_running() -> None:
    """Before 3.13, attaching to a segment starts this process's resource tracker, whose pipe
    would otherwise count as a descriptor leaked by the first test that attaches."""
    if sys.version_info < (3, 13):
        from multiprocessing import resource_tracker

        resource_tracker.ensure_running()


# -- (a) the simulator killed under a driver -----------------------------------------------------


class Blocked:
    """A call that blocks in the server, in a thread: once, or in a loop until it raises."""

    def __init__(self, name: str, call: Callable[[], object], loop: bool) -> None:
        self.name = name
        self.calls = 0
        self.error: BaseException | None = None
        self.at = 0.0
        self._call = call
        self._loop = loop
        self._thread = threading.Thread(target=self._run, name=f"blocked-{name}", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        try:
            while True:
                self._call()
                self.calls += 1
                if not self._loop:
                    break
        except BaseException as exc:
            self.error = exc
        self.at = time.monotonic()

    def join(self) -> None:
        self._thread.join(WAIT)
        assert not self._thread.is_alive(), f"{self.name} is still blocked"


@pytest.mark.slow
def test_a_killed_simulator_is_a_bus_fault_for_every_caller(
    no_leaks: None, tmp_path: Path, env: dict[str, str]
) -> None:
    sim = Simulator(tmp_path, env, time_scale=20.0)
    threads_before = set(threading.enumerate())
    try:
        hw = attach(sim.name, socket_path=sim.socket, timeout=WAIT)
        try:
            with BirisServer(hw, BirisInitRecord()) as server:
                conn = server.open()
                latest = server.open(ConnectionKind.DATA)
                points = server.open(
                    ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_ACQUISITION, depth=4096
                )
                waiter = server.open()
                conn.continuous_scan(-90.0, 90.0)
                callers = [
                    Blocked("latest", lambda: latest.ready_for_data(timeout=WAIT), loop=True),
                    Blocked("points", lambda: points.ready_for_data(timeout=WAIT), loop=True),
                    Blocked("wait_idle", lambda: waiter.wait_idle(timeout=WAIT), loop=False),
                ]
                first = callers[0]  # a whole sweep delivered: scanning for sure
                until(lambda: first.calls >= 1 or first.error is not None, WAIT, "a sweep")
                assert first.error is None, first.error

                killed = time.monotonic()
                sim.kill()
                told: dict[str, float] = {}
                for caller in callers:
                    caller.join()
                    assert isinstance(caller.error, HardwareFault), (caller.name, caller.error)
                    assert caller.error.kind == "bus", (caller.name, caller.error)
                    told[caller.name] = caller.at - killed
                assert max(told.values()) <= TOLD_WALL_S, told
                print(f"simulator killed: callers told after {told} s")

                assert server.status()["state"] == "fault:bus"
                with pytest.raises(HardwareFault) as later:
                    conn.request_point()
                assert later.value.kind == "bus"
                with pytest.raises(HardwareFault) as reset:
                    conn.reset()
                assert reset.value.kind == "bus", reset.value
                assert server.status()["state"] == "fault:bus"
        finally:
            hw.close()
        rc, err = sim.finish()
        assert rc == -signal.SIGKILL, (rc, err)
    finally:
        sim.tidy()
    # no thread of the server, the bundle or the callers is left once closed (the no_leaks
    # fixture checks threads and descriptors again at teardown)
    left = [t for t in threading.enumerate() if t not in threads_before and t.is_alive()]
    assert left == [], left


def _segment_gone(name: str) -> None:
    """Wait for a killed simulator's segment to go (its resource tracker unlinks it as the
    process's end closes its pipe), bounded; then remove it as an operator would."""
    path = f"/dev/shm/{name}"
    with contextlib.suppress(AssertionError):
        until(lambda: not os.path.exists(path), WAIT / 3, "the killed simulator's segment")
    with contextlib.suppress(FileNotFoundError):
        os.unlink(path)


@pytest.mark.slow
@needs_relink_first
def test_a_restarted_simulator_is_found_again_by_one_reset(
    no_leaks: None, tmp_path: Path, env: dict[str, str]
) -> None:
    """(a) again, then the simulator is started again under the same name (issue 24): a reset
    while it is gone says so; once it runs, one reset reconnects the same bundle (new socket,
    eventfds and segment, same objects), homes afresh on the new plant and scans; the new
    simulator's audit is clean. Started again as another target, it is refused: only a new
    driver process can use it."""
    sim = Simulator(tmp_path, env, time_scale=10.0)
    hw = attach(sim.name, socket_path=sim.socket, timeout=WAIT)
    try:
        with BirisServer(hw, BirisInitRecord()) as server:
            conn = server.open()
            conn.single_scan(30.0)
            conn.wait_idle(timeout=WAIT)
            sim.kill()
            assert sim.finish()[0] == -signal.SIGKILL
            until(lambda: server.status().fault is not None, WAIT, "the bus fault")
            with pytest.raises(HardwareFault) as gone:
                conn.reset()
            assert gone.value.kind == "bus"
            assert "still gone" in gone.value.message and "connection lost" in gone.value.message

            _segment_gone(sim.name)
            sim = Simulator(tmp_path, env, time_scale=10.0, name=sim.name)
            conn.reset()
            assert server.status().fault is None
            assert getattr(hw, "relinks", None) == 1
            conn.single_scan(-30.0)
            conn.wait_idle(timeout=WAIT)
            assert server.status().fault is None
            rc, err = sim.stop()  # Ctrl-C: the new plant's audit (a wrong zero would show)
            assert rc == 0 and "audit clean" in err, err

            sim = Simulator(tmp_path, env, time_scale=10.0, name=sim.name, samples=128)
            with pytest.raises(HardwareFault) as other:
                conn.reset()
            assert other.value.kind == "bus"
            assert "another target" in other.value.message
            assert "new driver process" in other.value.message
    finally:
        hw.close()
        sim.tidy()


# -- (b) a driver killed under the simulator -----------------------------------------------------


def _driver(sim: Simulator, env: dict[str, str], mode: str) -> Process:
    """A driver process; ``check`` is started ahead and attaches when told (``go``)."""
    argv = [sys.executable, __file__, "driver", sim.name, sim.socket, mode]
    return Process(argv, env, stdin=mode == "check")


@pytest.mark.slow
def test_a_driver_killed_mid_scan_is_replaced_safely(
    no_leaks: None, tmp_path: Path, env: dict[str, str]
) -> None:
    # x2: the dead driver's 720 degree BI_ACQUIRE (5.8 s of hardware time) still runs for about
    # 2.5 s after SCANNING. The new driver is started first and waits, imported, until told to
    # attach: a Python process's start-up (seconds on a loaded host) is not in that window
    sim = Simulator(tmp_path, env, time_scale=2.0)
    old: Process | None = None
    new: Process | None = None
    try:
        new = _driver(sim, env, "check")
        new.wait_for("READY", timeout=60.0)
        old = _driver(sim, env, "longscan")
        old.wait_for("SCANNING", timeout=60.0)
        old.kill()
        assert old.finish()[0] == -signal.SIGKILL

        new.tell("go")
        line = new.wait_for("RESULT", timeout=90.0)
        rc, err = new.finish()
        result = json.loads(line.removeprefix("RESULT "))
        sim_rc, sim_err = sim.stop()  # its audit, whatever the new driver said
        audit = [line for line in sim_err.splitlines() if "audit" in line]
        print(f"new driver: {result}; simulator: {audit}")

        assert rc == 0, (result, err)
        assert result["busy_at_attach"] != 0, (
            "BIRIS had finished the dead driver's command before the new driver attached: the "
            f"test did not test what it says ({result})"
        )
        assert audit == ["biris sim: audit clean"], audit
        assert result["error"] is None, result
        assert result["state"] == "idle", result
        assert all(n > 0 for n in result["n_acq"]), result
        assert result["sweeps"] >= 2, result
        assert sim_rc == 0, sim_err
    finally:
        for proc in (old, new):
            if proc is not None:
                proc.kill()
                proc.finish()
        sim.tidy()


# -- the driver program of (b) ---------------------------------------------------------------------


def _driver_main(name: str, socket_path: str, mode: str) -> int:
    """``longscan``: initialise, scan to -360 degrees, start the 720 degree scan to +360, print
    SCANNING and wait to be killed. ``check``: print READY, wait for a line on stdin, then note
    whether BIRIS is busy, initialise (timed), scan +-90 degrees and two sweeps of +-30, print
    one ``RESULT {json}`` line."""
    if mode == "check":
        print("READY", flush=True)
        sys.stdin.readline()
    hw = attach(name, socket_path=socket_path, timeout=WAIT)
    result: dict[str, Any] = {"error": None}
    try:
        result["busy_at_attach"] = hw.biris.read16(hw.biexec_offset + OFF_COMMAND)
        started = time.monotonic()
        with BirisServer(hw, BirisInitRecord()) as server:
            result["init_s"] = round(time.monotonic() - started, 2)
            conn = server.open()
            if mode == "longscan":
                conn.single_scan(-360.0)
                conn.wait_idle(timeout=WAIT)
                conn.single_scan(360.0)
                moving, deadline = threading.Event(), time.monotonic() + WAIT
                while (server.status().azimuth_live or -4096) < -3000:  # under way, for sure
                    assert time.monotonic() < deadline, "the 720 degree scan never started"
                    moving.wait(0.01)
                print("SCANNING", flush=True)
                moving.wait()
            result["n_acq"] = []
            try:
                for to, way in ((90.0, Direction.CCW), (-90.0, Direction.CW)):
                    conn.single_scan(to)
                    conn.wait_idle(timeout=WAIT)
                    scan = conn.request_scan_data(way)
                    result["n_acq"].append(0 if scan is None else scan.n_acq)
                data = server.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_BUFFER)
                conn.continuous_scan(-30.0, 30.0)
                result["sweeps"] = 0
                for _ in range(2):
                    data.ready_for_data(timeout=WAIT)
                    result["sweeps"] += 1
                conn.stop_scan()
                conn.wait_idle(timeout=WAIT)
            except Exception as exc:
                result["error"] = f"{type(exc).__name__}: {exc}"
            result["state"] = server.status()["state"]
    finally:
        hw.close()
    print("RESULT " + json.dumps(result), flush=True)
    return 0


def _main(argv: list[str]) -> int:
    if len(argv) == 4 and argv[0] == "driver":
        return _driver_main(*argv[1:])
    print(f"usage: {Path(__file__).name} driver NAME SOCKET longscan|check", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(_main(sys.argv[1:]))

"""``biris sim --shm NAME``: the simulator as a process of its own, reached like a real target.

A driver in another process then sees what it would see on the robot: BIRIS memory in a shared
memory segment (the coupler's window), the boards' registers with every side effect (over a Unix
socket, see :mod:`biris_hw.bus.remote`), and interrupt levels 2 and 3 as eventfds it polls
(passed with ``SCM_RIGHTS``). ``biris_hw.simlink.attach(NAME)`` builds that driver's hardware.

The segment holds a whole :class:`~regs.layout.TargetImage`. BIRIS memory in it is the simulator's
own; the coupler and board areas are a *mirror*, refreshed from the models' side-effect-free
snapshots every 20 ms, so ``biris regdump --shm NAME`` can watch live registers without latching
an HCTL-1000 or clearing a status bit under the driver's feet.

One driver at a time, as on the robot: a second connection is told why and closed. The main
thread serves the socket; SIGINT and SIGTERM only wake it, so Ctrl-C tears everything down in
order (socket, mirror, simulator, segment) and exits 0.

Its time scale defaults to every other command's (:data:`~biris_hw.commands.argtypes.
DEFAULT_TIME_SCALE`), and a scale this host cannot keep up with is said once on stderr
(:meth:`SimulatedBiris.lag_s <sim.rig.SimulatedBiris.lag_s>`), not silently used.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import select
import signal
import socket
import stat
import struct
import sys
import threading
import time
import traceback
from collections.abc import Callable, Iterator, Sequence
from multiprocessing.shared_memory import SharedMemory
from types import FrameType
from typing import Any

from biris_hw.bus.base import BusWindow
from biris_hw.bus.remote import (
    MAX_PACKET,
    Handshake,
    Region,
    default_socket_path,
    refusal,
    serve_request,
)
from biris_hw.commands.argtypes import (
    DEFAULT_TIME_SCALE,
    add_simulator_arguments,
    seconds,
    time_scale_warning,
)
from biris_hw.errors import BirisError
from biris_hw.pan_reference import default_journal_path, forget_journal
from regs.layout import BirisMemoryMap, ImageRegion, TargetImage
from sim.rig import SimulatedBiris
from sim.scene import Scene

__all__ = ["MIRROR_PERIOD", "SimProcessError", "add_arguments", "main", "run"]

MIRROR_PERIOD = 0.02
"""Real seconds between two copies of the board and coupler registers into the image."""

_SEND_TIMEOUT = 5.0
"""A driver that stops reading its replies is dropped after this long, not waited for."""


class SimProcessError(BirisError):
    """The simulator cannot serve as asked (name or socket taken, bad option); one line says why."""


# -- options ---------------------------------------------------------------------------------------


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The ``sim`` options (the caller owns the parser)."""
    parser.add_argument(
        "--shm", required=True, metavar="NAME", help="name of the shared-memory segment to create"
    )
    parser.add_argument(
        "--socket", metavar="PATH", default=None, help="Unix socket (default /tmp/biris-NAME.sock)"
    )
    add_simulator_arguments(parser, default_time_scale=DEFAULT_TIME_SCALE)
    parser.add_argument(
        "--duration", type=seconds, default=None, metavar="S",
        help="exit after S real seconds (default: until Ctrl-C)",
    )  # fmt: skip


# -- the shared-memory image -----------------------------------------------------------------------


class _Segment:
    """The image's segment, owned: created here, unlinked on close whatever else fails."""

    def __init__(self, name: str, size: int) -> None:
        try:
            self._shm = SharedMemory(name=name, create=True, size=size)
        except FileExistsError:
            raise SimProcessError(
                f"shared memory {name!r} already exists: another simulator serves it, or one "
                f"was killed (remove /dev/shm/{name.lstrip('/')})"
            ) from None
        except (OSError, ValueError) as exc:
            why = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
            raise SimProcessError(f"creating shared memory {name!r}: {why}") from None
        self._slices: list[memoryview] = []

    @property
    def name(self) -> str:
        return self._shm.name

    def write(self, offset: int, data: bytes) -> None:
        buf = self._shm.buf
        assert buf is not None
        buf[offset : offset + len(data)] = data

    def region(self, region: ImageRegion) -> memoryview:
        """A view of one area, valid until :meth:`close` (which releases it)."""
        buf = self._shm.buf
        assert buf is not None
        view = buf[region.offset : region.end]
        self._slices.append(view)
        return view

    def close(self) -> None:
        try:
            for view in self._slices:
                view.release()
            self._shm.close()
        except BufferError:
            pass  # something still points into the segment: the mapping goes with the process
        finally:
            self._shm.unlink()


# -- the register mirror ---------------------------------------------------------------------------


class _Mirror:
    """Copies the board's and the coupler's registers into the image, side-effect free.

    Being the one thread of the process that wakes regularly anyway, it also watches whether
    the simulator keeps up with its time scale, and says so once (``warn``) if it does not.
    """

    def __init__(
        self,
        rig: SimulatedBiris,
        segment: _Segment,
        image: TargetImage,
        period: float,
        warn: Callable[[str], None] | None = None,
    ) -> None:
        self._rig = rig
        self._segment = segment
        self._image = image
        self._period = period
        self._warn = warn
        self._warned = False
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="biris-sim-mirror", daemon=True)
        self.failure: BaseException | None = None

    def copy(self) -> None:
        self._segment.write(self._image.motion_offset, self._rig.board.snapshot())
        self._segment.write(self._image.coupler_offset, self._rig.coupler.snapshot())

    def start(self) -> None:
        self.copy()
        self._thread.start()

    def _run(self) -> None:
        try:
            while not self._stop.wait(self._period):
                self.copy()
                self._check_lag()
        except BaseException as exc:  # reported at exit; the drivers keep their socket
            self.failure = exc

    def _check_lag(self) -> None:
        if self._warned or self._warn is None or not self._rig.behind():
            return
        self._warned = True
        rig = self._rig
        self._warn(time_scale_warning(rig.lag_s(), rig.lag_bound_s, rig.time_scale))

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join()


# -- the driver socket -----------------------------------------------------------------------------


def _peer_pid(sock: socket.socket) -> int:
    try:
        creds = sock.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, struct.calcsize("3i"))
    except OSError:
        return 0
    return int(struct.unpack("3i", creds)[0])


def _listen(path: str) -> socket.socket:
    """Bind ``path``, taking over a stale socket file but never a live simulator's."""
    try:
        mode = os.lstat(path).st_mode
    except FileNotFoundError:
        pass
    else:
        if not stat.S_ISSOCK(mode):
            raise SimProcessError(f"{path} exists and is not a socket")
        probe = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET | socket.SOCK_CLOEXEC)
        try:
            probe.connect(path)
        except OSError:
            os.unlink(path)  # nobody listens: left by a simulator that was killed
        else:
            raise SimProcessError(f"{path} is in use: another simulator is listening there")
        finally:
            probe.close()
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET | socket.SOCK_CLOEXEC)
    try:
        listener.bind(path)
        listener.listen(2)
    except OSError as exc:
        listener.close()
        raise SimProcessError(f"listening on {path}: {exc.strerror or exc}") from None
    return listener


class _DriverPort:
    """The socket a driver attaches to: one driver at a time, served from the main thread."""

    def __init__(
        self,
        listener: socket.socket,
        rig: SimulatedBiris,
        handshake: Handshake,
        stop_fd: int,
        log: Callable[[str], None],
    ) -> None:
        self._listener = listener
        self._rig = rig
        self._handshake = handshake.encode()
        self._name = handshake.shm
        self._stop_fd = stop_fd
        self._log = log
        motion = rig.hardware.motion
        if motion is None:
            raise ValueError("a rig whose axes are CAN drives has no motion window to serve")
        self._windows: dict[Region, BusWindow] = {
            Region.MOTION: motion,
            Region.COUPLER: rig.hardware.coupler,
        }
        self._client: socket.socket | None = None
        self._client_pid = 0
        self._poller = select.poll()

    def serve(self, deadline: float | None) -> None:
        """Until the stop descriptor is written (a signal) or ``deadline`` (monotonic) passes."""
        self._poller.register(self._stop_fd, select.POLLIN)
        self._poller.register(self._listener, select.POLLIN)
        while True:
            if deadline is None:
                timeout_ms = None
            else:
                left = deadline - time.monotonic()
                if left <= 0.0:
                    return
                timeout_ms = int(left * 1000.0 + 0.999)
            client = self._client
            for fd, _ in self._poller.poll(timeout_ms):
                if fd == self._stop_fd:
                    return
                if fd == self._listener.fileno():
                    self._accept()
                elif client is not None and client is self._client and fd == client.fileno():
                    # (an accept may have replaced the driver, and its socket taken the number)
                    self._serve_client()

    def _accept(self) -> None:
        try:
            conn, _ = self._listener.accept()
        except OSError:
            return  # the peer gave up before we accepted
        conn.settimeout(_SEND_TIMEOUT)
        pid = _peer_pid(conn)
        if not self._client_gone():
            message = (
                f"simulator {self._name!r} already has a driver attached "
                f"(pid {self._client_pid}); one driver at a time"
            )
            with contextlib.suppress(OSError):
                conn.send(refusal(message))
            conn.close()
            self._log(f"refused a second driver (pid {pid})")
            return
        self._drain_lines()
        lines = (self._rig.hardware.level2.fileno(), self._rig.hardware.level3.fileno())
        try:
            socket.send_fds(conn, [self._handshake], list(lines))
        except OSError as exc:
            conn.close()
            self._log(f"handshake with pid {pid} failed: {exc.strerror or exc}")
            return
        self._client, self._client_pid = conn, pid
        self._poller.register(conn, select.POLLIN)
        self._log(f"driver attached (pid {pid})")

    def _client_gone(self) -> bool:
        """Serve what the present driver has sent; True once it has hung up (or there is none).

        A driver that closes and attaches again at once has its hang-up and its new connection
        arrive together; the hang-up must be seen first, or the driver would be refused its own
        place.
        """
        while self._client is not None:
            probe = select.poll()
            probe.register(self._client, select.POLLIN)
            if not probe.poll(0) or not self._serve_client():
                return self._client is None
        return True

    def _serve_client(self) -> bool:
        """Answer one request, or drop a driver that hung up; False if there was nothing."""
        client = self._client
        assert client is not None
        try:
            packet = client.recv(MAX_PACKET, socket.MSG_DONTWAIT)
            if packet:
                client.send(serve_request(packet, self._windows))
                return True
        except BlockingIOError:
            return False
        except OSError:
            pass
        self._drop_client()
        return True

    def _drop_client(self) -> None:
        client, self._client = self._client, None
        if client is None:
            return
        self._poller.unregister(client)
        client.close()
        # The driver's lines were dups of ours: closing them woke pollers by writing to the
        # shared counters. Those wakes are not interrupts; the next driver must not see them.
        self._drain_lines()
        self._log(f"driver detached (pid {self._client_pid})")

    def _drain_lines(self) -> None:
        for line in (self._rig.hardware.level2, self._rig.hardware.level3):
            with contextlib.suppress(BlockingIOError):
                os.eventfd_read(line.fileno())

    def close(self) -> None:
        self._drop_client()


# -- the process -----------------------------------------------------------------------------------


def _handshake(name: str, rig: SimulatedBiris, image: TargetImage) -> Handshake:
    mm = image.biris
    return Handshake(
        shm=name,
        pid=os.getpid(),
        time_scale=rig.clock.time_scale,
        t0=rig.clock.t0,
        samples=mm.samples,
        biris_base=mm.biris_base,
        biexec_offset=mm.biexec_offset,
        range_offset=mm.range_offset,
        max_acquisitions=mm.max_acquisitions,
        image_size=image.size,
        coupler_offset=image.coupler.offset,
        coupler_size=image.coupler.size,
        motion_offset=image.motion.offset,
        motion_size=image.motion.size,
        biris_offset=image.biris_region.offset,
        biris_size=image.biris_region.size,
    )


def _log(text: str) -> None:
    print(f"biris sim: {text}", file=sys.stderr, flush=True)


@contextlib.contextmanager
def _socket_file(path: str) -> Iterator[socket.socket]:
    listener = _listen(path)
    try:
        yield listener
    finally:
        listener.close()
        with contextlib.suppress(FileNotFoundError):
            os.unlink(path)


def _serve(args: argparse.Namespace, stop_fd: int) -> int:
    image = TargetImage(biris=BirisMemoryMap(samples=args.samples))
    path = args.socket if args.socket is not None else default_socket_path(args.shm)
    deadline = None if args.duration is None else time.monotonic() + args.duration
    with contextlib.ExitStack() as stack:
        # Unwound in reverse: driver dropped, mirror stopped, simulator closed, segment
        # unlinked, socket file removed.
        listener = stack.enter_context(_socket_file(path))
        segment = _Segment(args.shm, image.size)
        stack.callback(segment.close)
        # a new plant wakes within half a revolution of true zero: what a driver journalled
        # about the previous simulator of this name no longer holds
        forget_journal(default_journal_path(f"sim-{args.shm}"))
        rig = SimulatedBiris(
            Scene.from_spec(args.scene),
            samples=args.samples,
            time_scale=args.time_scale,
            seed=args.seed,
            biris_buffer=segment.region(image.biris_region),
        )
        stack.callback(rig.close)
        rig.start()
        mirror = _Mirror(rig, segment, image, MIRROR_PERIOD, warn=_log)
        mirror.start()
        stack.callback(mirror.stop)
        port = _DriverPort(listener, rig, _handshake(segment.name, rig, image), stop_fd, _log)
        stack.callback(port.close)
        print(f"ready {segment.name} {path}", flush=True)
        port.serve(deadline)
        _log("stopping")
        status = _report(rig, mirror)
    return status


def _report(rig: SimulatedBiris, mirror: _Mirror) -> int:
    """What a driver broke, and whether the simulator itself failed (exit status 1)."""
    violations = rig.audit.violations
    for violation in violations:
        _log(f"audit: {violation}")
    if not violations:
        _log("audit clean")
    failures = [f for f in (rig.supervisor.failure, mirror.failure) if f is not None]
    for failure in failures:
        _log(f"internal failure: {failure!r}")
    return 1 if failures else 0


def _wake_on_signals(stop_fd: int) -> dict[int, Any]:
    """SIGINT/SIGTERM write ``stop_fd``; nothing else runs in a handler (no lock is taken there,
    so a signal can never deadlock with the thread it interrupts)."""

    def wake(signum: int, frame: FrameType | None) -> None:
        os.eventfd_write(stop_fd, 1)

    previous: dict[int, Any] = {}
    if threading.current_thread() is threading.main_thread():
        for signum in (signal.SIGINT, signal.SIGTERM):
            previous[signum] = signal.signal(signum, wake)
    return previous


def run(args: argparse.Namespace) -> int:
    """Run ``biris sim``: 0 after Ctrl-C or ``--duration``, 2 with one line on stderr when it
    cannot start, 1 if the simulator failed while running."""
    stop_fd = os.eventfd(0, os.EFD_CLOEXEC | os.EFD_NONBLOCK)
    previous = _wake_on_signals(stop_fd)
    try:
        return _serve(args, stop_fd)
    except KeyboardInterrupt:  # a signal before our handlers were in place
        return 0
    except (BirisError, OSError, ValueError) as exc:
        if getattr(args, "debug", False):
            traceback.print_exc(file=sys.stderr)
        message = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        _log(message)
        return 2
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
        os.close(stop_fd)


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m sim.process --shm NAME ...`` (what ``biris sim`` runs)."""
    parser = argparse.ArgumentParser(
        prog="biris sim", description="Run the BIRIS simulator as a process drivers attach to."
    )
    add_arguments(parser)
    parser.add_argument("--debug", action="store_true", help="show tracebacks")
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help, or a usage error already reported
        return exc.code if isinstance(exc.code, int) else 2
    return run(args)


if __name__ == "__main__":
    sys.exit(main())

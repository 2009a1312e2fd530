"""Attach to a simulator running as its own process (``biris sim --shm NAME``).

The result is an ordinary :class:`~biris_hw.hardware.BirisHardware`, built the way a real target's
is: BIRIS memory is a window onto shared memory (as the coupler's window is onto VME), the boards
are reached through windows whose accesses reach the devices (here over a Unix socket), the
interrupt levels are descriptors the driver polls (eventfds received with ``SCM_RIGHTS``), and
the clock is the target's. A driver cannot tell it from an in-process rig except by speed.

**A simulator that dies is a bus fault, whether or not a register is being read.** The eventfds
stay valid in this process after the simulator has gone; they simply never fire again. So each
interrupt line of the bundle (:class:`LinkedLine`) also watches the socket to the simulator for
its hang-up, and its ``wait()`` then raises :class:`BusError`. The server's interrupt service
routine polls that line, so it is woken by the hang-up itself, and the supervisor reports a
``bus`` fault. Detection bound: as soon as the kernel has closed the dead process's end of the
socket. That is part of the process's exit, so it is no timer and no polling period; measured in
``tests/test_lost_target.py``. A simulator that hangs without dying keeps its socket open. A
register access then fails after the link's ``timeout`` (a bus fault too), and a hung BIRIS
stops answering commands (the BIRIS timeout).

**A simulator that is started again is found again by a reset.** The server's reset re-links its
hardware bundle first (:meth:`RemoteHardware.relink`): when the simulator has gone, it connects
to the socket again and, if a simulator of the same target answers (the handshake's layout and
time scale equal the first one's), carries on with it through the same objects -- the link gets
the new socket, each line the new eventfd, the BIRIS window the new segment. The new process
starts a new plant whose head wakes within half a revolution of zero (it forgets the pan
journal), so the pan reference is dropped and homing searches afresh. A simulator that is still
gone, or one of another target (other samples, another time scale), leaves the reset failing
with a ``bus`` fault that says so; for the second, only a new driver process (a new
:func:`attach`) can use it.
"""

from __future__ import annotations

import array
import contextlib
import errno
import logging
import os
import select
import socket
import threading
import time
from dataclasses import dataclass, field, fields

from biris_hw.bus.base import BusWindow
from biris_hw.bus.registry import open_window
from biris_hw.bus.remote import (
    LINE_NAMES,
    MAX_PACKET,
    Handshake,
    Region,
    RemoteLink,
    RemoteWindow,
    SliceWindow,
    default_socket_path,
)
from biris_hw.errors import BusError, HardwareFault
from biris_hw.hardware import BirisHardware
from biris_hw.irq.eventfd import EventFdLine
from biris_hw.pan_reference import default_journal_path
from regs.bit3 import BIT3_SPACE
from regs.layout import BirisMemoryMap, TargetImage
from regs.tech80 import MOTION_WINDOW_SIZE

__all__ = ["LinkedLine", "RemoteHardware", "SimulatorClock", "attach", "default_socket_path"]

log = logging.getLogger(__name__)


@dataclass
class RemoteHardware(BirisHardware):
    """A bundle whose boards are reached over ``link``; :meth:`close` also closes the link.

    The link is closed last, after the lines and windows, so the simulator sees the driver go
    only once it has let go of everything. :meth:`relink` reconnects to a simulator that was
    started again under the same name (module notes).
    """

    link: RemoteLink | None = field(default=None, repr=False, compare=False)
    handshake: Handshake | None = field(default=None, repr=False, compare=False)
    name: str = ""
    """The shared-memory name the simulator serves (``biris sim --shm NAME``)."""
    socket_path: str = ""
    """Where the simulator listens."""
    link_timeout: float = 10.0
    """What :func:`attach` was given: bounds a reconnection as it bounded the first."""
    relinks: int = field(default=0, init=False, compare=False)
    """How many times :meth:`relink` reconnected to a restarted simulator."""

    def relink(self) -> None:
        """Reconnect to the simulator if it has gone and is back (see the module notes); at
        once while the link is alive.

        Raises:
            HardwareFault: ``bus``: the simulator is still gone (start it again with ``biris
                sim --shm NAME``, then reset), or it came back as another target (then only a
                new driver process can use it).
        """
        link, hello = self.link, self.handshake
        if link is None or hello is None or not self._lost(link):
            super().relink()
            return
        try:
            self._reconnect(link, hello)
        except BusError as exc:
            raise HardwareFault("bus", str(exc)) from exc
        super().relink()

    def _lost(self, link: RemoteLink) -> bool:
        """The link broke, or a line saw the simulator hang up (nothing was read since)."""
        if link.broken is not None:
            return True
        return any(isinstance(line, LinkedLine) and line.hung_up() for line in self._lines())

    def _lines(self) -> tuple[object, object]:
        return (self.level2, self.level3)

    def _reconnect(self, link: RemoteLink, old: Handshake) -> None:
        """Connect again, check that it is the same target, and hand every object its new
        descriptor; on any failure nothing is changed (the bundle stays lost)."""
        name, path = self.name, self.socket_path
        what = f"simulator {name!r}"
        lost = link.broken or "connection lost (the simulator went away)"
        link.drop_connection()  # a simulator still running (hung) sees this driver go
        fds: list[int] = []
        with contextlib.ExitStack() as undo:
            try:
                sock = _connect(path, name, self.link_timeout)
                undo.callback(sock.close)
                # a process being killed may still accept on its socket, then drop the
                # connection before its handshake: that simulator is gone as well
                raw, fds = _receive(sock, path, self.link_timeout)
            except BusError as exc:
                if exc.errno == errno.EPROTO:
                    raise
                raise BusError(
                    f"{what} is still gone ({lost}): {exc}; once it runs again, reset",
                    exc.errno or errno.ENOENT,
                ) from None
            undo.callback(_close_fds, fds)
            hello = Handshake.decode(raw)
            _check(hello, name, path, len(fds))
            changed = _target_changes(old, hello)
            if changed:
                raise BusError(
                    f"{what} came back as another target ({changed}): this driver cannot carry "
                    f"on with it; start a new driver process (or attach to it anew)",
                    errno.EPROTO,
                )
            biris = _open_biris(hello)
            undo.callback(biris.close)
            lines = [self.level2, self.level3]
            if not all(isinstance(line, LinkedLine) for line in lines) or not isinstance(
                self.biris, SliceWindow
            ):
                raise BusError(f"{what}: this bundle's lines or BIRIS window cannot be re-linked")
            undo.pop_all()
        # committed: from here every object is handed its new descriptor
        for line, fd in zip(lines, fds, strict=True):
            assert isinstance(line, LinkedLine)
            line.relink(fd, sock)
        old_socket = link.reconnect(sock)
        old_socket.close()
        assert isinstance(self.biris, SliceWindow) and isinstance(biris, SliceWindow)
        old_segment = self.biris.replace_parent(biris.parent)
        with contextlib.suppress(BusError):
            old_segment.close()  # the dead simulator's segment, unlinked by its end
        self.handshake = hello
        self.relinks += 1
        if hello.pid != old.pid:
            # a new process starts a new plant and forgets the pan journal (sim.process)
            self.pan_reference.lose(
                f"{what} was started again (pid {old.pid} -> {hello.pid}): its head woke "
                "within half a revolution of zero, so homing searches afresh"
            )
        log.warning("%s: reconnected (pid %d); the reset initialises it", what, hello.pid)

    def close(self) -> None:
        try:
            super().close()
        finally:
            if self.link is not None:
                self.link.close()


_HANG_UP = select.EPOLLHUP | select.EPOLLRDHUP | select.EPOLLERR


class LinkedLine(EventFdLine):
    """An interrupt line of a target reached over a socket: its eventfd, and the socket's life.

    ``fd`` is the eventfd the simulator passed. The line adopts it, even if the constructor
    fails: it is closed either way, and the caller must not close it again. ``peer`` is the
    socket to the simulator, which stays the link's: the line keeps its own duplicate of it,
    watched only for hang-up (a pending reply never wakes it). Both are in one epoll set, whose
    descriptor is :meth:`fileno`. A thread that polls the line (the interrupt service routine)
    is therefore woken by an interrupt *or* by the simulator's end. Interrupts raised before
    the end are still delivered. After that, every ``wait()`` raises :class:`BusError`
    (``ECONNRESET``) until the line is closed: a lost simulator never comes back on the same
    descriptors, so the line stays broken.

    The hang-up shows as soon as the kernel closes the simulator's end of the socket. That
    happens when the process exits or is killed, and when its owner shuts the link down.
    """

    kind = "linked-eventfd"

    def __init__(self, fd: int, peer: socket.socket, label: str = "simulator") -> None:
        self._label = label
        self._swap = threading.Lock()
        """Held while the descriptors are looked at or swapped (:meth:`relink`)."""
        self._peer_fd = -1
        self._epoll: select.epoll | None = None
        try:
            super().__init__(fd)
        except BaseException:
            os.close(fd)
            raise
        try:
            self._peer_fd = os.dup(peer.fileno())  # close-on-exec, as every dup in Python
            self._epoll = select.epoll()
            self._epoll.register(fd, select.EPOLLIN)
            self._epoll.register(self._peer_fd, select.EPOLLRDHUP)
        except BaseException:
            self.close()  # releases the eventfd, the duplicate and the epoll set
            raise

    def _line_fd(self) -> int:
        assert self._epoll is not None
        return self._epoll.fileno()

    def _consume(self) -> int:
        with self._swap:
            count = super()._consume()
            if count:
                return count
            if self._hung_up():
                raise BusError(
                    f"{self._label}: connection lost (the simulator went away)", errno.ECONNRESET
                )
            return 0

    def _hung_up(self) -> bool:
        """Whether the socket has been hung up; a look, never a wait."""
        assert self._epoll is not None
        return any(fd == self._peer_fd and events & _HANG_UP for fd, events in self._epoll.poll(0))

    def hung_up(self) -> bool:
        """Whether the simulator at the other end has gone (its socket hung up); a look."""
        with self._swap:
            if self.closed or self._epoll is None:
                return False
            try:
                return self._hung_up()
            except (OSError, ValueError):  # released meanwhile (closed)
                return False

    def relink(self, fd: int, peer: socket.socket) -> None:
        """Carry on with a restarted simulator: ``fd`` its new eventfd (adopted, as by the
        constructor) and ``peer`` the new socket to it. The descriptor that threads poll
        (:meth:`fileno`, the epoll set) stays the same, so a waiter blocked across the swap
        simply sees the new simulator's interrupts and hang-up from then on."""
        with self._swap:
            try:
                peer_fd = os.dup(peer.fileno())
            except BaseException:
                os.close(fd)
                raise
            with self._lock:
                if self._closed or self._epoll is None:
                    os.close(fd)
                    os.close(peer_fd)
                    raise BusError(f"{self._label}: the line is closed")
                epoll = self._epoll
                old_fd, old_peer = self._fd, self._peer_fd
                epoll.unregister(old_fd)
                epoll.unregister(old_peer)
                epoll.register(fd, select.EPOLLIN)
                epoll.register(peer_fd, select.EPOLLRDHUP)
                self._fd, self._peer_fd = fd, peer_fd
            os.close(old_fd)
            os.close(old_peer)

    def _release_line(self) -> None:
        try:
            if self._epoll is not None:
                self._epoll.close()
            if self._peer_fd >= 0:
                os.close(self._peer_fd)
        finally:
            super()._release_line()


class SimulatorClock:
    """The simulator's hardware clock, computed here: CLOCK_MONOTONIC is shared by every process,
    so ``(monotonic() - t0) * scale`` reads the same in both, with no round trip."""

    def __init__(self, t0: float, time_scale: float) -> None:
        self.t0 = t0
        self.time_scale = time_scale

    def __call__(self) -> float:
        return (time.monotonic() - self.t0) * self.time_scale

    def __repr__(self) -> str:
        return f"SimulatorClock(t0={self.t0!r}, time_scale={self.time_scale!r})"


def attach(name: str, *, socket_path: str | None = None, timeout: float = 10.0) -> BirisHardware:
    """Connect to the simulator serving shared memory ``name`` and return its hardware bundle.

    ``socket_path`` defaults to ``/tmp/biris-NAME.sock``; ``timeout`` bounds the connection, the
    handshake and every later register round trip. The caller closes the bundle.

    Raises:
        BusError: no simulator at the socket (``ENOENT``/``ECONNREFUSED``), the simulator
            refused us because another driver is attached (``EBUSY``), a handshake that does
            not match this driver (``EPROTO``), or no such shared-memory segment (``ENOENT``).
    """
    path = socket_path if socket_path is not None else default_socket_path(name)
    sock = _connect(path, name, timeout)
    fds: list[int] = []
    with contextlib.ExitStack() as undo:
        undo.callback(sock.close)
        raw, fds = _receive(sock, path, timeout)
        undo.callback(_close_fds, fds)
        hello = Handshake.decode(raw)
        _check(hello, name, path, len(fds))
        undo.pop_all()
    try:
        return _assemble(hello, sock, fds, timeout, name=name, path=path)
    except BaseException:
        sock.close()
        raise


def _connect(path: str, name: str, timeout: float) -> socket.socket:
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET | socket.SOCK_CLOEXEC)
    sock.settimeout(timeout)
    try:
        sock.connect(path)
    except (FileNotFoundError, ConnectionRefusedError) as exc:
        sock.close()
        raise BusError(
            f"no simulator at {path} ({exc.strerror}); start one with `biris sim --shm {name}`",
            exc.errno or errno.ENOENT,
        ) from None
    except OSError as exc:
        sock.close()
        raise BusError(
            f"connecting to {path}: {exc.strerror or exc}", exc.errno or errno.EIO
        ) from None
    return sock


def _receive(sock: socket.socket, path: str, timeout: float) -> tuple[bytes, list[int]]:
    """The handshake packet and the descriptors that came with it (close-on-exec here)."""
    fds = array.array("i")
    space = socket.CMSG_SPACE(len(LINE_NAMES) * fds.itemsize)
    try:
        raw, ancillary, flags, _ = sock.recvmsg(MAX_PACKET, space, socket.MSG_CMSG_CLOEXEC)
    except TimeoutError:
        raise BusError(
            f"handshake: {path} sent nothing within {timeout:g} s", errno.ETIMEDOUT
        ) from None
    except OSError as exc:
        raise BusError(f"handshake: {exc.strerror or exc}", exc.errno or errno.EIO) from None
    for level, kind, data in ancillary:
        if level == socket.SOL_SOCKET and kind == socket.SCM_RIGHTS:
            fds.frombytes(data[: len(data) - len(data) % fds.itemsize])
    got = list(fds)
    if flags & (socket.MSG_TRUNC | socket.MSG_CTRUNC):
        _close_fds(got)
        raise BusError("handshake mismatch: the packet or its descriptors were cut", errno.EPROTO)
    if not raw:
        _close_fds(got)
        raise BusError(f"handshake: {path} closed the connection at once", errno.ECONNRESET)
    return raw, got


def _close_fds(fds: list[int]) -> None:
    for fd in fds:
        with contextlib.suppress(OSError):
            os.close(fd)


def _check(hello: Handshake, name: str, path: str, n_fds: int) -> None:
    """Refuse a simulator whose idea of the target differs from this driver's."""

    def mismatch(what: str) -> BusError:
        return BusError(f"handshake mismatch with {path}: {what}", errno.EPROTO)

    if hello.shm.lstrip("/") != name.lstrip("/"):
        raise mismatch(f"it serves shared memory {hello.shm!r}, not {name!r}")
    if tuple(hello.lines) != LINE_NAMES or n_fds != len(LINE_NAMES):
        raise mismatch(f"lines {list(hello.lines)} with {n_fds} descriptor(s)")
    if hello.clock != "CLOCK_MONOTONIC" or "CLOCK_MONOTONIC" not in _monotonic_kind():
        raise mismatch(f"its clock is {hello.clock}, ours is {_monotonic_kind()}")
    if not hello.time_scale > 0.0:
        raise mismatch(f"time scale {hello.time_scale}")
    try:
        image = TargetImage(
            hello.coupler_offset,
            hello.motion_offset,
            hello.biris_offset,
            BirisMemoryMap(
                samples=hello.samples,
                biris_base=hello.biris_base,
                biexec_offset=hello.biexec_offset,
                range_offset=hello.range_offset,
                max_acquisitions=hello.max_acquisitions,
            ),
        )
    except ValueError as exc:
        raise mismatch(f"bad layout ({exc})") from None
    ours = (image.size, BIT3_SPACE, MOTION_WINDOW_SIZE, image.biris.size)
    theirs = (hello.image_size, hello.coupler_size, hello.motion_size, hello.biris_size)
    if ours != theirs:
        raise mismatch(f"sizes (image, coupler, motion, BIRIS) {theirs}, expected {ours}")


def _monotonic_kind() -> str:
    return time.get_clock_info("monotonic").implementation


_SAME_EACH_START = ("shm", "lines", "clock", "protocol")
"""Handshake fields :func:`_check` holds to this driver already."""
_NEW_EACH_START = ("pid", "t0")
"""Handshake fields a restarted simulator changes without being another target."""


def _target_changes(old: Handshake, new: Handshake) -> str:
    """What makes ``new`` another target than ``old`` (layout, samples, time scale), as words;
    empty when it is the same target restarted."""
    skip = _SAME_EACH_START + _NEW_EACH_START
    diffs = [
        f"{f.name} {getattr(new, f.name)!r}, was {getattr(old, f.name)!r}"
        for f in fields(Handshake)
        if f.name not in skip and getattr(new, f.name) != getattr(old, f.name)
    ]
    return "; ".join(diffs)


def _assemble(
    hello: Handshake,
    sock: socket.socket,
    fds: list[int],
    timeout: float,
    *,
    name: str = "",
    path: str = "",
) -> RemoteHardware:
    """Adopt the descriptors, open the windows; on any failure release what was taken."""
    with contextlib.ExitStack() as undo:
        lines: list[EventFdLine] = []
        pending = list(fds)
        undo.callback(_close_fds, pending)
        for fd in fds:
            pending.remove(fd)  # the line adopts it, even if it cannot be made
            line = LinkedLine(fd, sock, f"simulator {hello.shm!r}")
            undo.callback(line.close)
            lines.append(line)
        biris = _open_biris(hello)
        undo.callback(biris.close)
        link = RemoteLink(sock, timeout=timeout, label=f"simulator {hello.shm!r}")
        undo.callback(link.close)
        motion = RemoteWindow(link, Region.MOTION, hello.motion_size)
        coupler = RemoteWindow(link, Region.COUPLER, hello.coupler_size)
        hw = RemoteHardware(
            biris=biris,
            motion=motion,
            coupler=coupler,
            level2=lines[0],
            level3=lines[1],
            biexec_offset=hello.biexec_offset,
            biris_base=hello.biris_base,
            clock=SimulatorClock(hello.t0, hello.time_scale),
            time_scale=hello.time_scale,
            link=link,
            handshake=hello,
            # the simulator process outlives its drivers: a restarted driver must know which
            # revolution the head is in (the simulator forgets this file when it starts)
            pan_journal=default_journal_path(f"sim-{hello.shm}"),
            name=name or hello.shm,
            socket_path=path or default_socket_path(hello.shm),
            link_timeout=timeout,
        )
        undo.pop_all()
    return hw


def _open_biris(hello: Handshake) -> BusWindow:
    """The BIRIS region of the simulator's image, as a window of its own."""
    try:
        segment = open_window("shm", name=hello.shm)
    except BusError as exc:
        raise BusError(f"simulator {hello.shm!r}: {exc}", exc.errno or errno.EIO) from None
    if segment.size < hello.image_size:
        segment.close()
        raise BusError(
            f"handshake mismatch: shared memory {hello.shm!r} holds 0x{segment.size:X} bytes, "
            f"the image needs 0x{hello.image_size:X}",
            errno.EPROTO,
        )
    return SliceWindow(segment, hello.biris_offset, hello.biris_size)

"""The Wiener VME crate BIRIS sits in, watched over CAN: power, voltages, fans and temperatures.

A :class:`CrateMonitor` reads one crate (its id set on the fan tray) on any python-can bus: one
remote frame per read function (:data:`regs.wiener_crate.READ_FUNCTIONS`), each answered by an
8-byte data frame of the same id, decoded into a :class:`~regs.wiener_crate.CrateReading`. The
layouts are :mod:`regs.wiener_crate`'s.

**One request at a time.** A crate answers by id only, with no sequence number, so the monitor
asks for one function, waits for its answer, then asks for the next; a lock makes a
:meth:`~CrateMonitor.read` whole when several threads share a monitor. Before each request the
frames already waiting are dropped, so that an answer that came after an earlier read gave up
is not taken for the new one. That is best effort (where python-can filters in software, the
drop stops at the first frame the filter refuses) and enough: the only frame with the wanted id
is the crate's answer to that function, so a stale one is older data, never wrong data. While
waiting for the answer, a bounded ``timeout_s``, every frame that is not the answer is
skipped: other crates' frames, other devices' traffic, extended ids, remote frames (the
monitor's own, echoed by an interface that reflects what it sends). A frame with the right id
and the wrong length is an error, not noise: the crate (or something posing as it) answered,
and wrongly.

**Failures are :class:`~biris_hw.errors.BusError`**, naming the crate and the function: no
answer within ``timeout_s`` (errno ETIMEDOUT: the crate is off its CAN bus, unplugged or
unpowered), a malformed answer (EPROTO), the bus's own failure (EIO), a closed monitor. A read
of a silent crate fails at its first request, one ``timeout_s`` after it began; a healthy read
takes seven round trips (about a millisecond on the ``virtual`` interface).

**Read only.** The crate's command function (on, off, SYSRESET, fan speed) is not offered: a
range sensor's driver has no business switching off, or resetting, a crate whose other boards
belong to other equipment (the robot's computers share it), and a SYSRESET in the middle of
an acquisition would take the BIRIS boards down with the rest. Powering a crate is the
operator's, with the crate's own tools.
"""

from __future__ import annotations

import errno
import math
import threading
import time
from collections.abc import Callable
from types import TracebackType
from typing import Any

import can

from biris_hw.errors import BusError
from regs.wiener_crate import (
    CRATE_IDS,
    FRAME_DLC,
    READ_FUNCTIONS,
    CrateReading,
    can_id,
    check_crate_id,
    function_name,
)

__all__ = ["CRATE_IDS", "DEFAULT_TIMEOUT_S", "CrateMonitor", "CrateReading"]

DEFAULT_TIMEOUT_S = 0.25
"""How long each answer may take. A crate's controller answers within milliseconds; the rest
is room for a loaded bus or host."""

_DRAIN_LIMIT = 256
"""Stale frames dropped at most before one request (a bus flooding faster than that is not
drained; its frames are skipped while waiting instead)."""


class CrateMonitor:
    """Reads crate ``crate_id`` on ``bus`` (a python-can bus whose receive side this monitor
    alone uses: every frame it does not want is thrown away).

    ``clock`` stamps each reading (``read_at``); ``owns_bus`` makes :meth:`close` shut ``bus``
    down. :meth:`open` builds the bus as well.
    """

    def __init__(
        self,
        bus: can.BusABC,
        crate_id: int,
        *,
        timeout_s: float = DEFAULT_TIMEOUT_S,
        clock: Callable[[], float] = time.monotonic,
        owns_bus: bool = False,
    ) -> None:
        self.crate_id = check_crate_id(crate_id)
        self.timeout_s = _check_timeout(timeout_s)
        self.bus = bus
        self.channel_info: str = str(getattr(bus, "channel_info", "") or "CAN bus")
        """Where the crate is, for display (the interface's own description by default)."""
        self._clock = clock
        self._owns_bus = owns_bus
        self._lock = threading.Lock()
        self._closed = threading.Event()
        self._shut_down = False

    @classmethod
    def open(
        cls,
        *,
        interface: str | None = None,
        channel: str | None = None,
        bitrate: int | None = None,
        crate_id: int,
        timeout_s: float = DEFAULT_TIMEOUT_S,
        clock: Callable[[], float] = time.monotonic,
        **config: Any,
    ) -> CrateMonitor:
        """A monitor on a bus of its own: ``can.Bus(interface=..., channel=..., bitrate=...,
        **config)``, each of the three passed only when given (python-can's own configuration
        file or environment supplies what is not, and some interfaces take no bitrate),
        receiving only standard frames of ``crate_id`` where the interface filters. BusError
        when the bus cannot be opened; ValueError for a bad crate id or timeout, before
        anything is opened. ``clock`` is the monitor's (not python-can's)."""
        check_crate_id(crate_id)
        _check_timeout(timeout_s)
        options = dict(config)
        for key, value in (("interface", interface), ("channel", channel), ("bitrate", bitrate)):
            if value is not None:
                options[key] = value
        options.setdefault(
            "can_filters", [{"can_id": crate_id, "can_mask": 0x7F, "extended": False}]
        )
        where = f"CAN {interface or '(configured)'} channel {channel or '(configured)'}"
        try:
            bus = can.Bus(**options)
        except (can.CanError, OSError, ValueError, ImportError) as exc:
            raise BusError(f"Wiener crate {crate_id}: cannot open {where} ({exc})") from exc
        monitor = cls(bus, crate_id, timeout_s=timeout_s, clock=clock, owns_bus=True)
        if interface is not None and channel is not None:
            monitor.channel_info = where
        return monitor

    def read(self) -> CrateReading:
        """One reading of every read function, in :data:`READ_FUNCTIONS` order; BusError on
        the first that fails (see the module's notes)."""
        with self._lock:
            frames: dict[int, bytes] = {}
            for function in READ_FUNCTIONS:
                frames[function] = self._request(function)
            read_at = self._clock()
        try:
            return CrateReading.from_frames(self.crate_id, frames, read_at)
        except ValueError as exc:  # _request checked the lengths: a driver bug if it happens
            raise BusError(f"{self._where()}: {exc}", errno.EPROTO) from exc

    def _request(self, function: int) -> bytes:
        """Ask for ``function`` and wait for its answer (holding the lock)."""
        what = function_name(function)
        if self._closed.is_set():
            raise BusError(f"{self._where()}: the monitor is closed (reading {what})")
        wanted = can_id(function, self.crate_id)
        try:
            for _ in range(_DRAIN_LIMIT):
                if self.bus.recv(timeout=0.0) is None:
                    break
            self.bus.send(
                can.Message(
                    arbitration_id=wanted,
                    is_extended_id=False,
                    is_remote_frame=True,
                    dlc=FRAME_DLC,
                )
            )
            deadline = time.monotonic() + self.timeout_s
            while True:
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                msg = self.bus.recv(timeout=left)
                if msg is None:
                    break
                if (
                    msg.arbitration_id != wanted
                    or msg.is_extended_id
                    or msg.is_remote_frame
                    or msg.is_error_frame
                ):
                    continue
                if msg.dlc != FRAME_DLC or len(msg.data) != FRAME_DLC:
                    raise BusError(
                        f"{self._where()}: malformed answer to the read of {what}: dlc"
                        f" {msg.dlc} ({bytes(msg.data).hex() or 'no data'}), not {FRAME_DLC}",
                        errno.EPROTO,
                    )
                return bytes(msg.data)
        except can.CanError as exc:
            raise BusError(f"{self._where()}: CAN failure reading {what} ({exc})") from exc
        raise BusError(
            f"{self._where()}: no answer within {self.timeout_s:g} s to the read of {what},"
            f" CAN id 0x{wanted:03X}",
            errno.ETIMEDOUT,
        )

    def _where(self) -> str:
        return f"Wiener crate {self.crate_id} on {self.channel_info}"

    @property
    def closed(self) -> bool:
        return self._closed.is_set()

    def close(self) -> None:
        """Stop reading; shut the bus down if the monitor owns it. A read under way ends at
        its next request (within one timeout) before the bus goes. Idempotent."""
        self._closed.set()
        with self._lock:
            if self._owns_bus and not self._shut_down:
                self._shut_down = True
                self.bus.shutdown()

    def __enter__(self) -> CrateMonitor:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def __repr__(self) -> str:
        state = "closed" if self.closed else "open"
        return f"<CrateMonitor crate {self.crate_id} on {self.channel_info} ({state})>"


def _check_timeout(timeout_s: float) -> float:
    if (
        isinstance(timeout_s, bool)
        or not isinstance(timeout_s, (int, float))
        or not 0 < timeout_s < math.inf
    ):
        raise ValueError(f"crate answer timeout {timeout_s!r} s is not a positive number")
    return float(timeout_s)

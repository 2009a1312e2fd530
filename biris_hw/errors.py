"""The exception tree of biris-hw.

Every error the package raises on purpose derives from :class:`BirisError`, and each also derives
from the built-in it refines (``OSError`` for bus trouble, ``ValueError`` for bad requests), so a
caller can catch either our names or Python's.
"""

from __future__ import annotations

__all__ = [
    "RIDE_OUT_S",
    "AccessDenied",
    "BirisError",
    "BusError",
    "ConnectionClosed",
    "ConnectionLost",
    "FaultKind",
    "HardwareFault",
    "Initialising",
    "LineClosed",
    "RequestError",
    "SetupError",
    "UnknownKind",
]

import errno
from typing import Literal

FaultKind = Literal["timeout", "bus", "parity", "motor_stall", "protocol", "internal"]
"""What broke: the four hardware faults of the report, plus ``protocol`` for a target that answers
with garbage (a malformed PARAM reply, an impossible register value)."""


class BirisError(Exception):
    """Root of every error biris-hw raises on purpose."""


class BusError(BirisError, OSError):
    """An access through a bus window failed or was refused; nothing was read or written.

    Raised for an offset outside the window, a misaligned access, a closed window, and the
    operating system's own failures when opening or mapping a device.
    """

    def __init__(self, message: str, err: int = errno.EIO) -> None:
        OSError.__init__(self, err, message)

    def __str__(self) -> str:
        return str(self.strerror)


class UnknownKind(BirisError, LookupError):
    """A window or interrupt-line kind that no registry entry provides."""


class LineClosed(BirisError):
    """The interrupt line was closed while (or before) a thread waited on it."""


class HardwareFault(BirisError):
    """The sensor or its bus reported a fatal fault (the report's *_ERR messages).

    ``kind`` says which: ``timeout`` (BIRIS_TIMEOUT_ERR), ``bus`` (BIRIS_BUS_ERR), ``parity``
    (BIRIS_PARITY_ERR), ``motor_stall`` (no end of scan while the head stands still) or
    ``protocol`` (the target answered with something impossible).
    """

    def __init__(self, kind: FaultKind, message: str) -> None:
        super().__init__(f"{kind}: {message}")
        self.kind: FaultKind = kind
        self.message = message


class RequestError(BirisError, ValueError):
    """A client request was malformed or impossible; the server changed nothing."""


class Initialising(RequestError):
    """The server is initialising (starting, or a reset under way): the request was refused and
    nothing changed. Transient: the sensor's data come back on the same connections once the
    initialisation ends, so a long-running reader waits it out (the feed, the recorder and the
    live view do); a request asked again after ``wait_idle`` or the reset's return is served."""


class ConnectionClosed(BirisError):
    """The connection was closed, or the server that owned it has stopped."""


class ConnectionLost(BirisError, ConnectionError):
    """The network between a remote client and its service is down (a partition, a router that
    restarts, a service that stopped answering in time); nothing is known of what the request did.

    Not a :class:`ConnectionClosed`: the connection may come back by itself, and a long-running
    consumer (the feed, ``biris watch``, ``biris record``) rides it out for a bounded time,
    counting what it missed. Not a :class:`RequestError` either: the service did not refuse
    anything. A built-in ``ConnectionError`` too, so ``except OSError`` catches it.
    """


RIDE_OUT_S = 30.0
"""How long (real seconds) the long-running consumers wait out a :class:`ConnectionLost` before
they fail naming the span they missed: the feed's sinks (the recorder, the live view), ``biris
watch --connect`` and ``biris record --connect``. One bound, so they all say the same."""


class AccessDenied(BirisError):
    """A remote client without control rights asked for motion or configuration (or, on a service
    that requires credentials for reading, for data); nothing was changed."""


class SetupError(BirisError):
    """The sensor could not be reached as described: a target, init or credentials file that
    cannot be read or says something impossible, a device node that will not open, no
    simulator process or service of that name, a recording that cannot be played, or the extra
    a kind needs (``net``, ``record``) is not installed (:func:`biris_hw.sensor.open_sensor`).

    Something on this side must be fixed; the hardware has not failed (that is a
    :class:`HardwareFault`). The error met on the way is the ``__cause__``.
    """

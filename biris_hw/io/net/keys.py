"""What the service and its clients agree on: key expressions, operations, errors, limits.

Kept in one small module, apart from the code that serves or calls, so that the contract
``docs/wire-format.md`` writes down for non-Python clients is one page of Python too. Requests are
JSON objects (small, and every language has a parser); the sensor's data are CDR
(:mod:`biris_hw.io.codec`), since they are large and must come back bit for bit.
"""

from __future__ import annotations

import json
import re
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from biris_hw.errors import (
    AccessDenied,
    BirisError,
    ConnectionClosed,
    HardwareFault,
    Initialising,
    RequestError,
)

__all__ = [
    "BLOCKING_OPS",
    "CONTROL_OPS",
    "MAX_NESTING",
    "MAX_REQUEST",
    "MAX_WAIT_S",
    "OPS",
    "READ_OPS",
    "RESET_WAIT_S",
    "AuthLimited",
    "Keys",
    "ServiceClosing",
    "UnknownConnection",
    "check_client",
    "check_token",
    "error_payload",
    "parse_request",
    "raise_error",
]

MAX_REQUEST = 4096
"""Largest request payload the service parses (bytes): every request is a few dozen bytes of JSON,
so anything bigger is refused unread."""

MAX_NESTING = 16
"""Most JSON objects and arrays one request may hold, all together (outside strings), and so the
deepest it may nest: a request is one object with at most one more inside (``params``).
Counted before the JSON is parsed, so that 4,000 nested ``[`` cost a byte count, not the
parser's recursion."""

MAX_WAIT_S = 5.0
"""Longest a blocking request (ready_for_data, wait_idle) is held by the service; a client that
wants to wait longer asks again. Keeps a worker from being held for ever by a client that left,
and bounds how long a client waits before it learns that the service has gone."""

RESET_WAIT_S = 120.0
"""Longest a ``reset`` is waited for. A reset is answered when the server's initialisation ends
(a real head homes in about 12 s; the initialiser's own watchdogs fault it long before this), so
the client waits this long, not :data:`MAX_WAIT_S`: giving up earlier would leave the caller
believing the reset failed while it carries on, and lose the HardwareFault of one that fails.
A service that goes away is still noticed at once (its liveliness token)."""

READ_OPS = frozenset(
    {"open", "close", "status", "request_point", "request_scan_data", "ready_for_data", "wait_idle"}
)
"""Operations that read: free for anyone unless the service is given ``readers``."""

CONTROL_OPS = frozenset(
    {
        "single_scan",
        "continuous_scan",
        "set_elevation",
        "stop_scan",
        "start_continuous",
        "stop_continuous",
        "home",
        "set_motor_params",
        "timeout_enable",
        "timeout_disable",
        "reset",
    }
)
"""Operations that move the head or change the configuration: controllers only."""

BLOCKING_OPS = frozenset({"ready_for_data", "wait_idle"})
"""Reads that may hold a worker for up to :data:`MAX_WAIT_S` (unless their ``timeout`` is 0):
capped across all clients by the service, and never run where control operations run."""

OPS = READ_OPS | CONTROL_OPS

_NAME = re.compile(r"^[A-Za-z0-9_-]{1,64}$")

_TOKEN = re.compile(r"^[A-Za-z0-9_-]{16,64}$")


def check_token(token: object) -> str:
    """A connection token as ``open`` returns it (url-safe base64, 16 to 64 characters).

    Raises:
        BadRequest: anything else (a connection is named by its token, never by a number).
    """
    if not isinstance(token, str) or not _TOKEN.match(token):
        raise BadRequest(f"conn: expected the connection token that open returned, not {token!r}")
    return token


def check_client(request: Mapping[str, Any]) -> str:
    """A request's ``client``: a string usable as a key chunk.

    Raises:
        BadRequest: missing, not a string, or not a name (a request of nobody is served as
            nobody's: refused).
    """
    ident = request.get("client")
    if not isinstance(ident, str):
        raise BadRequest(f"client: expected the client's id (a string), not {ident!r}")
    if not _NAME.match(ident):
        raise BadRequest(
            f"client: {ident!r} is not 1 to 64 letters, digits, '-' or '_' (one key chunk)"
        )
    return ident


_STRING = re.compile(rb'"(?:[^"\\]|\\.)*"?', re.DOTALL)
"""A JSON string (escapes included), whose brackets are text, not structure; one left open runs
to the end. Every match succeeds where it starts, so a scan is linear in the payload."""


def parse_request(raw: bytes, op: str) -> dict[str, Any]:
    """A request's JSON object, read within the bounds every request keeps.

    Raises:
        BadRequest: over :data:`MAX_REQUEST` bytes, more than :data:`MAX_NESTING` objects and
            arrays, not JSON (invalid UTF-8, a syntax error, a number out of range), or not an
            object. Nothing else: whatever the bytes, the caller has an answer to send.
    """
    if len(raw) > MAX_REQUEST:
        raise BadRequest(f"{op}: request of {len(raw)} bytes exceeds {MAX_REQUEST}")
    if raw.count(b"[") + raw.count(b"{") > MAX_NESTING:
        structure = _STRING.sub(b"", raw)  # only a request with many brackets pays for this
        if structure.count(b"[") + structure.count(b"{") > MAX_NESTING:
            raise BadRequest(f"{op}: request holds more than {MAX_NESTING} JSON objects and arrays")
    try:
        request = json.loads(raw)
    except (ValueError, RecursionError) as exc:  # UnicodeDecodeError is a ValueError
        raise BadRequest(f"{op}: request is not JSON ({exc})") from None
    if not isinstance(request, dict):
        raise BadRequest(f"{op}: request must be a JSON object")
    return request


def check_name(name: str, what: str) -> str:
    """A service or client name usable as one key-expression chunk (no ``/``, ``*``, ``$``...)."""
    if not isinstance(name, str) or not _NAME.match(name):
        raise RequestError(
            f"{what}: {name!r} is not 1 to 64 letters, digits, '-' or '_' (one key chunk)"
        )
    return name


@dataclass(frozen=True)
class Keys:
    """The key expressions of service ``name`` (all under ``biris/<name>/``)."""

    name: str

    @property
    def prefix(self) -> str:
        return f"biris/{self.name}"

    @property
    def point(self) -> str:
        """Every acquisition, as ``biris_msgs/msg/Point``."""
        return f"{self.prefix}/point"

    def scan(self, direction: str) -> str:
        """Every completed scan of ``direction`` ("cw" or "ccw"), as ``biris_msgs/msg/Scan``."""
        return f"{self.prefix}/scan/{direction}"

    @property
    def scans(self) -> str:
        return f"{self.prefix}/scan/*"

    @property
    def status(self) -> str:
        """``biris_msgs/msg/Status`` on change and periodically."""
        return f"{self.prefix}/status"

    @property
    def fault(self) -> str:
        """``biris_msgs/msg/Fault`` when the server enters a fault."""
        return f"{self.prefix}/fault"

    @property
    def odom(self) -> str:
        """With the vehicle's poses: each pose sample, as ``nav_msgs/msg/Odometry`` (odom ->
        vehicle)."""
        return f"{self.prefix}/odom"

    @property
    def tf(self) -> str:
        """With the vehicle's poses: each pose sample as the ``odom -> vehicle`` transform, a
        ``tf2_msgs/msg/TFMessage``."""
        return f"{self.prefix}/tf"

    @property
    def cloud(self) -> str:
        """With the vehicle's poses: each completed scan deskewed, as
        ``sensor_msgs/msg/PointCloud2`` in ``odom``."""
        return f"{self.prefix}/cloud"

    @property
    def grid(self) -> str:
        """With a certainty grid: the grid at a few Hz, as ``nav_msgs/msg/OccupancyGrid`` in
        ``odom``."""
        return f"{self.prefix}/grid"

    @property
    def proximity(self) -> str:
        """With a proximity alarm: its answer at a few Hz, as ``biris_msgs/msg/Proximity`` in
        ``vehicle``."""
        return f"{self.prefix}/proximity"

    def rpc(self, op: str) -> str:
        """The queryable answering operation ``op``."""
        return f"{self.prefix}/rpc/{op}"

    @property
    def rpcs(self) -> str:
        return f"{self.prefix}/rpc/*"

    @property
    def service_token(self) -> str:
        """Liveliness token: the service is up."""
        return f"{self.prefix}/alive/service"

    def client_token(self, client: str) -> str:
        """Liveliness token of one client; when it goes, the client's connections are closed."""
        return f"{self.prefix}/alive/client/{client}"

    @property
    def client_tokens(self) -> str:
        return f"{self.prefix}/alive/client/*"


# -- errors ----------------------------------------------------------------------------------------

_ERRORS: dict[str, type[BirisError]] = {
    "RequestError": RequestError,
    "ConnectionClosed": ConnectionClosed,
    "AccessDenied": AccessDenied,
    "BirisError": BirisError,
}


def error_payload(exc: BaseException) -> bytes:
    """The JSON of an error reply: ``{"error": <name>, "message": ..., ["kind": ...]}``.

    ``error`` is one of RequestError, HardwareFault (with ``kind``), ConnectionClosed,
    AccessDenied, TimeoutError, BadRequest (malformed, unknown or oversized: a RequestError to a
    client), Busy (too many requests from this client; nothing was done) and BirisError (any
    other failure of the sensor: a served recording found damaged raises ReplayError).
    ``class`` names the exception's own class when it is a subclass of those
    (``EndOfRecording``, a ConnectionClosed; ``ReplayRefused``, a RequestError).
    """
    body: dict[str, Any]
    if isinstance(exc, HardwareFault):
        body = {"error": "HardwareFault", "kind": exc.kind, "message": exc.message}
    elif isinstance(exc, AccessDenied):
        body = {"error": "AccessDenied", "message": str(exc)}
    elif isinstance(exc, BadRequest):
        body = {"error": "BadRequest", "message": str(exc)}
    elif isinstance(exc, Busy):
        body = {"error": "Busy", "message": str(exc)}
    elif isinstance(exc, RequestError):
        body = {"error": "RequestError", "message": str(exc)}
    elif isinstance(exc, ConnectionClosed):
        body = {"error": "ConnectionClosed", "message": str(exc)}
    elif isinstance(exc, TimeoutError):
        body = {"error": "TimeoutError", "message": str(exc) or "timed out"}
    elif isinstance(exc, BirisError):  # the sensor's own failure, not a bug (ReplayError)
        body = {"error": "BirisError", "message": str(exc)}
    else:
        body = {"error": "InternalError", "message": f"{type(exc).__name__}: {exc}"}
    if type(exc).__name__ != body["error"]:
        # the exact class where it is a refinement (EndOfRecording, ReplayRefused from a served
        # recording): a client may tell "the recording is over" from "the link is closed"
        body["class"] = type(exc).__name__
    return json.dumps(body).encode()


class BadRequest(RequestError):
    """The service could not read a request: not JSON, unknown operation, too big, bad fields."""


class Busy(RequestError):
    """Too many requests at once (from one client, of one kind, or in all): refused unread,
    nothing was done; asking again later may succeed."""


class AuthLimited(Busy):
    """Too many failed authentications lately, by this client or on the service as a whole:
    the credentials were not checked and nothing was done (a password guesser gets a few
    guesses a second, not thousands). Asking again later may succeed."""


class UnknownConnection(ConnectionClosed):
    """The service holds no connection of that token (released when its client's liveliness
    token went, or issued by an instance of the service that has restarted since): refused
    unread. A client that did not close it may open a new one (the remote client does so)."""


class ServiceClosing(ConnectionClosed):
    """The service is stopping: the request was not served. Its liveliness token goes a moment
    later; a remote client waits for the service to come back."""


def raise_error(payload: bytes, op: str) -> None:
    """Raise the exception an error reply describes (RequestError for anything unreadable)."""
    try:
        body = json.loads(payload)
        name = str(body["error"])
        message = str(body.get("message", ""))
    except (ValueError, KeyError, TypeError):
        raise RequestError(f"{op}: the service replied with an unreadable error") from None
    if name == "HardwareFault":
        kind = body.get("kind")
        if kind not in ("timeout", "bus", "parity", "motor_stall", "protocol", "internal"):
            kind = "internal"
        raise HardwareFault(kind, message)
    if name == "TimeoutError":
        raise TimeoutError(message)
    if name == "BadRequest":
        raise BadRequest(message)
    if name == "Busy":
        raise Busy(message)
    if name == "RequestError" and body.get("class") == "Initialising":
        raise Initialising(message)  # transient: a reset under way
    raise _ERRORS.get(name, RequestError)(message)

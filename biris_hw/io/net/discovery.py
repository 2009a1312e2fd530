"""Which BIRIS services can be reached, and what each is doing (``biris list``).

Every service holds a liveliness token, ``biris/<name>/alive/service``, for as long as it runs
(:class:`~biris_hw.io.net.keys.Keys`); :func:`find_services` opens a client session (no
listener, :func:`~biris_hw.io.net.zconfig.make_config`) on the endpoints given -- probed first,
so that a refused one is said at once (:mod:`biris_hw.io.net.probe`) -- or on whatever multicast
scouting finds, asks for every such token, and then asks each service its ``status`` (with
``"info": true``). A service answers with its sensor's state and, in the reply's attachment,
what it serves (a recording or a sensor) and, from services that say it, how many clients it
has and how many of them are controllers. Only the service can say that: its clients' own
liveliness tokens reach it, not a third peer (Zenoh peers do not route for each other).
"""

from __future__ import annotations

import json
import time
import uuid
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import zenoh

from biris_hw.errors import RequestError
from biris_hw.io import codec
from biris_hw.io.net.keys import Keys
from biris_hw.io.net.probe import reachable
from biris_hw.io.net.zconfig import make_config, zenoh_message

__all__ = ["LOOK_S", "ServiceInfo", "find_services"]

LOOK_S = 2.0
"""How long :func:`find_services` looks by default: scouting's answers come within a few
hundred milliseconds on a local network; endpoints given end the look as soon as each is linked."""

_ASK_S = 2.0
"""How long one service's status is waited for."""

_RELOOK_S = 0.2
"""With endpoints given, the services' tokens are asked for again this long after the first
answer, and both answers counted."""


@dataclass(frozen=True)
class ServiceInfo:
    """One service found."""

    name: str
    state: str
    """Its sensor's state (``idle``, ``scanning``, ``fault:parity``...), or why it is not
    known: ``needs credentials`` (a service whose readers need them), ``no answer``."""
    controllers: int | None
    """Its clients that are controllers (have been granted a control operation and are still
    there); None from a service that does not say."""
    clients: int | None
    """Its clients holding connections now; None from a service that does not say."""
    playback: bool | None
    """It serves a recording (True) or a sensor (False); None when unknown."""
    instance: str | None = None
    """The Zenoh session id that answered (a restarted service has a new one)."""

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "state": self.state,
            "controllers": self.controllers,
            "clients": self.clients,
            "playback": self.playback,
            "instance": self.instance,
        }


def find_services(
    endpoints: Sequence[str] = (),
    *,
    options: Mapping[str, Any] | None = None,
    multicast: bool | None = None,
    timeout: float = LOOK_S,
    user: str | None = None,
    password: str | None = None,
) -> list[ServiceInfo]:
    """The BIRIS services reachable on ``endpoints`` (none: by multicast scouting), by name.

    ``options`` are further Zenoh settings (TLS: ``tls_options(root_ca=...)``); ``user`` and
    ``password`` go with the status requests (for services that require reader credentials:
    they are sent to every service found, so give them only where you trust every one).

    Raises:
        ConnectionClosed: none of ``endpoints`` can be reached (each one's reason said).
        RequestError: a malformed endpoint or option, TLS files that cannot be used.
    """
    endpoints = list(endpoints)
    probes = reachable(endpoints, options, "no endpoint")
    config = make_config(
        connect=endpoints,
        multicast=(not endpoints) if multicast is None else multicast,
        options=options,
        client=True,
    )
    try:
        session = zenoh.open(config)
    except Exception as exc:  # zenoh.ZError
        raise RequestError(f"cannot start the Zenoh session: {zenoh_message(exc)}") from exc
    try:
        linked = sum(1 for p in probes if not p.failed)
        _look(session, linked, timeout)
        names = _names(session, Keys("*").service_token, 1)
        if linked:
            # a peer just linked may not have handed this session its tokens yet (a busy host:
            # a listing once missed the very service whose endpoint it was given); ask again
            time.sleep(_RELOOK_S)
            names = sorted(set(names) | set(_names(session, Keys("*").service_token, 1)))
        credentials = {} if user is None else {"user": user, "password": password or ""}
        return _ask(session, names, credentials)
    finally:
        session.close()  # type: ignore[no-untyped-call]


def _look(session: zenoh.Session, endpoints: int, timeout: float) -> None:
    """Wait until each endpoint given is linked (then everything behind it is known), or,
    scouting, for the whole ``timeout``."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if endpoints and _links(session) >= endpoints:
            return
        time.sleep(0.05)  # the session has no event for a new link


def _links(session: zenoh.Session) -> int:
    info = session.info
    return sum(1 for _ in info.peers_zid()) + sum(1 for _ in info.routers_zid())


def _names(session: zenoh.Session, key: str, chunk: int) -> list[str]:
    """The ``chunk``-th part of every liveliness token's key under ``key``."""
    found: set[str] = set()
    for reply in session.liveliness().get(key, timeout=_ASK_S):
        if reply.ok is not None:
            parts = str(reply.ok.key_expr).split("/")
            if len(parts) > chunk:
                found.add(parts[chunk])
    return sorted(found)


def _ask(
    session: zenoh.Session, names: Sequence[str], credentials: Mapping[str, str]
) -> list[ServiceInfo]:
    """Each service's status, asked of all at once."""
    client = uuid.uuid4().hex
    request = {"client": client, "info": True, **credentials}
    payload = json.dumps(request).encode()
    pending = {
        name: session.get(
            Keys(name).rpc("status"),
            payload=payload,
            encoding=zenoh.Encoding.APPLICATION_JSON,
            timeout=_ASK_S,
        )
        for name in names
    }
    return [_read(name, list(replies)) for name, replies in pending.items()]


def _count(value: object) -> int | None:
    """A count from a service's attachment, or None."""
    if isinstance(value, int) and not isinstance(value, bool) and value >= 0:
        return value
    return None


def _read(name: str, replies: list[Any]) -> ServiceInfo:
    """What one service's status reply says."""
    for reply in replies:
        ok = reply.ok
        if ok is None:
            err = reply.err
            body = _json(err.payload.to_bytes() if err is not None else b"")
            refused = body.get("error") == "AccessDenied" or body.get("class") == "AuthLimited"
            state = "needs credentials" if refused else f"refused ({body.get('error', '?')})"
            return ServiceInfo(name, state, None, None, None)
        try:
            status = codec.decode_status(ok.payload.to_bytes())
        except codec.WireError:
            return ServiceInfo(name, "unreadable status", None, None, None)
        attachment = ok.attachment
        info = _json(attachment.to_bytes() if attachment is not None else b"")
        playback = info.get("playback")
        try:
            instance: str | None = str(reply.replier_id.zid)
        except Exception:  # an unstable Zenoh API
            instance = None
        return ServiceInfo(
            name,
            str(status["state"]),
            _count(info.get("controllers")),
            _count(info.get("clients")),
            playback if isinstance(playback, bool) else None,
            instance,
        )
    return ServiceInfo(name, "no answer", None, None, None)


def _json(raw: bytes) -> dict[str, Any]:
    try:
        value = json.loads(raw)
    except (ValueError, UnicodeDecodeError):
        return {}
    return value if isinstance(value, dict) else {}

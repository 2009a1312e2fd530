"""Building a Zenoh session's configuration from the few things a BIRIS user chooses.

Zenoh's configuration is a large JSON5 tree; a service or client here needs only where to
listen, where to connect, whether to discover peers by multicast, and the security settings of
the hardened set-up (TLS files, user/password, access control), which are passed through as
``{"key/path": value}`` so that everything Zenoh offers stays reachable without us wrapping it.

A client (``client=True``) is a Zenoh peer that listens nowhere: Zenoh's default would give it a
TCP listener on every interface, a port anyone on the network could reach for as long as a
``biris watch`` runs. It still connects to every endpoint it is given (and, with multicast, to
every peer it scouts), reconnects to them, and waits for a service that is not up yet -- what a
Zenoh *client* (``mode: "client"``) would not do: that one links to one endpoint only and fails
at once when it cannot.

Zenoh's errors name the Rust source line they come from (``... at /root/.cargo/git/...rs:61.``);
:func:`zenoh_message` keeps their words and drops the path.
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterable, Mapping
from typing import Any

import zenoh

from biris_hw.errors import RequestError

__all__ = ["RECONNECT", "make_config", "tls_options", "zenoh_message"]

RECONNECT = {"period_init_ms": 500, "period_max_ms": 2000, "period_increase_factor": 2}
"""How a session tries its ``connect`` endpoints again once a link is lost (a service that
restarts, a router in between, a partition): at once-ish, then every 2 s at most. Zenoh's
default backs off to 4 s; a remote client that rides out an outage (``biris watch --connect``,
``biris record --connect``) is back that much sooner, for one TCP connect attempt per 2 s."""


_RUST_SOURCE = re.compile(r"\s*\bat\s+\S*?\.rs(?::\d+)+\.?")
"""`` at /root/.cargo/git/checkouts/zenoh-.../tcp.rs:61.``: where in Zenoh's source an error was
made, which tells a user nothing."""


_DEBUG_MESSAGE = re.compile(
    r'\w+\(Message \{ msg: "((?:[^"\\]|\\.)*)"'
    r"(?:, location: (?:None|Some\(Location \{[^}]*\}\)))? \}\)"
)
"""``Json5Err(Message { msg: "Endpoints must be ...", location: ... })``: Rust's debug form of an
error around the sentence that says it."""


def zenoh_message(error: BaseException | str) -> str:
    """Zenoh's error text on one line, without the Rust source paths and debug wrappers it
    carries."""
    text = _RUST_SOURCE.sub("", str(error))
    text = _DEBUG_MESSAGE.sub(lambda found: found.group(1), text)
    return " ".join(text.split())


def make_config(
    *,
    listen: Iterable[str] = (),
    connect: Iterable[str] = (),
    multicast: bool = False,
    options: Mapping[str, Any] | None = None,
    client: bool = False,
) -> zenoh.Config:
    """A peer-mode config: ``listen``/``connect`` endpoints (``tcp/127.0.0.1:7447``,
    ``tls/host:7448``...), multicast scouting on or off, then ``options`` inserted as given.
    Lost links to ``connect`` endpoints are tried again as :data:`RECONNECT` says.

    ``client``: a program that uses a service and serves nothing: no listener at all unless
    ``listen`` (or ``options``) names one, and it does not answer other peers' multicast scouts
    (it scouts itself, with ``multicast``). Without it, no ``listen`` means Zenoh's default (a
    random TCP port on every interface).

    Raises:
        RequestError: an endpoint or option Zenoh refuses (named).
    """
    config: zenoh.Config = zenoh.Config()
    settings: dict[str, Any] = {
        "mode": "peer",
        "scouting/multicast/enabled": bool(multicast),
        # no shared-memory segments: they outlive a session in /dev/shm and a sensor service
        # gains little from them (payloads of kilobytes, most readers on other machines)
        "transport/shared_memory/enabled": False,
    }
    if not multicast:
        # a peer's open waits this long for scouting to find others (500 ms by default, paid
        # on some opens and not others); without multicast there is nothing to scout, and
        # whoever opens waits for what it needs anyway (a client: the service's token)
        settings["scouting/delay"] = 0
    listen, connect = list(listen), list(connect)
    if listen or client:
        settings["listen/endpoints"] = listen
    if client:
        settings["scouting/multicast/listen"] = False
    if connect:
        settings["connect/endpoints"] = connect
        settings["connect/retry"] = dict(RECONNECT)
    settings.update(options or {})
    for key, value in settings.items():
        try:
            config.insert_json5(key, json.dumps(value))
        except Exception as exc:  # zenoh raises its own ZError for a key or value it refuses
            raise RequestError(
                f"zenoh configuration {key}={value!r}: {zenoh_message(exc)}"
            ) from exc
    return config


def tls_options(
    *,
    certificate: str | None = None,
    private_key: str | None = None,
    root_ca: str | None = None,
) -> dict[str, Any]:
    """Zenoh options for TLS links: a listener's certificate and key, a connector's root CA.

    A service listening on ``tls/host:port`` gives ``certificate`` and ``private_key`` (PEM
    files); a client connecting to it gives ``root_ca`` (the CA that signed the certificate).
    """
    found: dict[str, Any] = {}
    if certificate is not None:
        found["transport/link/tls/listen_certificate"] = str(certificate)
    if private_key is not None:
        found["transport/link/tls/listen_private_key"] = str(private_key)
    if root_ca is not None:
        found["transport/link/tls/root_ca_certificate"] = str(root_ca)
    return found

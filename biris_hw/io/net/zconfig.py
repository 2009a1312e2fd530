"""Building a Zenoh session's configuration from the few things a BIRIS user chooses.

Zenoh's configuration is a large JSON5 tree; a service or client here needs only where to
listen, where to connect, whether to discover peers by multicast, and the security settings of
the hardened set-up (TLS files, user/password, access control), which are passed through as
``{"key/path": value}`` so that everything Zenoh offers stays reachable without us wrapping it.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping
from typing import Any

import zenoh

from biris_hw.errors import RequestError

__all__ = ["RECONNECT", "make_config", "tls_options"]

RECONNECT = {"period_init_ms": 500, "period_max_ms": 2000, "period_increase_factor": 2}
"""How a session tries its ``connect`` endpoints again once a link is lost (a service that
restarts, a router in between, a partition): at once-ish, then every 2 s at most. Zenoh's
default backs off to 4 s; a remote client that rides out an outage (``biris watch --connect``,
``biris record --connect``) is back that much sooner, for one TCP connect attempt per 2 s."""


def make_config(
    *,
    listen: Iterable[str] = (),
    connect: Iterable[str] = (),
    multicast: bool = False,
    options: Mapping[str, Any] | None = None,
) -> zenoh.Config:
    """A peer-mode config: ``listen``/``connect`` endpoints (``tcp/127.0.0.1:7447``,
    ``tls/host:7448``...), multicast scouting on or off, then ``options`` inserted as given.
    Lost links to ``connect`` endpoints are tried again as :data:`RECONNECT` says.

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
    if listen:
        settings["listen/endpoints"] = listen
    if connect:
        settings["connect/endpoints"] = connect
        settings["connect/retry"] = dict(RECONNECT)
    settings.update(options or {})
    for key, value in settings.items():
        try:
            config.insert_json5(key, json.dumps(value))
        except Exception as exc:  # zenoh raises its own ZError for a key or value it refuses
            raise RequestError(f"zenoh configuration {key}={value!r}: {exc}") from exc
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

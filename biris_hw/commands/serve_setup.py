"""What ``biris serve`` checks, and warns about, before the sensor is touched.

Starting a sensor homes its head (seconds on the simulator, some 12 s on a real one), so every
mistake a flag can carry is found first (:func:`check_service_flags`): the service's name, each
``--listen`` endpoint (its form, and whether its port is free on this machine), the TLS
certificate and key (there, readable, the key private, the pair matching), the credentials file
(private, and what it holds), every ``--zenoh-option`` (as Zenoh reads them, and a link
password dictionary private), the live view's port. Each is one line and exit status 2, with
nothing started.

And what deserves a warning in the service's log, though it may be what the operator wants
(:func:`warn_about_exposure`): listening beyond loopback in the clear or open to anyone, a
certificate that has expired or expires within :data:`CERT_WARN_DAYS`, a live view reachable
from the network.
"""

from __future__ import annotations

import argparse
import datetime
import ipaddress
import logging
import socket
import ssl
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from biris_hw.commands.failures import SetupError, UsageError
from biris_hw.commands.options import check_private_file, parse_zenoh_options, read_toml
from biris_hw.errors import RequestError

__all__ = [
    "CERT_WARN_DAYS",
    "DEFAULT_LISTEN",
    "ServiceSetup",
    "check_service_flags",
    "loopback_only",
    "warn_about_exposure",
]

log = logging.getLogger("biris_hw.commands.serve")

DEFAULT_LISTEN = "tcp/127.0.0.1:7447"
"""Loopback: a service reaches the network only when ``--listen`` says so."""

CERT_WARN_DAYS = 30
"""A service certificate that ends within this many days is warned about at start."""

_DICTIONARY = "transport/auth/usrpwd/dictionary_file"
_ACCESS_CONTROL = "access_control/enabled"
_MTLS = "transport/link/tls/enable_mtls"
_TLS_SCHEMES = ("tls", "quic")
_LOCAL_SCHEMES = ("unixsock-stream", "unixpipe", "vsock")


@dataclass(frozen=True)
class ServiceSetup:
    """What the checked flags make of the service."""

    listen: list[str]
    controllers: dict[str, str] | None
    readers: dict[str, str] | None
    options: dict[str, Any]
    multicast: bool


def check_service_flags(args: argparse.Namespace) -> ServiceSetup:
    """Every flag of ``biris serve`` that concerns the service, checked; see the module.

    Raises:
        UsageError: a malformed name or endpoint, a flag without its partner, a port out of
            range.
        SetupError: a file missing, unreadable, open to others or not what it should be; a
            port in use.
    """
    from biris_hw.io.net.keys import check_name
    from biris_hw.io.net.zconfig import make_config, tls_options

    try:
        check_name(args.name, "--name")
    except RequestError as exc:
        raise UsageError(str(exc)) from None
    listen = list(args.listen or [DEFAULT_LISTEN])
    _check_endpoints(listen)
    options: dict[str, Any] = {}
    if (args.tls_cert is None) != (args.tls_key is None):
        raise UsageError("--tls-cert and --tls-key go together")
    if args.tls_cert is not None:
        _check_tls_pair(Path(args.tls_cert), Path(args.tls_key))
        options.update(tls_options(certificate=str(args.tls_cert), private_key=str(args.tls_key)))
    else:
        tls = [e for e in listen if e.split("/", 1)[0] in _TLS_SCHEMES]
        if tls and not any("listen_certificate" in o for o in args.zenoh_option):
            raise UsageError(f"--listen {tls[0]}: a TLS endpoint needs --tls-cert and --tls-key")
    options.update(parse_zenoh_options(args.zenoh_option))
    dictionary = options.get(_DICTIONARY)
    if isinstance(dictionary, str):
        check_private_file(f"--zenoh-option {_DICTIONARY}", Path(dictionary))
    controllers, readers = _tables(args.credentials)
    multicast = _multicast(args, controllers)
    try:
        make_config(listen=listen, multicast=multicast, options=options)
    except RequestError as exc:
        raise UsageError(str(exc)) from None
    _check_foxglove(args)
    return ServiceSetup(listen, controllers, readers, options, multicast)


def _check_endpoints(listen: Sequence[str]) -> None:
    """Each ``--listen`` endpoint well formed and, for TCP, its port free here."""
    from biris_hw.io.net.probe import parse_endpoint, port_taken

    for endpoint in listen:
        try:
            parse_endpoint(endpoint)
            taken = port_taken(endpoint)
        except RequestError as exc:
            raise UsageError(f"--listen: {exc}") from None
        if taken is not None:
            raise SetupError(f"--listen {endpoint}: cannot listen there: {taken}")


def _check_tls_pair(cert: Path, key: Path) -> None:
    """The certificate readable, the key private, and the two a pair."""
    if not cert.is_file():
        raise SetupError(f"--tls-cert {cert}: no such file")
    check_private_file("--tls-key", key)
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    try:
        context.load_cert_chain(str(cert), str(key))
    except ssl.SSLError as exc:
        if exc.reason == "KEY_VALUES_MISMATCH":
            why = "the key is not the certificate's"
        else:
            why = "they are not a PEM certificate and its PEM private key"
        raise SetupError(f"--tls-cert {cert} and --tls-key {key} cannot be used: {why}") from exc
    except OSError as exc:
        raise SetupError(f"--tls-cert {cert}: {exc.strerror or exc}") from exc


def _tables(file: Any) -> tuple[dict[str, str] | None, dict[str, str] | None]:
    """(controllers, readers) from a credentials file, which must be private."""
    if file is None:
        return None, None
    check_private_file("--credentials", Path(file))
    table = read_toml(file)
    unknown = set(table) - {"controllers", "readers"}
    if unknown:
        raise SetupError(f"{file}: unknown table(s) {', '.join(sorted(unknown))}")
    found: list[dict[str, str] | None] = []
    for key in ("controllers", "readers"):
        users = table.get(key)
        if users is None:
            found.append(None)
            continue
        if not isinstance(users, Mapping) or not all(
            isinstance(v, str) and v for v in users.values()
        ):
            raise SetupError(f'{file}: [{key}] must hold user = "password" lines')
        found.append(dict(users))
    return found[0], found[1]


def _multicast(args: argparse.Namespace, controllers: Mapping[str, str] | None) -> bool:
    """Scouting on unless refused; with credentials, off unless asked for."""
    if args.no_multicast:
        return False
    return bool(args.multicast or not (controllers or args.credentials is not None))


def _check_foxglove(args: argparse.Namespace) -> None:
    """``--foxglove PORT``: a TCP port, free on ``--foxglove-host``."""
    port = getattr(args, "foxglove", None)
    if port is None:
        return
    if not 0 <= port <= 65535:
        raise UsageError(f"--foxglove {port}: not a TCP port (0 to 65535)")
    if port == 0:
        return
    host = args.foxglove_host
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except socket.gaierror as exc:
        raise UsageError(f"--foxglove-host {host}: cannot resolve it ({exc.strerror})") from None
    family, kind, proto, _, address = infos[0]
    with socket.socket(family, kind, proto) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind(address)
        except OSError as exc:
            raise SetupError(
                f"--foxglove {port}: cannot listen on {host}:{port}: "
                f"{(exc.strerror or str(exc)).lower()}"
            ) from None


# -- warnings ----------------------------------------------------------------------------------


def loopback_only(endpoint: str) -> bool:
    """The endpoint can be reached from this machine only: a loopback address or
    ``localhost``, or a local socket."""
    scheme, _, rest = endpoint.partition("/")
    if scheme in _LOCAL_SCHEMES:
        return True
    address = rest.split("?", 1)[0].split("#", 1)[0]
    host = address.rpartition(":")[0] if ":" in address else address
    host = host.strip("[]")
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def warn_about_exposure(
    setup: ServiceSetup, args: argparse.Namespace, now: datetime.datetime | None = None
) -> list[str]:
    """Log (WARNING) what leaves the service open; returns the lines (for tests).

    * an endpoint beyond loopback without TLS (requests, passwords and connection tokens cross
      the network readable), or with nothing that keeps strangers out (no access control, no
      link authentication, no mutual TLS, no reader credentials): anyone who reaches it reads
      the sensor;
    * the TLS certificate expired, or ending within :data:`CERT_WARN_DAYS`;
    * the live view (``--foxglove``) on an address beyond loopback: its protocol has no
      authentication.
    """
    said: list[str] = []
    exposed = [e for e in setup.listen if not loopback_only(e)]
    options = setup.options
    guarded = (
        options.get(_ACCESS_CONTROL) is True
        or (
            isinstance(options.get("access_control"), Mapping)
            and options["access_control"].get("enabled") is True
        )
        or _DICTIONARY in options
        or options.get(_MTLS) is True
        or setup.readers is not None
    )
    for endpoint in exposed:
        missing = []
        if endpoint.split("/", 1)[0] not in _TLS_SCHEMES:
            secret = "passwords, connection tokens and data" if setup.controllers else "the data"
            missing.append(f"in the clear ({secret} readable on the network: use tls/)")
        if not guarded:
            missing.append(
                "open to anyone who reaches it (no access control, link authentication, "
                "mutual TLS or [readers])"
            )
        if missing:
            said.append(
                f"listening on {endpoint}, beyond this machine, {' and '.join(missing)}; "
                "see docs/service.md#security"
            )
    if args.tls_cert is not None:
        said.extend(_certificate_warning(Path(args.tls_cert), now))
    port = getattr(args, "foxglove", None)
    if port is not None and not loopback_only(f"tcp/{args.foxglove_host}:{port}"):
        said.append(
            f"the live view listens on {args.foxglove_host}:{port}, beyond this machine: its "
            "WebSocket has no authentication, anyone who reaches it reads the sensor"
        )
    for line in said:
        log.warning("%s", line)
    return said


def _certificate_warning(cert: Path, now: datetime.datetime | None) -> list[str]:
    from biris_hw.io.net.probe import certificate_not_after

    try:
        ends = certificate_not_after(cert)
    except RequestError as exc:
        return [f"--tls-cert: cannot read its validity: {exc}"]
    now = now or datetime.datetime.now(datetime.timezone.utc)
    left = ends - now
    day = ends.strftime("%Y-%m-%d %H:%M UTC")
    if left.total_seconds() <= 0:
        return [f"--tls-cert {cert} expired on {day}: every client will refuse the service"]
    if left <= datetime.timedelta(days=CERT_WARN_DAYS):
        days = left.total_seconds() / 86400
        return [
            f"--tls-cert {cert} expires on {day} (in {days:.0f} day(s)): renew it before "
            "clients refuse the service"
        ]
    return []

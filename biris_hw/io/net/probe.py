"""What can be learned about a service's endpoints and TLS files before Zenoh is started.

Zenoh reports none of a client's connection problems: a peer given an endpoint nobody listens
on, a TLS port spoken to in plain TCP, a certificate its CA did not sign or that has expired --
each is retried quietly in the background, and the client only learns, after its whole timeout,
that no service answered. So a client first does, with Python's own ``socket`` and ``ssl`` and a
bound of :data:`PROBE_S`, what Zenoh is about to do: a TCP connect to each ``tcp/`` and ``tls/``
endpoint and, for ``tls/``, a TLS handshake with the same root CA, client certificate and name
check. A refusal, a host that cannot be reached or resolved, and a certificate that fails (with
OpenSSL's reason: "certificate has expired", "Hostname mismatch, ...") are then said at once, in
the client's terms (:class:`Probe`). So is a ``tls/`` endpoint on a port without TLS: a TLS
server answers a ClientHello at once, Zenoh's TCP listener waits for more bytes, and the
handshake gets no answer within :data:`HANDSHAKE_S`. Other schemes (``udp/``, ``quic/``,
``unixsock-stream/``...) are left to Zenoh.

The reverse, a ``tcp/`` endpoint on a TLS port, cannot be told by a connect (it succeeds, and
Zenoh's handshake then never does); :func:`speaks_tls` looks, once Zenoh has failed to link.

Also here, for ``biris serve``: a certificate's end of validity (:func:`certificate_not_after`),
and a listening port already taken (:func:`port_taken`).
"""

from __future__ import annotations

import base64
import binascii
import contextlib
import datetime
import errno
import logging
import socket
import ssl
import threading
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from biris_hw.errors import ConnectionClosed, RequestError

__all__ = [
    "HANDSHAKE_S",
    "PROBE_S",
    "Endpoint",
    "Probe",
    "TlsFiles",
    "certificate_not_after",
    "parse_endpoint",
    "port_taken",
    "probe",
    "probe_all",
    "reachable",
    "speaks_tls",
]

log = logging.getLogger(__name__)

PROBE_S = 1.0
"""Longest a TCP connect of the probe may take: on a network where the service can be used at
all, it takes milliseconds."""

HANDSHAKE_S = 2.0
"""Longest the TLS handshake after it may take before the port is taken for a plain one (a TLS
server answers a ClientHello at once; Zenoh's TCP listener waits for more bytes, for ever):
twice :data:`PROBE_S`, so that a busy service's late answer is not taken for none."""

_IP_SCHEMES = ("tcp", "tls")
"""Endpoint schemes the probe knows how to try (TCP, and TLS over TCP)."""

_CA = "transport/link/tls/root_ca_certificate"
_CA_BASE64 = "transport/link/tls/root_ca_certificate_base64"
_CLIENT_CERT = "transport/link/tls/connect_certificate"
_CLIENT_KEY = "transport/link/tls/connect_private_key"
_VERIFY_NAME = "transport/link/tls/verify_name_on_connect"


@dataclass(frozen=True)
class Endpoint:
    """A ``tcp/`` or ``tls/`` endpoint, read: ``tls/robot:7448`` is ("tls", "robot", 7448)."""

    text: str
    scheme: str
    host: str
    port: int


def parse_endpoint(text: str) -> Endpoint | None:
    """``tcp/HOST:PORT`` or ``tls/HOST:PORT`` (``[v6]`` hosts, Zenoh's ``?metadata`` and
    ``#config`` tails allowed) as an :class:`Endpoint`; None for another scheme.

    Raises:
        RequestError: a ``tcp/`` or ``tls/`` endpoint without a host, or whose port is not a
            number from 0 to 65535.
    """
    scheme, sep, rest = text.partition("/")
    if not sep or scheme not in _IP_SCHEMES:
        return None
    address = rest.split("?", 1)[0].split("#", 1)[0]
    host, colon, port_text = address.rpartition(":")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    if not colon or not host:
        raise RequestError(f"endpoint {text}: expected {scheme}/HOST:PORT")
    try:
        port = int(port_text, 10)
    except ValueError:
        raise RequestError(f"endpoint {text}: {port_text!r} is not a port number") from None
    if not 0 <= port <= 65535:
        raise RequestError(f"endpoint {text}: port {port} is not a TCP port (0 to 65535)")
    return Endpoint(text, scheme, host, port)


@dataclass(frozen=True)
class TlsFiles:
    """What a TLS handshake of the client uses, read from its Zenoh options."""

    root_ca: str | None = None
    root_ca_pem: str | None = None
    """The CA given inline (Zenoh's ``root_ca_certificate_base64``), decoded."""
    certificate: str | None = None
    """The client's own certificate and key, for mutual TLS."""
    private_key: str | None = None
    verify_name: bool = True

    @classmethod
    def from_options(cls, options: Mapping[str, Any] | None) -> TlsFiles:
        """The TLS settings among Zenoh options (``tls_options(root_ca=...)``,
        ``--zenoh-option``)."""
        options = options or {}
        inline = options.get(_CA_BASE64)
        pem = None
        if isinstance(inline, str):
            with contextlib.suppress(binascii.Error, UnicodeDecodeError, ValueError):
                pem = base64.b64decode(inline, validate=True).decode("ascii")
        ca, cert, key = options.get(_CA), options.get(_CLIENT_CERT), options.get(_CLIENT_KEY)
        return cls(
            root_ca=str(ca) if isinstance(ca, (str, Path)) else None,
            root_ca_pem=pem,
            certificate=str(cert) if isinstance(cert, (str, Path)) else None,
            private_key=str(key) if isinstance(key, (str, Path)) else None,
            verify_name=options.get(_VERIFY_NAME) is not False,
        )

    def context(self) -> ssl.SSLContext:
        """An SSL context that checks what Zenoh's TLS link checks.

        Raises:
            RequestError: a CA, certificate or key file that cannot be read or is not PEM.
        """
        context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)  # verifies, and checks the name
        context.check_hostname = self.verify_name
        try:
            if self.root_ca is not None:
                context.load_verify_locations(cafile=self.root_ca)
            elif self.root_ca_pem is not None:
                context.load_verify_locations(cadata=self.root_ca_pem)
            else:  # no CA of the user's: the machine's trusted ones (as Zenoh's are)
                context.load_default_certs()
        except FileNotFoundError:
            raise RequestError(f"the root CA {self.root_ca}: no such file") from None
        except (OSError, ssl.SSLError) as exc:
            raise RequestError(f"the root CA {self.root_ca}: not a PEM certificate") from exc
        if self.certificate is not None and self.private_key is not None:
            try:
                context.load_cert_chain(self.certificate, self.private_key)
            except (OSError, ssl.SSLError) as exc:
                raise RequestError(
                    f"the client certificate {self.certificate} and key {self.private_key} "
                    f"cannot be used: {exc}"
                ) from exc
        return context


Verdict = Literal["ok", "refused", "unreachable", "tls", "no_tls", "timeout", "skipped"]


@dataclass(frozen=True)
class Probe:
    """What trying one endpoint found."""

    endpoint: str
    verdict: Verdict
    """``ok``; ``refused`` (nobody listens there); ``unreachable`` (no route, a host name that
    does not resolve); ``tls`` (the handshake failed: a certificate refused, with OpenSSL's
    reason); ``no_tls`` (TCP connects, but no TLS answer: a plain port, probably); ``timeout``
    (no answer to the TCP connect: a firewall that drops, a slow network; left to Zenoh);
    ``skipped`` (a scheme the probe does not try)."""
    reason: str = ""

    @property
    def failed(self) -> bool:
        """Zenoh cannot link there either: the reason is the one to say."""
        return self.verdict in ("refused", "unreachable", "tls", "no_tls")

    def __str__(self) -> str:
        return f"{self.endpoint}: {self.reason}" if self.reason else self.endpoint


def probe(text: str, tls: TlsFiles | None = None, timeout: float = PROBE_S) -> Probe:
    """Try ``text`` as Zenoh is about to: a TCP connect, and a TLS handshake for ``tls/``.

    Raises:
        RequestError: a malformed ``tcp/``/``tls/`` endpoint (:func:`parse_endpoint`), or TLS
            files that cannot be used (:meth:`TlsFiles.context`).
    """
    endpoint = parse_endpoint(text)
    if endpoint is None:
        return Probe(text, "skipped")
    context = (tls or TlsFiles()).context() if endpoint.scheme == "tls" else None
    try:
        raw = socket.create_connection((endpoint.host, endpoint.port), timeout=timeout)
    except socket.gaierror as exc:
        return Probe(text, "unreachable", f"cannot resolve {endpoint.host!r} ({exc.strerror})")
    except ConnectionRefusedError:
        return Probe(text, "refused", "connection refused (nothing listens there)")
    except TimeoutError:
        return Probe(text, "timeout", f"no answer to a TCP connect within {timeout:g} s")
    except OSError as exc:
        if exc.errno in (errno.ENETUNREACH, errno.EHOSTUNREACH, errno.EADDRNOTAVAIL):
            return Probe(text, "unreachable", exc.strerror or str(exc))
        return Probe(text, "timeout", exc.strerror or str(exc))
    with raw:
        if context is None:
            return Probe(text, "ok")
        raw.settimeout(max(timeout, HANDSHAKE_S))
        return _handshake(endpoint, raw, context, tls or TlsFiles())


def _handshake(
    endpoint: Endpoint, raw: socket.socket, context: ssl.SSLContext, tls: TlsFiles
) -> Probe:
    text = endpoint.text
    try:
        with context.wrap_socket(raw, server_hostname=endpoint.host):
            return Probe(text, "ok")
    except ssl.SSLCertVerificationError as exc:
        return Probe(text, "tls", _verify_reason(exc, endpoint, tls))
    except TimeoutError:
        return Probe(
            text,
            "no_tls",
            f"no TLS answer within {raw.gettimeout() or 0:g} s: a port without TLS? "
            f"(tcp/{_address(text)})",
        )
    except (ssl.SSLError, ConnectionError) as exc:
        return Probe(text, "tls", f"TLS handshake failed: {_ssl_reason(exc)}")
    except OSError as exc:
        return Probe(text, "tls", f"TLS handshake failed: {exc.strerror or exc}")


def _verify_reason(exc: ssl.SSLCertVerificationError, endpoint: Endpoint, tls: TlsFiles) -> str:
    """OpenSSL's reason the certificate was refused, and what to do about it."""
    why = str(exc.verify_message or exc.reason or exc)
    said = f"TLS handshake failed: certificate verify failed: {why}"
    if "expired" in why:
        return f"{said} (the service's certificate is out of date: renew it)"
    if "not yet valid" in why:
        return f"{said} (check both machines' clocks)"
    if "mismatch" in why:
        return f"{said} (connect with the name the certificate was issued for)"
    if "issuer" in why or "self-signed" in why or "self signed" in why:
        if tls.root_ca is None and tls.root_ca_pem is None:
            return f"{said} (give --tls-ca FILE: the CA that signed the service's certificate)"
        return f"{said} (the service's certificate is not signed by {tls.root_ca or 'that CA'})"
    return said


def _ssl_reason(exc: BaseException) -> str:
    reason = getattr(exc, "reason", None)
    if isinstance(reason, str) and reason:
        text = reason.replace("_", " ").lower()
    else:
        text = str(exc) or type(exc).__name__
    if isinstance(exc, (ssl.SSLEOFError, ConnectionError)) or "eof" in text:
        return f"{text} (the service closed the link during the handshake)"
    return text


def _address(text: str) -> str:
    return text.partition("/")[2]


def probe_all(
    endpoints: Sequence[str], options: Mapping[str, Any] | None = None, timeout: float = PROBE_S
) -> list[Probe]:
    """:func:`probe` of every endpoint, at once (one thread each beyond the first), in order.

    Raises:
        RequestError: as :func:`probe`, for the first endpoint that raises it.
    """
    tls = TlsFiles.from_options(options)
    if len(endpoints) <= 1:
        return [probe(e, tls, timeout) for e in endpoints]
    found: list[Probe | BaseException | None] = [None] * len(endpoints)

    def one(index: int, text: str) -> None:
        try:
            found[index] = probe(text, tls, timeout)
        except BaseException as exc:  # handed to the caller below
            found[index] = exc

    threads = [
        threading.Thread(target=one, args=(i, e), name="biris-probe", daemon=True)
        for i, e in enumerate(endpoints)
    ]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout + HANDSHAKE_S + 1.0)  # a connect and a handshake, each bounded
    results: list[Probe] = []
    for text, item in zip(endpoints, found, strict=True):
        if isinstance(item, BaseException):
            raise item
        results.append(item if item is not None else Probe(text, "timeout", "no answer"))
    return results


def reachable(
    endpoints: Sequence[str], options: Mapping[str, Any] | None, what: str
) -> list[Probe]:
    """:func:`probe_all`, raising the reasons when no endpoint can be linked to; those that
    fail while others do not are logged. ``what`` begins the error (``no BIRIS service
    'biris0'``). A refusal is not tried again: a service listens only once its sensor has
    started, seconds after its process, so a moment's wait would not find it either.

    Raises:
        ConnectionClosed: no endpoint can be reached (each one's reason said).
        RequestError: a malformed endpoint, TLS files that cannot be used.
    """
    found = probe_all(endpoints, options)
    failed = [p for p in found if p.failed]
    if found and len(failed) == len(found):
        raise ConnectionClosed(f"{what} can be reached: {'; '.join(map(str, failed))}")
    for each in failed:
        log.warning("%s: %s", what.replace("no ", "", 1), each)
    return found


def speaks_tls(text: str, timeout: float = PROBE_S) -> bool:
    """Whether the server at ``text``'s address answers a TLS handshake (certificate not
    checked): a ``tcp/`` endpoint given for a TLS port. Never raises."""
    try:
        endpoint = parse_endpoint(text)
    except RequestError:
        return False
    if endpoint is None:
        return False
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    context.check_hostname = False
    context.verify_mode = ssl.CERT_NONE
    try:
        with (
            socket.create_connection((endpoint.host, endpoint.port), timeout=timeout) as raw,
            context.wrap_socket(raw, server_hostname=endpoint.host),
        ):
            return True
    except ssl.SSLError as exc:
        # an alert after the server's hello (a client certificate wanted) is still TLS
        return "alert" in str(exc).lower()
    except OSError:
        return False


def certificate_not_after(file: str | Path) -> datetime.datetime:
    """When the (first) certificate of a PEM file stops being valid, in UTC.

    Raises:
        RequestError: the file cannot be read or holds no certificate.
    """
    try:
        pem = Path(file).read_bytes()
    except OSError as exc:
        raise RequestError(f"{file}: {exc.strerror or exc}") from exc
    try:
        from cryptography import x509
    except ImportError:  # an optional package: the standard library's decoder then
        return _not_after_with_ssl(file)
    try:
        cert = x509.load_pem_x509_certificate(pem)
    except ValueError as exc:
        raise RequestError(f"{file}: not a PEM certificate ({exc})") from exc
    after = getattr(cert, "not_valid_after_utc", None)  # cryptography 42 and later
    if isinstance(after, datetime.datetime):
        return after
    return cert.not_valid_after.replace(tzinfo=datetime.timezone.utc)


def _not_after_with_ssl(file: str | Path) -> datetime.datetime:
    decode = getattr(getattr(ssl, "_ssl", None), "_test_decode_cert", None)
    if decode is None:
        raise RequestError(f"{file}: cannot read certificates here (no cryptography package)")
    try:
        found = decode(str(file))
        stamp = ssl.cert_time_to_seconds(found["notAfter"])
    except (ssl.SSLError, KeyError, ValueError) as exc:
        raise RequestError(f"{file}: not a PEM certificate ({exc})") from exc
    return datetime.datetime.fromtimestamp(stamp, tz=datetime.timezone.utc)


def port_taken(text: str) -> str | None:
    """Why a service could not listen on ``text`` (a ``tcp/`` or ``tls/`` endpoint): "address
    already in use", "cannot assign requested address" (not an address of this machine)...;
    None when it can, or for a port 0 or another scheme. Checked by binding the port a moment,
    as Zenoh will (SO_REUSEADDR, as Zenoh sets it).

    Raises:
        RequestError: a malformed endpoint (:func:`parse_endpoint`).
    """
    endpoint = parse_endpoint(text)
    if endpoint is None or endpoint.port == 0:
        return None
    try:
        infos = socket.getaddrinfo(endpoint.host, endpoint.port, type=socket.SOCK_STREAM)
    except socket.gaierror as exc:
        return f"cannot resolve {endpoint.host!r} ({exc.strerror})"
    family, kind, proto, _, address = infos[0]
    with socket.socket(family, kind, proto) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind(address)
        except OSError as exc:
            return (exc.strerror or str(exc)).lower()
    return None

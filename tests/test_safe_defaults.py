"""Safe by default, and mistakes told at once (fast tier: services on a FakeSensor, loopback).

Clients open no port; ``biris serve`` listens on loopback unless told, checks every flag before
the sensor is touched, refuses secrets other users may read, and warns about what it leaves
open (the network, an ending certificate). A client names what is wrong, soon: a refused
connection, a certificate refused (with OpenSSL's reason, an expired one included), a TLS port
spoken to in plain TCP and the reverse, another service's name, wrong credentials; Zenoh's Rust
source paths never reach a message. ``biris record``'s progress line is drawn in place and
gets out of the way of every other line.
"""

from __future__ import annotations

import argparse
import datetime
import io
import ipaddress
import os
import socket
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from biris_hw.cli import build_parser
from biris_hw.commands import session as cli_session
from biris_hw.commands.console import StatusLine
from biris_hw.commands.failures import SetupError, error_line
from biris_hw.commands.options import check_private_file
from biris_hw.commands.record import _progress, progress_text
from biris_hw.commands.serve_setup import (
    DEFAULT_LISTEN,
    ServiceSetup,
    check_service_flags,
    loopback_only,
    warn_about_exposure,
)
from biris_hw.errors import AccessDenied, ConnectionClosed
from biris_hw.io.net import connect, serve, tls_options
from biris_hw.io.net.zconfig import make_config, zenoh_message
from tests.conftest import Run
from tests.net_helpers import FakeSensor, endpoint, free_port, warm_up_zenoh

CONTROLLERS = {"op": "s3cret"}

PROMPT_S = 5.0
"""A mistake said "at once" is said well within this (it used to take the whole 10 s connect
timeout); generous for a loaded machine."""


@pytest.fixture(scope="module", autouse=True)
def _zenoh_runtime() -> None:
    warm_up_zenoh()


# -- certificates ----------------------------------------------------------------------------------


def _certificates(folder: Path, *, days: float = 2.0, name: str = "ca") -> dict[str, Path]:
    """A CA and a server certificate for 127.0.0.1/localhost valid for ``days`` from now
    (negative: expired that long ago); the key mode 600."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    now = datetime.datetime.now(datetime.timezone.utc)
    start = now - datetime.timedelta(days=max(0.0, -days) + 1)
    end = now + datetime.timedelta(days=days)
    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, f"biris-test-{name}")])
    ca = (
        x509.CertificateBuilder().subject_name(ca_name).issuer_name(ca_name)
        .public_key(ca_key.public_key()).serial_number(x509.random_serial_number())
        .not_valid_before(start).not_valid_after(now + datetime.timedelta(days=400))
        .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
        .sign(ca_key, hashes.SHA256())
    )  # fmt: skip
    key = ec.generate_private_key(ec.SECP256R1())
    names = [x509.DNSName("localhost"), x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]
    cert = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "localhost")]))
        .issuer_name(ca_name).public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(start).not_valid_after(end)
        .add_extension(x509.SubjectAlternativeName(names), critical=False)
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .sign(ca_key, hashes.SHA256())
    )  # fmt: skip
    folder.mkdir(parents=True, exist_ok=True)
    paths = {
        "ca": folder / f"{name}.pem",
        "cert": folder / f"{name}-server.pem",
        "key": folder / f"{name}-server.key",
    }
    paths["ca"].write_bytes(ca.public_bytes(serialization.Encoding.PEM))
    paths["cert"].write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    paths["key"].write_bytes(
        key.private_bytes(
            serialization.Encoding.PEM,
            serialization.PrivateFormat.PKCS8,
            serialization.NoEncryption(),
        )
    )
    paths["key"].chmod(0o600)
    return paths


# -- services --------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def tls_folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("tls")


@pytest.fixture(scope="module")
def certificates(tls_folder: Path) -> dict[str, dict[str, Path]]:
    """A valid server certificate, an expired one, and a CA that signed neither."""
    return {
        "good": _certificates(tls_folder, name="good"),
        "expired": _certificates(tls_folder, days=-3, name="old"),
        "other": _certificates(tls_folder, name="other"),
    }


@pytest.fixture
def services(certificates: dict[str, dict[str, Path]]) -> Iterator[dict[str, Any]]:
    """Three services on loopback: "h" in plain TCP with a controller, "t" on TLS, "x" on TLS
    with an expired certificate (each test its own: their threads and links are its own)."""
    good, expired, other = certificates["good"], certificates["expired"], certificates["other"]
    fakes = [FakeSensor() for _ in range(3)]
    sensors: list[Any] = list(fakes)  # a Sensor in all that the service uses
    plain, tls, old = (
        endpoint(free_port()),
        endpoint(free_port(), "tls"),
        endpoint(free_port(), "tls"),
    )
    with (
        serve(sensors[0], name="h", listen=[plain], controllers=CONTROLLERS, multicast=False),
        serve(
            sensors[1], name="t", listen=[tls], multicast=False,
            options=tls_options(certificate=str(good["cert"]), private_key=str(good["key"])),
        ),
        serve(
            sensors[2], name="x", listen=[old], multicast=False,
            options=tls_options(certificate=str(expired["cert"]), private_key=str(expired["key"])),
        ),
    ):  # fmt: skip
        yield {
            "plain": plain, "tls": tls, "old": old, "good": good, "expired": expired, "other": other
        }  # fmt: skip
    for fake in fakes:
        fake.free()


def _listening_ports() -> set[int]:
    """TCP ports this process listens on (Linux: /proc's socket table against our fds)."""
    inodes = set()
    for fd in os.listdir("/proc/self/fd"):
        with_link = os.path.join("/proc/self/fd", fd)
        try:
            target = os.readlink(with_link)
        except OSError:
            continue
        if target.startswith("socket:["):
            inodes.add(target[8:-1])
    ports = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        try:
            lines = Path(table).read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            parts = line.split()
            if parts[3] == "0A" and parts[9] in inodes:  # LISTEN
                ports.add(int(parts[1].rsplit(":", 1)[1], 16))
    return ports


# -- clients open no port --------------------------------------------------------------------------


def test_a_client_session_has_no_listener() -> None:
    config = make_config(connect=["tcp/127.0.0.1:7447"], client=True)
    assert config.get_json("listen/endpoints") == "[]"
    assert config.get_json("scouting/multicast/listen") == "false"
    service_config = make_config(listen=["tcp/127.0.0.1:7447"])
    assert "127.0.0.1" in service_config.get_json("listen/endpoints")


@pytest.mark.skipif(not Path("/proc/net/tcp").exists(), reason="reads Linux's socket table")
def test_a_connected_client_listens_on_no_port(services: dict[str, Any]) -> None:
    before = _listening_ports()
    with connect("h", [services["plain"]], multicast=False) as remote:
        assert remote.status()["state"] == "idle"
        assert _listening_ports() == before  # the service's own port was there before


# -- biris serve: loopback, every flag before the sensor, secrets private, warnings --------------


def test_serve_listens_on_loopback_unless_told() -> None:
    assert DEFAULT_LISTEN == "tcp/127.0.0.1:7447"
    assert loopback_only(DEFAULT_LISTEN)
    assert build_parser("serve").parse_args(["serve", "--sim"]).listen is None
    for local in ("tcp/[::1]:7447", "tls/localhost:7448", "unixsock-stream//tmp/b.sock"):
        assert loopback_only(local), local
    for wide in ("tcp/0.0.0.0:7447", "tcp/[::]:7447", "tls/192.168.1.5:7448", "tcp/robot:1"):
        assert not loopback_only(wide), wide


@pytest.fixture
def no_sensor(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """The simulator may not start: a check that came after it would fail the test."""
    started: list[str] = []

    def refuse(args: argparse.Namespace) -> Any:
        started.append("sim")
        raise AssertionError("the sensor was started before the flags were checked")

    monkeypatch.setattr(cli_session, "_start_rig", refuse)
    return started


def _serve_cases(folder: Path) -> list[tuple[list[str], str]]:
    good = _certificates(folder / "pair", name="a")
    other = _certificates(folder / "pair", name="b")
    open_credentials = folder / "open.toml"
    open_credentials.write_text('[controllers]\nop = "pw"\n')
    open_credentials.chmod(0o644)
    open_dictionary = folder / "users.txt"
    open_dictionary.write_text("robot:pw\n")
    open_dictionary.chmod(0o644)
    port = free_port()
    return [
        (["--name", "bad name!"], "not 1 to 64 letters"),
        (["--listen", "foo"], "Endpoints must be of the form"),
        (["--listen", "tcp/127.0.0.1:notaport"], "'notaport' is not a port number"),
        (["--listen", "tcp/127.0.0.1:70000"], "port 70000 is not a TCP port"),
        (["--listen", f"tls/127.0.0.1:{port}"], "a TLS endpoint needs --tls-cert and --tls-key"),
        (["--foxglove", "99999"], "--foxglove 99999: not a TCP port"),
        (["--tls-cert", str(good["cert"])], "--tls-cert and --tls-key go together"),
        (
            ["--tls-cert", str(good["cert"]), "--tls-key", str(folder / "nosuch.key")],
            "nosuch.key: no such file",
        ),
        (
            ["--tls-cert", str(good["cert"]), "--tls-key", str(other["key"])],
            "cannot be used: the key is not the certificate's",
        ),
        (["--credentials", str(folder / "nosuch.toml")], "nosuch.toml: no such file"),
        (["--credentials", str(open_credentials)], "mode 0644 lets other users read it"),
        (
            ["--zenoh-option", f"transport/auth/usrpwd/dictionary_file={open_dictionary}"],
            "mode 0644 lets other users read it",
        ),
        (["--zenoh-option", "transport/auth/usrpwd/password=x"], "no passwords on the command"),
    ]


def test_serve_checks_every_flag_before_the_sensor(
    biris: Run, tmp_path: Path, no_sensor: list[str]
) -> None:
    """Each mistake is one line and exit status 2, and the simulator was never started."""
    for flags, said in _serve_cases(tmp_path):
        argv = ["serve", "--sim", "--no-multicast", "--duration", "1"]
        if "--listen" not in flags:
            argv += ["--listen", endpoint(free_port())]
        code, out, err = biris(*argv, *flags)
        assert (code, out) == (2, ""), (flags, err)
        lines = err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("biris serve: "), (flags, err)
        assert said in lines[0], (flags, lines[0])
        assert ".rs" not in lines[0] and "/root/.cargo" not in lines[0], lines[0]
    assert no_sensor == []


def test_serve_refuses_ports_in_use_before_the_sensor(biris: Run, no_sensor: list[str]) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        base = ["serve", "--sim", "--no-multicast", "--duration", "1"]
        code, _, err = biris(*base, "--listen", f"tcp/127.0.0.1:{port}")
        assert code == 2
        assert f"--listen tcp/127.0.0.1:{port}: cannot listen there: address already in use" in err
        code, _, err = biris(*base, "--listen", endpoint(free_port()), "--foxglove", str(port))
        assert code == 2
        assert f"--foxglove {port}: cannot listen on 127.0.0.1:{port}: address already" in err
    assert no_sensor == []


def _setup(listen: list[str], **options: Any) -> ServiceSetup:
    return ServiceSetup(listen, dict(CONTROLLERS), None, dict(options), False)


def _args(**values: Any) -> argparse.Namespace:
    defaults = {"tls_cert": None, "foxglove": None, "foxglove_host": "127.0.0.1"}
    return argparse.Namespace(**{**defaults, **values})


def test_serve_warns_when_it_listens_beyond_loopback_unprotected(tmp_path: Path) -> None:
    assert warn_about_exposure(_setup(["tcp/127.0.0.1:7447"]), _args()) == []
    open_wide = warn_about_exposure(_setup(["tcp/0.0.0.0:7447"]), _args())
    assert len(open_wide) == 1
    assert "listening on tcp/0.0.0.0:7447, beyond this machine" in open_wide[0]
    assert "in the clear (passwords, connection tokens and data readable" in open_wide[0]
    assert "open to anyone who reaches it" in open_wide[0]
    certs = _certificates(tmp_path, days=300)
    tls_args = _args(tls_cert=certs["cert"])
    guarded = _setup(["tls/0.0.0.0:7448"], **{"access_control/enabled": True})
    assert warn_about_exposure(guarded, tls_args) == []
    tls_only = warn_about_exposure(_setup(["tls/0.0.0.0:7448"]), tls_args)
    assert len(tls_only) == 1 and "in the clear" not in tls_only[0]
    assert "open to anyone" in tls_only[0]
    view = warn_about_exposure(
        _setup(["tcp/127.0.0.1:7447"]), _args(foxglove=8765, foxglove_host="0.0.0.0")
    )
    assert len(view) == 1 and "no authentication" in view[0]


def test_serve_warns_about_a_certificate_that_ends_soon_or_has(tmp_path: Path) -> None:
    setup = _setup(["tls/127.0.0.1:7448"], **{"access_control/enabled": True})
    soon = _certificates(tmp_path / "soon", days=10)
    said = warn_about_exposure(setup, _args(tls_cert=soon["cert"]))
    assert len(said) == 1 and "expires on" in said[0] and "(in 10 day(s))" in said[0]
    later = _certificates(tmp_path / "later", days=60)
    assert warn_about_exposure(setup, _args(tls_cert=later["cert"])) == []
    old = _certificates(tmp_path / "old", days=-2)
    said = warn_about_exposure(setup, _args(tls_cert=old["cert"]))
    assert len(said) == 1 and "expired on" in said[0] and "every client will refuse" in said[0]


def test_a_certificates_end_is_read_with_or_without_cryptography(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from biris_hw.io.net.probe import certificate_not_after

    cert = _certificates(tmp_path, days=5)["cert"]
    ends = certificate_not_after(cert)
    assert datetime.timedelta(days=4) < ends - datetime.datetime.now(datetime.timezone.utc)
    monkeypatch.setitem(sys.modules, "cryptography", None)  # not installed: the ssl module's
    assert certificate_not_after(cert) == ends.replace(microsecond=0)


def test_the_checked_flags_are_what_the_service_gets(tmp_path: Path) -> None:
    certs = _certificates(tmp_path)
    credentials = tmp_path / "service.toml"
    credentials.write_text('[controllers]\nop = "pw"\n[readers]\nme = "r"\n')
    credentials.chmod(0o640)  # the service's group may read it
    where = endpoint(free_port(), "tls")
    argv = ["serve", "--sim", "--listen", where, "--credentials", str(credentials)]
    argv += ["--tls-cert", str(certs["cert"]), "--tls-key", str(certs["key"])]
    argv += ["--zenoh-option", "scouting/delay=0"]  # with --sim as with every source
    setup = check_service_flags(build_parser("serve").parse_args(argv))
    assert setup.options["scouting/delay"] == 0
    assert setup.listen == [where]
    assert setup.controllers == {"op": "pw"} and setup.readers == {"me": "r"}
    assert setup.options["transport/link/tls/listen_certificate"] == str(certs["cert"])
    assert setup.multicast is False  # credentials: not announced unless --multicast


# -- secrets other users may read ------------------------------------------------------------------


@pytest.mark.skipif(os.name != "posix", reason="file modes")
def test_a_secret_file_open_to_others_is_refused(tmp_path: Path) -> None:
    secret = tmp_path / "secret"
    secret.write_text("x")
    for mode in (0o600, 0o400, 0o640):
        secret.chmod(mode)
        assert check_private_file("--credentials", secret) == secret
    for mode, what in ((0o644, "read"), (0o620, "change"), (0o606, "read and change")):
        secret.chmod(mode)
        with pytest.raises(SetupError) as refused:
            check_private_file("--credentials", secret)
        assert str(refused.value) == (
            f"--credentials {secret}: mode {mode:04o} lets other users {what} it, and it holds "
            f"secrets: chmod 600 {secret}"
        )
    with pytest.raises(SetupError, match="nosuch: no such file"):
        check_private_file("--credentials", tmp_path / "nosuch")


def test_a_client_refuses_open_secret_files_before_the_network(
    biris: Run, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    credentials = tmp_path / "me.toml"
    credentials.write_text('user = "op"\npassword = "pw"\n')
    credentials.chmod(0o666)
    closed = endpoint(free_port())
    code, _, err = biris(
        "home", "--connect", "h", "--endpoint", closed, "--credentials", str(credentials)
    )
    assert code == 2
    assert "mode 0666 lets other users read and change it" in err and "chmod 600" in err
    link = tmp_path / "link.txt"
    link.write_text("pw\n")
    link.chmod(0o644)
    code, _, err = biris(
        "home", "--connect", "h", "--endpoint", closed, "--link-user", "robot",
        "--link-password-file", str(link),
    )  # fmt: skip
    assert code == 2 and "--link-password-file" in err and "mode 0644" in err


# -- mistakes told at once -------------------------------------------------------------------------


def _timed(biris: Run, *argv: str) -> tuple[int, str, float]:
    started = time.monotonic()
    code, _, err = biris(*argv)
    return code, err.strip(), time.monotonic() - started


def test_a_refused_connection_is_said_at_once(biris: Run) -> None:
    closed = endpoint(free_port())
    code, err, took = _timed(
        biris, "watch", "--connect", "h", "--endpoint", closed, "--duration", "1"
    )
    assert code == 2
    assert err == (
        f"biris watch: no BIRIS service 'h' can be reached: {closed}: connection refused "
        "(nothing listens there)"
    )
    assert took < PROMPT_S


def test_a_malformed_endpoint_or_a_missing_ca_is_named(biris: Run, tmp_path: Path) -> None:
    code, err, _ = _timed(biris, "watch", "--connect", "h", "--endpoint", "tcp/127.0.0.1:x")
    assert code == 2 and err.endswith("endpoint tcp/127.0.0.1:x: 'x' is not a port number")
    code, err, _ = _timed(biris, "watch", "--connect", "h", "--endpoint", "foo")
    assert code == 2 and "Endpoints must be of the form" in err
    assert ".rs" not in err and "Json5Err" not in err
    missing = tmp_path / "nosuch.pem"
    where = endpoint(free_port(), "tls")
    code, err, _ = _timed(
        biris, "watch", "--connect", "t", "--endpoint", where, "--tls-ca", str(missing)
    )
    assert (code, err) == (2, f"biris watch: --tls-ca {missing}: no such file")


def test_another_services_name_is_said(
    biris: Run, services: dict[str, Any], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr("biris_hw.io.net.remote.LOOK_S", 0.3)  # when the names are looked at
    code, err, took = _timed(
        biris, "watch", "--connect", "nosuch", "--endpoint", services["plain"], "--duration", "1"
    )
    assert code == 2
    assert err.startswith(
        f"biris watch: no BIRIS service 'nosuch' on {services['plain']}: the service there is 'h' "
        "(--connect h;"
    )
    assert took < PROMPT_S


def test_tls_mistakes_are_said_with_their_reason(
    biris: Run, services: dict[str, Any], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr("biris_hw.io.net.probe.HANDSHAKE_S", 0.5)  # the plain port's wait
    monkeypatch.setattr("biris_hw.io.net.remote.LOOK_S", 0.3)  # when a link is looked for
    tls, plain, old = services["tls"], services["plain"], services["old"]
    good, other = str(services["good"]["ca"]), str(services["other"]["ca"])
    expired = str(services["expired"]["ca"])
    cases = [
        ("t", tls, [], "unable to get local issuer certificate (give --tls-ca FILE"),
        ("t", tls, ["--tls-ca", other], f"(the service's certificate is not signed by {other})"),
        ("x", old, ["--tls-ca", expired], "certificate verify failed: certificate has expired"),
        ("h", plain.replace("tcp/", "tls/"), ["--tls-ca", good], "no TLS answer within"),
        ("t", tls.replace("tls/", "tcp/"), [], "is a TLS port: connect to tls/"),
    ]
    for name, where, flags, said in cases:
        code, err, took = _timed(
            biris, "watch", "--connect", name, "--endpoint", where, *flags, "--duration", "1"
        )
        assert code == 2, (where, flags, err)
        assert err.startswith(f"biris watch: no BIRIS service {name!r} can be reached: "), err
        assert said in err, (said, err)
        assert took < PROMPT_S, (where, took)


def test_the_right_ca_connects(services: dict[str, Any]) -> None:
    ca = tls_options(root_ca=str(services["good"]["ca"]))
    with connect("t", [services["tls"]], multicast=False, options=ca) as remote:
        assert remote.status()["state"] == "idle"


def test_a_library_client_waits_through_a_refusal_then_names_it() -> None:
    """``connect`` expects a service that may be starting; when it has not come by the
    timeout, the refusal is the reason given."""
    closed = endpoint(free_port())
    with pytest.raises(ConnectionClosed) as ended:
        connect("h", [closed], multicast=False, timeout=0.3)
    assert str(ended.value) == (
        f"no BIRIS service 'h' answered within 0.3 s ({closed}): {closed}: connection refused "
        "(nothing listens there)"
    )


def test_wrong_credentials_are_told_from_none(services: dict[str, Any]) -> None:
    def stop_scan(**credentials: str) -> None:
        with (
            connect("h", [services["plain"]], multicast=False, **credentials) as remote,
            remote.open() as conn,
        ):
            conn.stop_scan()

    with pytest.raises(AccessDenied) as refused:
        stop_scan(user="op", password="wrong")
    assert "the service refused the credentials of user 'op'" in str(refused.value)
    assert "nothing was done" in str(refused.value)
    with pytest.raises(AccessDenied) as refused:
        stop_scan()
    assert "needs a controller's credentials" in str(refused.value)
    stop_scan(user="op", password="s3cret")  # the right ones do


def test_rust_source_paths_never_reach_a_message() -> None:
    zenoh_error = (
        "Can not create a new TCP listener bound to tcp/127.0.0.1:7447: [127.0.0.1:7447: Address "
        "already in use (os error 98) at /root/.cargo/git/checkouts/zenoh-9c5/cc8/io/zenoh-links"
        "/zenoh-link-tcp/src/unicast.rs:61.] at /root/.cargo/git/checkouts/zenoh-9c5/cc8/zenoh/"
        "src/net/runtime/orchestrator.rs:447."
    )
    cleaned = (
        "Can not create a new TCP listener bound to tcp/127.0.0.1:7447: [127.0.0.1:7447: Address "
        "already in use (os error 98)]"
    )
    assert zenoh_message(zenoh_error) == cleaned
    assert error_line(RuntimeError(zenoh_error)).endswith(cleaned + " (--debug shows where)")
    wrapped = (
        'Json5Err(Message { msg: "Endpoints must be of the form x: foo", location: '
        "Some(Location { line: 1, column: 2 }) })"
    )
    assert zenoh_message(wrapped) == "Endpoints must be of the form x: foo"


# -- record's progress line ------------------------------------------------------------------------


def test_the_status_line_is_drawn_in_place_and_gives_way() -> None:
    err = io.StringIO()
    shown = iter(["1 s, 2 scans", "2 s, 5 scans"])
    with StatusLine("biris record", lambda: next(shown), every_s=3600, err=err) as line:
        line.draw()
        StatusLine.write_above(err, "biris: warning: a short scan\n")
        line.draw()
    assert err.getvalue() == (
        "\r\x1b[Kbiris record: 1 s, 2 scans"
        "\r\x1b[Kbiris: warning: a short scan\n"
        "\r\x1b[Kbiris record: 2 s, 5 scans"
        "\r\x1b[K"  # erased at the end: the summary starts on a clean line
    )
    StatusLine.write_above(err, "after\n")  # none shown any more: written as it is
    assert err.getvalue().endswith("\r\x1b[Kafter\n")


def test_record_shows_its_progress_on_a_terminal_only(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    assert progress_text(12.3, 37, 1_234_567, 2) == "12 s, 37 scans, 1.2 MB, dropped 2"
    out = tmp_path / "run.mcap"
    out.write_bytes(b"x" * 250_000)
    recorder = argparse.Namespace(scans=3, dropped_points=1, dropped_scans=0)
    args = argparse.Namespace(out=str(out), command="record", quiet=False, debug=False)
    err = io.StringIO()
    monkeypatch.setattr("sys.stderr", err)
    shown: list[StatusLine | None] = []
    with _progress(args, recorder):  # type: ignore[arg-type]
        shown.append(StatusLine._current)
    assert shown == [None]  # a StringIO is no terminal: no line
    monkeypatch.setattr("biris_hw.commands.record.wants_progress", lambda a: True)
    with _progress(args, recorder):  # type: ignore[arg-type]
        shown.append(StatusLine._current)
        line = shown[-1]
        assert line is not None
        line.draw()
    assert "biris record: 0 s, 3 scans, 0.2 MB, dropped 1" in err.getvalue()
    assert err.getvalue().endswith("\r\x1b[K")

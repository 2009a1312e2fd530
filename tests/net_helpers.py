"""Helpers for the network-service tests: free ports, a service or a client in another process.

Run as a program (``python -m tests.net_helpers ROLE ...``) it is that other process:

* ``serve --port P --name N [--controllers USER:PW] [--tls DIR] [--samples S]`` -- a simulator,
  a server and the service, printing ``ready`` once it serves, until killed or stdin closes;
* ``cli-serve ARGS...`` -- ``biris serve ARGS`` (the command module, whatever cli.py lists);
* ``reader --endpoint E --name N --scans K`` -- subscribes to scans and reads K through a DATA
  connection, tries a motion request, prints one JSON line of what it saw;
* ``controller --endpoint E --name N --user U --password P`` -- opens connections, starts a
  continuous scan, prints ``scanning``, then waits to be killed.

Every wait is bounded by an event or a subprocess read with a timeout, never a sleep.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import queue
import signal
import socket
import subprocess
import sys
import threading
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent

START_S = 30.0
"""Longest a helper process may take to say it is ready (a slow CI host)."""


def free_port() -> int:
    """A TCP port on loopback nobody listens on now (the service binds it a moment later)."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def endpoint(port: int, scheme: str = "tcp", host: str = "127.0.0.1") -> str:
    return f"{scheme}/{host}:{port}"


class Helper:
    """A helper process whose stdout lines arrive on a queue (read by a thread of ours)."""

    def __init__(self, args: Sequence[str], env: dict[str, str] | None = None) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "tests.net_helpers", *args],
            cwd=ROOT,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env={**os.environ, **(env or {})},
        )
        self.lines: queue.Queue[str | None] = queue.Queue()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.put(line.rstrip("\n"))
        self.lines.put(None)

    def expect(self, prefix: str, timeout: float = START_S) -> str:
        """The next stdout line starting with ``prefix``; fails with the helper's stderr."""
        while True:
            try:
                line = self.lines.get(timeout=timeout)
            except queue.Empty:
                raise AssertionError(
                    f"helper said nothing like {prefix!r} in {timeout} s"
                ) from None
            if line is None:
                err = self.proc.stderr.read() if self.proc.stderr else ""
                raise AssertionError(f"helper ended before {prefix!r}:\n{err}")
            if line.startswith(prefix):
                return line

    def kill(self) -> None:
        """SIGKILL: the process vanishes without closing anything."""
        if self.proc.poll() is None:
            self.proc.kill()
        self.close()

    def close(self, timeout: float = START_S) -> int:
        """Ask it to end (stdin closed, then SIGTERM) and reap it."""
        if self.proc.poll() is None:
            if self.proc.stdin is not None:
                with contextlib.suppress(OSError):
                    self.proc.stdin.close()
            self.proc.terminate()  # biris serve ends on SIGTERM; the roles raise KeyboardInterrupt
            try:
                self.proc.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
        code = self.proc.wait(timeout=timeout)
        self._reader.join(timeout)
        for stream in (self.proc.stdout, self.proc.stderr, self.proc.stdin):
            if stream is not None:
                with contextlib.suppress(OSError):
                    stream.close()
        return code


@contextlib.contextmanager
def service_process(*args: str) -> Iterator[Helper]:
    """A service in another process, ready when the block begins, ended when it ends."""
    helper = Helper(["serve", *args])
    try:
        helper.expect("ready")
        yield helper
    finally:
        helper.close()


def make_tls(folder: Path) -> dict[str, Path]:
    """A CA and a server certificate for localhost/127.0.0.1, made by the test (the
    ``cryptography`` package, a dev dependency: no openssl command needed on the machine)."""
    import datetime
    import ipaddress

    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    now = datetime.datetime.now(datetime.timezone.utc)
    later = now + datetime.timedelta(days=2)
    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "biris-test-ca")])
    ca_cert = (
        x509.CertificateBuilder()
        .subject_name(ca_name)
        .issuer_name(ca_name)
        .public_key(ca_key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(later)
        .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True, content_commitment=False, key_encipherment=False,
                data_encipherment=False, key_agreement=False, key_cert_sign=True,
                crl_sign=True, encipher_only=False, decipher_only=False,
            ),
            critical=True,
        )
        .sign(ca_key, hashes.SHA256())
    )  # fmt: skip
    key = ec.generate_private_key(ec.SECP256R1())
    cert = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "localhost")]))
        .issuer_name(ca_name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(later)
        .add_extension(
            x509.SubjectAlternativeName(
                [x509.DNSName("localhost"), x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]
            ),
            critical=False,
        )
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .sign(ca_key, hashes.SHA256())
    )
    paths = {"ca": folder / "ca.pem", "cert": folder / "server.pem", "key": folder / "server.key"}
    paths["ca"].write_bytes(ca_cert.public_bytes(serialization.Encoding.PEM))
    paths["cert"].write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    paths["key"].write_bytes(
        key.private_bytes(
            serialization.Encoding.PEM,
            serialization.PrivateFormat.PKCS8,
            serialization.NoEncryption(),
        )
    )
    return paths


# -- the roles, when run as a program --------------------------------------------------------------


def _serve(argv: Sequence[str]) -> None:
    from biris_hw import BirisInitRecord, BirisServer
    from biris_hw.io.net import serve
    from sim import Scene, SimulatedBiris

    parser = argparse.ArgumentParser()
    parser.add_argument("--port", type=int, required=True)
    parser.add_argument("--name", default="biris0")
    parser.add_argument("--controllers", nargs="*", default=[])
    parser.add_argument("--tls", type=Path)
    parser.add_argument("--samples", type=int, default=64)
    # x10: a loaded host late by 0.1 s stays far inside every deadline
    parser.add_argument("--time-scale", type=float, default=10.0)
    args = parser.parse_args(argv)
    controllers = dict(item.split(":", 1) for item in args.controllers)
    options = {}
    scheme = "tcp"
    if args.tls is not None:
        scheme = "tls"
        options = {
            "transport/link/tls/listen_certificate": str(args.tls / "server.pem"),
            "transport/link/tls/listen_private_key": str(args.tls / "server.key"),
        }
    host = "localhost" if args.tls is not None else "127.0.0.1"
    rig = SimulatedBiris(
        scene=Scene.circle(2.0), samples=args.samples, time_scale=args.time_scale, seed=3
    )
    with (
        rig.start(),
        BirisServer(rig.hardware, BirisInitRecord()) as server,
        serve(
            server,
            name=args.name,
            listen=[endpoint(args.port, scheme, host)],
            controllers=controllers,
            multicast=False,
            options=options,
        ),
    ):
        print("ready", flush=True)
        with contextlib.suppress(KeyboardInterrupt):  # SIGTERM: leave through the with blocks
            sys.stdin.read()  # until the test closes our stdin (or kills us)
        _STOPPING.set()  # on the way out: a SIGTERM now must not cut the service's close short


def _cli_serve(argv: Sequence[str]) -> None:
    """``biris serve ARGV`` as the CLI runs it: its own SIGTERM handling (exit 143) included."""
    from biris_hw.cli import main as cli_main

    raise SystemExit(cli_main(["serve", *argv]))


def _reader(argv: Sequence[str]) -> None:
    from biris_hw import ConnectionKind
    from biris_hw.data import DeliveryPolicy
    from biris_hw.errors import AccessDenied
    from biris_hw.io.net import connect

    parser = argparse.ArgumentParser()
    parser.add_argument("--endpoint", required=True)
    parser.add_argument("--name", default="biris0")
    parser.add_argument("--scans", type=int, default=2)
    args = parser.parse_args(argv)
    published: queue.Queue[int] = queue.Queue()
    with connect(args.name, [args.endpoint], multicast=False) as remote:
        subscription = remote.subscribe("scan", lambda scan: published.put(scan.seq))
        data = remote.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_BUFFER)
        print("listening", flush=True)
        pulled = [(int(s.direction), s.seq, s.n_acq) for s in _scans(data, args.scans)]
        seen = [published.get(timeout=START_S) for _ in range(args.scans)]
        denied = False
        try:
            remote.open().single_scan(10.0)
        except AccessDenied:
            denied = True
        subscription.close()
        print(json.dumps({"pulled": pulled, "published": seen, "denied": denied}), flush=True)


def _scans(data: Any, n: int) -> Iterator[Any]:
    for _ in range(n):
        yield data.ready_for_data(timeout=START_S)


def _controller(argv: Sequence[str]) -> None:
    from biris_hw import ConnectionKind
    from biris_hw.io.net import connect

    parser = argparse.ArgumentParser()
    parser.add_argument("--endpoint", required=True)
    parser.add_argument("--name", default="biris0")
    parser.add_argument("--user", required=True)
    args = parser.parse_args(argv)
    password = os.environ["BIRIS_PASSWORD"]
    remote = connect(args.name, [args.endpoint], args.user, password, multicast=False)
    conn = remote.open()
    remote.open(ConnectionKind.DATA)
    conn.continuous_scan(-30.0, 30.0)
    print("scanning", flush=True)
    sys.stdin.read()  # until killed


_STOPPING = threading.Event()


def _on_term(signum: int, frame: object) -> None:
    """SIGTERM: a KeyboardInterrupt the first time, while the role waits; ignored once it is
    leaving (Helper.close closes stdin and then terminates: both arrive together, and an
    interrupt in the middle of the service's close would leave its threads and session up)."""
    if not _STOPPING.is_set():
        _STOPPING.set()
        from biris_hw.commands.failures import Terminated

        raise Terminated  # a KeyboardInterrupt that CPython does not turn into death by SIGINT


def main(argv: Sequence[str]) -> None:
    signal.signal(signal.SIGTERM, _on_term)
    roles = {"serve": _serve, "cli-serve": _cli_serve, "reader": _reader, "controller": _controller}
    roles[argv[0]](argv[1:])


if __name__ == "__main__":
    main(sys.argv[1:])


class _NoSensor:
    """A sensor that is already closed: enough for a service to start and stop."""

    playback = False
    paced = True
    record = None

    def clock(self) -> float:
        return 0.0

    def open(self, *args: object, **kwargs: object) -> object:
        from biris_hw.errors import ConnectionClosed

        raise ConnectionClosed("no sensor")

    def status(self, **_wait: object) -> object:
        from biris_hw.errors import ConnectionClosed

        raise ConnectionClosed("no sensor")

    def close(self) -> None:
        pass


class FakeSensor:
    """A sensor in memory, for the service's fast tests (no simulator, no homing).

    Its connections record every call in :attr:`calls`. The service's own EVERY_BUFFER feed
    takes what :meth:`feed` is given (a Scan, or an exception to raise); a LATEST DATA
    connection's ``ready_for_data`` blocks (counted in :attr:`blocked`) until :meth:`free`, its
    timeout or its close; ``reset`` takes :attr:`reset_s` seconds, then raises
    :attr:`reset_fault` if set. Its status never changes: a wait for a newer one lasts its
    timeout (or until its connection closes). Every wait is on one condition, woken by whatever
    ends it.
    """

    playback = False
    paced = True
    record = None

    def __init__(self) -> None:
        self.cond = threading.Condition()
        self.scans: list[Any] = []
        self.freed = False
        self.calls: list[str] = []
        self.opened: list[FakeConnection] = []
        self.reset_s = 0.0
        self.reset_fault: BaseException | None = None
        self.blocked = 0
        self.status_error: BaseException | None = None
        self._next = 1

    def feed(self, item: Any) -> None:
        with self.cond:
            self.scans.append(item)
            self.cond.notify_all()

    def free(self) -> None:
        """End every blocked read (and any later one at once)."""
        with self.cond:
            self.freed = True
            self.cond.notify_all()

    def open(self, kind: Any = None, *, policy: Any = None, depth: int | None = None) -> Any:
        from biris_hw.data import ConnectionKind, DeliveryPolicy

        with self.cond:
            conn = FakeConnection(
                self,
                self._next,
                kind or ConnectionKind.NORMAL,
                policy or DeliveryPolicy.LATEST,
                depth or 8,
            )
            self._next += 1
            self.opened.append(conn)
        return conn

    def clock(self) -> float:
        return 0.0

    def status(self, *, newer_than: int | None = None, timeout: float | None = None) -> Any:
        from tests.conftest import idle_status

        if newer_than is not None:
            with self.cond:
                self.cond.wait(timeout)
            raise TimeoutError("the fake's status never changes")
        if self.status_error is not None:
            error, self.status_error = self.status_error, None
            raise error
        return idle_status()

    def close(self) -> None:
        pass


class FakeConnection:
    """One connection of a :class:`FakeSensor`."""

    def __init__(self, sensor: FakeSensor, ident: int, kind: Any, policy: Any, depth: int) -> None:
        self.sensor = sensor
        self.ident = ident
        self.kind = kind
        self.policy = policy
        self.depth = depth
        self.dropped = 0
        self.closed = False

    def _record(self, what: str) -> None:
        from biris_hw.errors import ConnectionClosed

        with self.sensor.cond:
            if self.closed:
                raise ConnectionClosed(f"connection {self.ident} is closed")
            self.sensor.calls.append(what)
            self.sensor.cond.notify_all()

    def ready_for_data(self, timeout: float | None = None) -> Any:
        from biris_hw.data import DeliveryPolicy
        from biris_hw.errors import ConnectionClosed

        sensor = self.sensor
        with sensor.cond:
            if self.policy is DeliveryPolicy.EVERY_BUFFER:  # the service's scan feed
                sensor.cond.wait_for(lambda: self.closed or bool(sensor.scans), timeout)
                if self.closed:
                    raise ConnectionClosed(f"connection {self.ident} is closed")
                if not sensor.scans:
                    raise TimeoutError("no scan")
                item = sensor.scans.pop(0)
                if isinstance(item, BaseException):
                    raise item
                return item
            if self.policy is DeliveryPolicy.LATEST:  # a remote reader: blocks until freed
                sensor.calls.append("ready_for_data")
                sensor.blocked += 1
                sensor.cond.notify_all()
                try:
                    sensor.cond.wait_for(lambda: self.closed or sensor.freed, timeout)
                finally:
                    sensor.blocked -= 1
                raise TimeoutError("nothing")
            sensor.cond.wait_for(lambda: self.closed, timeout)  # the point feed: nothing comes
            if self.closed:
                raise ConnectionClosed(f"connection {self.ident} is closed")
            raise TimeoutError("no point")

    def status(self, *, newer_than: int | None = None, timeout: float | None = None) -> Any:
        from biris_hw.errors import ConnectionClosed

        if newer_than is not None:  # never changes: waits out its timeout, or its close
            with self.sensor.cond:
                self.sensor.cond.wait_for(lambda: self.closed, timeout)
            if self.closed:
                raise ConnectionClosed(f"connection {self.ident} is closed")
            raise TimeoutError("the fake's status never changes")
        return self.sensor.status()

    def request_point(self) -> None:
        self._record("request_point")

    def stop_scan(self) -> None:
        self._record("stop_scan")

    def continuous_scan(self, cw: float, ccw: float) -> tuple[int, int]:
        self._record("continuous_scan")
        return -1, 1

    def reset(self) -> None:
        self._record("reset")
        with self.sensor.cond:  # the time an initialisation takes (or until closed)
            self.sensor.cond.wait_for(lambda: self.closed, self.sensor.reset_s)
        if self.sensor.reset_fault is not None:
            raise self.sensor.reset_fault

    def close(self) -> None:
        with self.sensor.cond:
            self.closed = True
            self.sensor.cond.notify_all()

    def __enter__(self) -> FakeConnection:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


_warm = False


def warm_up_zenoh() -> None:
    """Zenoh starts its runtimes (threads, epoll and eventfd descriptors) on first use and keeps
    them for the life of the process. Start them once, before a test's leak check takes its
    snapshot, so that they are not taken for the leak of whichever test came first."""
    global _warm
    if _warm:
        return
    from biris_hw.io.net import connect, serve

    where = endpoint(free_port())
    with serve(_NoSensor(), name="warmup", listen=[where], multicast=False):  # type: ignore[arg-type]
        connect("warmup", [where], multicast=False).close()
    _warm = True

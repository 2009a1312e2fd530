"""The network service across processes (slow tier): the service in one process, clients in
others, over loopback TCP (and TLS) with multicast scouting off."""

from __future__ import annotations

import argparse
import io
import json
import os
import shlex
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from biris_hw import ConnectionKind
from biris_hw.data import DeliveryPolicy
from biris_hw.errors import ConnectionClosed, ConnectionLost
from biris_hw.io.net import connect, tls_options
from tests.conftest import until
from tests.net_helpers import (
    ROOT,
    Helper,
    endpoint,
    free_port,
    make_tls,
    service_process,
    warm_up_zenoh,
)

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module", autouse=True)
def _zenoh_runtime() -> None:
    warm_up_zenoh()


def test_two_readers_and_a_controller(no_leaks: None) -> None:
    port = free_port()
    where = endpoint(port)
    with service_process("--port", str(port), "--controllers", "op:pw"):
        readers = [Helper(["reader", "--endpoint", where, "--scans", "2"]) for _ in range(2)]
        try:
            for reader in readers:
                reader.expect("listening")
            with connect("biris0", [where], "op", "pw", multicast=False) as remote:
                conn = remote.open()
                conn.continuous_scan(-20.0, 20.0)
                results = [json.loads(reader.expect("{")) for reader in readers]
                conn.stop_scan()
                conn.wait_idle(timeout=30)
        finally:
            for reader in readers:
                reader.close()
    for result in results:
        assert len(result["pulled"]) == 2 and len(result["published"]) == 2
        assert result["denied"] is True  # a reader is refused control
    assert results[0]["pulled"] == results[1]["pulled"]  # both saw the same scans


def test_controller_vanishes_mid_scan(no_leaks: None) -> None:
    port = free_port()
    where = endpoint(port)
    with (
        service_process("--port", str(port), "--controllers", "op:pw"),
        connect("biris0", [where], multicast=False) as observer,
    ):
        before = len(observer.status().connections)
        controller = Helper(
            ["controller", "--endpoint", where, "--user", "op"], env={"BIRIS_PASSWORD": "pw"}
        )
        try:
            controller.expect("scanning")
            assert len(observer.status().connections) == before + 2
            controller.kill()  # no CLOSE_REQUEST: the service must notice on its own
        finally:
            controller.close()
        until(
            lambda: len(observer.status().connections) == before,
            timeout=10,
            what="the vanished controller's connections released",
        )
        assert observer.status().continuous  # its scan goes on; another controller may stop it
        with connect("biris0", [where], "op", "pw", multicast=False) as second:
            conn = second.open()
            conn.stop_scan()
            conn.wait_idle(timeout=30)
            assert not second.status().continuous


def test_service_killed_clients_get_a_clear_error_in_bounded_time(no_leaks: None) -> None:
    port = free_port()
    where = endpoint(port)
    helper = Helper(["serve", "--port", str(port)])
    try:
        helper.expect("ready")
        remote = connect("biris0", [where], multicast=False)
        data = remote.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_BUFFER)
        outcome: list[BaseException] = []
        waiting = threading.Event()

        def wait_for_data() -> None:
            waiting.set()
            try:
                data.ready_for_data(timeout=None)  # nothing will come: nobody scans
            except BaseException as exc:
                outcome.append(exc)

        thread = threading.Thread(target=wait_for_data)
        thread.start()
        assert waiting.wait(5)
        killed = time.monotonic()
        helper.kill()
        thread.join(timeout=15)
        took = time.monotonic() - killed
        assert not thread.is_alive()
        assert outcome and isinstance(outcome[0], ConnectionLost), outcome  # it may come back
        assert took < 6.0, took  # at once when the link drops; MAX_WAIT_S at worst
        with pytest.raises(ConnectionLost):
            remote.status()
        remote.close()
    finally:
        helper.close()


@pytest.mark.skipif(shutil.which("openssl") is None, reason="needs the openssl CLI")
def test_tls(tmp_path: Path, no_leaks: None) -> None:
    files = make_tls(tmp_path)
    port = free_port()
    where = endpoint(port, "tls", "localhost")
    with service_process("--port", str(port), "--tls", str(tmp_path), "--controllers", "op:pw"):
        options = tls_options(root_ca=str(files["ca"]))
        with connect("biris0", [where], "op", "pw", multicast=False, options=options) as remote:
            conn = remote.open()
            assert conn.single_scan(10.0) == 114
            conn.wait_idle(timeout=30)
            assert remote.status()["state"] == "idle"
        with pytest.raises(ConnectionClosed):  # no CA: the certificate is not trusted
            connect("biris0", [where], multicast=False, timeout=1.0)


def test_cli_serve_and_watch_connect(tmp_path: Path, no_leaks: None) -> None:
    """``biris serve --sim`` in another process; ``biris watch --connect`` shows it, fast: no
    server of its own, so no homing."""
    from biris_hw.commands import watch

    port = free_port()
    where = endpoint(port)
    credentials = tmp_path / "service.toml"
    credentials.write_text('[controllers]\nop = "pw"\n')
    credentials.chmod(0o600)  # a secret others may read is refused
    serve = Helper(
        [
            "cli-serve",
            "--sim",
            "--time-scale",
            "30",
            "--name",
            "cli0",
            "--listen",
            where,
            "--credentials",
            str(credentials),
            "--no-multicast",
        ]
    )
    try:
        serve.expect("serving cli0")
        parser = argparse.ArgumentParser()
        watch.add_arguments(parser)
        args = parser.parse_args(
            ["--connect", "cli0", "--endpoint", where, "--duration", "0.3", "--interval", "0.1"]
        )
        args.command = "watch"
        out = io.StringIO()
        started = time.monotonic()
        assert watch.run(args, out) == 0
        assert time.monotonic() - started < 5.0
        assert "idle" in out.getvalue()
    finally:
        assert serve.close() == 143  # SIGTERM ends biris serve as Ctrl-C does: 128 + 15


def _readme_two_terminals() -> list[str]:
    """The command lines of README.md's "Two terminals" example, as written."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    section = text.split("### Two terminals", 1)[1]
    block = section.split("```sh", 1)[1].split("```", 1)[0]
    return [
        line.strip()
        for line in block.splitlines()
        if line.strip() and not line.lstrip().startswith("#")
    ]


def test_readme_two_terminal_example_runs_as_written(tmp_path: Path, no_leaks: None) -> None:
    """README.md, "On your robot in five minutes", "Two terminals": each command as written
    (the port substituted, `biris` the installed command), in a folder of its own."""
    lines = _readme_two_terminals()
    assert len(lines) == 4, lines
    setup, serve_line, watch_line, scan_line = lines
    port = str(free_port())
    bindir = str(Path(sys.executable).parent)
    env = {**os.environ, "PATH": bindir + os.pathsep + os.environ.get("PATH", "")}
    env.pop("BIRIS_PASSWORD", None)

    def words(line: str) -> tuple[dict[str, str], list[str]]:
        """A line's leading NAME=value assignments and its words, the port substituted."""
        found = shlex.split(line.replace("7447", port))
        assignments = {}
        while found and "=" in found[0] and not found[0].startswith("-"):
            name, _, value = found.pop(0).partition("=")
            assignments[name] = value
        assert found[0] == "biris", line
        return assignments, [str(Path(bindir) / "biris"), *found[1:]]

    subprocess.run(["bash", "-c", setup], cwd=tmp_path, env=env, check=True, timeout=30)
    assert "--no-multicast" in serve_line and "7447" in serve_line
    _, serve_argv = words(serve_line)
    service = subprocess.Popen(
        serve_argv, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    try:
        assert service.stdout is not None
        first = service.stdout.readline()  # "serving biris0 on ..." once it serves
        assert first.startswith("serving biris0"), (first, service.stderr and service.stderr.read())
        extra, watch_argv = words(watch_line)
        watched = subprocess.run(
            watch_argv, cwd=tmp_path, env={**env, **extra}, capture_output=True, text=True,
            timeout=60,
        )  # fmt: skip
        assert watched.returncode == 0, watched.stderr
        assert "idle" in watched.stdout, watched.stdout
        extra, scan_argv = words(scan_line)
        assert extra == {"BIRIS_PASSWORD": "change-me"}
        scanned = subprocess.run(
            scan_argv, cwd=tmp_path, env={**env, **extra}, capture_output=True, text=True,
            timeout=120,
        )  # fmt: skip
        assert scanned.returncode == 0, scanned.stderr
        assert "CCW" in scanned.stdout or "ccw" in scanned.stdout.lower(), scanned.stdout
    finally:
        if service.poll() is None:
            service.send_signal(signal.SIGTERM)
        try:
            code = service.wait(timeout=60)
        finally:
            if service.poll() is None:
                service.kill()
            for stream in (service.stdout, service.stderr):
                if stream is not None:
                    stream.close()
    assert code == 143  # SIGTERM: 128 + 15, the documented status

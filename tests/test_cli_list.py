"""``biris list``: the services reachable, with name, state, controller and clients (fast tier:
FakeSensor services on loopback).

Two services behind their endpoints are listed by name, with their state and what they serve;
a service whose reading needs credentials says so, and answers with them; a client connected
counts; ``--json`` says the same; an endpoint that cannot be reached is named with its reason;
a Zenoh peer that is no BIRIS service lists nothing, and says where it looked; declaring the
command loads nothing of Zenoh.
"""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Iterator
from typing import Any

import pytest
import zenoh

from biris_hw.commands.list_services import table
from biris_hw.commands.options import PASSWORD_ENV
from biris_hw.commands.profile import CONNECT_ENV, ENDPOINT_ENV, USER_ENV
from biris_hw.io.net import connect, serve
from biris_hw.io.net.discovery import ServiceInfo
from biris_hw.io.net.zconfig import make_config
from tests.conftest import Run
from tests.net_helpers import ROOT, FakeSensor, endpoint, free_port, warm_up_zenoh


@pytest.fixture(scope="module", autouse=True)
def _zenoh_runtime() -> None:
    """Zenoh's runtime started before any test's leak check looks (it lives on)."""
    warm_up_zenoh()


@pytest.fixture(autouse=True)
def _no_profile(monkeypatch: pytest.MonkeyPatch, tmp_path: Any) -> None:
    for name in (CONNECT_ENV, ENDPOINT_ENV, USER_ENV, PASSWORD_ENV):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "config"))


@pytest.fixture
def two() -> Iterator[tuple[str, str]]:
    """Service "alpha" (free reading, a controller) and "beta" (reading needs credentials)."""
    fakes = [FakeSensor(), FakeSensor()]
    sensors: list[Any] = list(fakes)  # a Sensor in all that the service uses
    first, second = endpoint(free_port()), endpoint(free_port())
    with (
        serve(sensors[0], name="alpha", listen=[first], controllers={"op": "pw"}, multicast=False),
        serve(sensors[1], name="beta", listen=[second], readers={"me": "r"}, multicast=False),
    ):
        yield first, second
    for fake in fakes:
        fake.free()


def test_the_services_behind_their_endpoints_are_listed(biris: Run, two: tuple[str, str]) -> None:
    first, second = two
    code, out, _ = biris("list", "--endpoint", first, "--endpoint", second)
    assert code == 0  # (stderr: the services in this process log the reader they refused)
    assert out.splitlines() == [
        "NAME   STATE              CONTROLLER  CLIENTS  SERVES",
        "alpha  idle               no          0        sensor",
        "beta   needs credentials  ?           ?        ?",
    ]


def test_credentials_are_sent_only_when_asked(
    biris: Run, two: tuple[str, str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv(PASSWORD_ENV, "r")

    def beta(*flags: str) -> dict[str, Any]:
        code, out, _ = biris("list", "--endpoint", two[1], "--user", "me", *flags, "--json")
        assert code == 0
        # alpha may be listed too: peers tell each other where they are (Zenoh's gossip)
        (found,) = [each for each in json.loads(out) if each["name"] == "beta"]
        assert isinstance(found, dict)
        return found

    assert beta()["state"] == "needs credentials"
    found = beta("--read-credentials")
    assert (found["state"], found["playback"]) == ("idle", False)


def test_the_profiles_endpoint_is_looked_at_and_a_controller_counts(
    biris: Run, two: tuple[str, str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv(ENDPOINT_ENV, two[0])  # the profile's endpoint, when none is given
    with (
        connect("alpha", [two[0]], multicast=False, user="op", password="pw") as remote,
        remote.open() as conn,
    ):
        conn.stop_scan()  # granted: a controller
        code, out, _ = biris("list", "--json")
    assert code == 0
    # beta may be listed too: peers tell each other where they are (Zenoh's gossip)
    (alpha,) = [each for each in json.loads(out) if each["name"] == "alpha"]
    assert isinstance(alpha["instance"], str) and alpha["instance"]
    assert (alpha["playback"], alpha["clients"], alpha["controllers"]) == (False, 1, 1)


def test_an_endpoint_that_cannot_be_reached_is_named(biris: Run) -> None:
    closed = endpoint(free_port())
    code, out, err = biris("list", "--endpoint", closed)
    assert (code, out) == (2, "")
    assert err == (
        f"biris list: no endpoint can be reached: {closed}: connection refused (nothing listens "
        "there)\n"
    )


def test_a_peer_that_is_no_biris_service_lists_nothing(biris: Run) -> None:
    where = endpoint(free_port())
    peer = zenoh.open(make_config(listen=[where]))
    try:
        code, out, err = biris("list", "--endpoint", where, "--timeout", "3")
    finally:
        peer.close()  # type: ignore[no-untyped-call]
    assert (code, out) == (0, "")
    assert err == f"biris list: no BIRIS service found ({where}, 3 s)\n"


def test_the_table_says_controllers_and_what_is_served() -> None:
    found = [
        ServiceInfo("biris0", "scanning", 1, 3, False),
        ServiceInfo("rec0", "idle", 0, 1, True),
        ServiceInfo("old", "idle", None, 0, None),
    ]
    assert table(found).splitlines() == [
        "NAME    STATE     CONTROLLER  CLIENTS  SERVES",
        "biris0  scanning  yes         3        sensor",
        "rec0    idle      no          1        recording",
        "old     idle      ?           0        ?",
    ]


def test_declaring_the_command_loads_no_zenoh() -> None:
    code = (
        "import sys; from biris_hw.cli import build_parser; build_parser('list'); "
        "print(sorted(m for m in sys.modules if m.split('.')[0] == 'zenoh' "
        "or m.startswith('biris_hw.io')))"
    )
    found = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60
    )
    assert found.returncode == 0, found.stderr
    assert found.stdout.strip() == "[]"

"""The client's profile: ``$BIRIS_CONNECT``, ``$BIRIS_ENDPOINT``, ``$BIRIS_USER`` and
``~/.config/biris/client.toml`` say once what every command would repeat (fast tier).

A flag wins over the environment, the environment over the file; a password is never read from
a profile, and a profile others may write is refused; a profile's user is used only with
``$BIRIS_PASSWORD``, and a refusal then says whose password was missing. End to end: a command
given no sensor flag uses the profile's service (a FakeSensor served on loopback).
"""

from __future__ import annotations

import argparse
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from biris_hw.cli import build_parser
from biris_hw.commands.failures import SetupError, UsageError
from biris_hw.commands.options import (
    PASSWORD_ENV,
    TARGET_ENV,
    check_target_arguments,
    connect_options,
)
from biris_hw.commands.profile import (
    CONNECT_ENV,
    ENDPOINT_ENV,
    USER_ENV,
    ClientProfile,
    load_profile,
    profile_path,
)
from biris_hw.commands.session import open_session
from biris_hw.errors import AccessDenied
from biris_hw.io.net import serve
from tests.net_helpers import FakeSensor, endpoint, free_port, warm_up_zenoh

_ENV = (CONNECT_ENV, ENDPOINT_ENV, USER_ENV, PASSWORD_ENV, TARGET_ENV)


@pytest.fixture(scope="module", autouse=True)
def _zenoh_runtime() -> None:
    """Zenoh's runtime started before any test's leak check looks (it lives on)."""
    warm_up_zenoh()


@pytest.fixture(autouse=True)
def _clean_env(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> Path:
    """No profile from the shell running the tests: its variables unset, its config folder a
    fresh one."""
    for name in _ENV:
        monkeypatch.delenv(name, raising=False)
    config = tmp_path / "config"
    monkeypatch.setenv("XDG_CONFIG_HOME", str(config))
    return config


def _write(config: Path, text: str, mode: int = 0o644) -> Path:
    file = config / "biris" / "client.toml"
    file.parent.mkdir(parents=True, exist_ok=True)
    file.write_text(text)
    file.chmod(mode)
    return file


# -- reading it ------------------------------------------------------------------------------------


def test_no_profile_is_an_empty_one(tmp_path: Path) -> None:
    assert load_profile({}, tmp_path / "none.toml") == ClientProfile()
    assert profile_path({"XDG_CONFIG_HOME": "/etc/xdg"}) == Path("/etc/xdg/biris/client.toml")
    assert profile_path({"XDG_CONFIG_HOME": "relative"}) == (
        Path.home() / ".config" / "biris" / "client.toml"
    )


def test_the_file_says_each_setting_and_the_environment_overrides_it(_clean_env: Path) -> None:
    file = _write(
        _clean_env,
        'connect = "biris0"\nendpoint = ["tls/robot:7448", "tls/robot2:7448"]\nuser = "op"\n'
        'tls_ca = "ca.pem"\ntls_cert = "~/me.pem"\ntls_key = "/keys/me.key"\n',
    )
    found = load_profile({}, file)
    assert found.connect == "biris0" and found.user == "op"
    assert found.endpoints == ("tls/robot:7448", "tls/robot2:7448")
    assert found.tls_ca == file.parent / "ca.pem"  # relative to the file's folder
    assert found.tls_cert == Path.home() / "me.pem" and found.tls_key == Path("/keys/me.key")
    env = {CONNECT_ENV: "lab1", ENDPOINT_ENV: "tcp/a:1, tcp/b:2 tcp/c:3"}
    mixed = load_profile(env, file)
    assert mixed.connect == "lab1" and mixed.user == "op"
    assert mixed.endpoints == ("tcp/a:1", "tcp/b:2", "tcp/c:3")
    assert mixed.source("connect") == f" (from ${CONNECT_ENV})"
    assert mixed.source("user") == f" (from {file})"


@pytest.mark.parametrize(
    ("text", "said"),
    [
        ('password = "x"\n', "'password': no passwords in the profile"),
        ('connect = "b"\nlink_password = "x"\n', "'link_password': no passwords in the profile"),
        ('secret = "x"\n', "'secret': no passwords"),
        ('hostname = "x"\n', "unknown key(s) hostname; known: connect, endpoint, user"),
        ('tls_cert = "me.pem"\n', "tls_cert and tls_key go together"),
        ("endpoint = 7447\n", 'endpoint = "tcp/HOST:PORT" or a list of such strings'),
        ("user = 3\n", 'user = "..." (a non-empty string)'),
        ("connect = \n", "not TOML"),
    ],
)
def test_a_profile_that_cannot_be_used_is_refused(_clean_env: Path, text: str, said: str) -> None:
    file = _write(_clean_env, text)
    with pytest.raises(SetupError) as refused:
        load_profile({}, file)
    assert str(refused.value).startswith(f"{file}: ")
    assert said in str(refused.value)


def test_a_profile_others_may_write_is_refused(_clean_env: Path) -> None:
    file = _write(_clean_env, 'connect = "biris0"\n', mode=0o664)
    with pytest.raises(SetupError) as refused:
        load_profile({}, file)
    assert str(refused.value) == (
        f"{file}: mode 0664 lets other users write it (and so choose the service your commands "
        f"use): chmod 644 {file}"
    )


# -- what the commands make of it ------------------------------------------------------------------


def _args(command: str, *argv: str) -> argparse.Namespace:
    return build_parser(command).parse_args([command, *argv])


def test_no_sensor_flag_means_the_profiles_service(
    monkeypatch: pytest.MonkeyPatch, _clean_env: Path
) -> None:
    monkeypatch.setenv(CONNECT_ENV, "lab1")
    args = _args("watch")
    check_target_arguments(args)
    assert args.connect == "lab1"
    args = _args("watch", "--sim")  # a flag wins
    check_target_arguments(args)
    assert args.connect is None and args.sim
    args = _args("watch", "--connect", "other")
    check_target_arguments(args)
    assert args.connect == "other"
    with pytest.raises(UsageError) as refused:
        check_target_arguments(_args("scan", "--init", "x.toml"))
    assert "(--connect lab1 (from $BIRIS_CONNECT))" in str(refused.value)


def test_the_environment_chooses_between_a_target_and_the_files_service(
    monkeypatch: pytest.MonkeyPatch, _clean_env: Path
) -> None:
    _write(_clean_env, 'connect = "biris0"\n')
    monkeypatch.setenv(TARGET_ENV, "robot.toml")
    args = _args("home")
    check_target_arguments(args)
    assert (args.connect, args.target) == (None, "robot.toml")  # the shell's, over the file
    monkeypatch.setenv(CONNECT_ENV, "lab1")
    args = _args("home")
    check_target_arguments(args)
    assert (args.connect, args.target) == ("lab1", None)
    monkeypatch.delenv(TARGET_ENV)
    monkeypatch.delenv(CONNECT_ENV)
    args = _args("home")
    check_target_arguments(args)
    assert args.connect == "biris0"


def test_flags_win_over_the_environment_and_it_over_the_file(
    monkeypatch: pytest.MonkeyPatch, _clean_env: Path
) -> None:
    (_clean_env / "biris").mkdir(parents=True)
    (_clean_env / "biris" / "ca.pem").write_text("not checked here")
    _write(_clean_env, 'endpoint = "tcp/file:1"\nuser = "fileuser"\ntls_ca = "ca.pem"\n')
    monkeypatch.setenv(PASSWORD_ENV, "pw")
    options = connect_options(_args("watch", "--connect", "x"))
    assert options["endpoints"] == ["tcp/file:1"]
    assert (options["user"], options["password"]) == ("fileuser", "pw")
    assert options["tls_ca"] == str(_clean_env / "biris" / "ca.pem")
    monkeypatch.setenv(ENDPOINT_ENV, "tcp/env:2")
    monkeypatch.setenv(USER_ENV, "envuser")
    options = connect_options(_args("watch", "--connect", "x"))
    assert options["endpoints"] == ["tcp/env:2"] and options["user"] == "envuser"
    flags = ["--connect", "x", "--endpoint", "tcp/flag:3", "--user", "flaguser"]
    options = connect_options(_args("watch", *flags))
    assert options["endpoints"] == ["tcp/flag:3"] and options["user"] == "flaguser"


def test_a_profiles_user_without_a_password_sends_nothing(
    monkeypatch: pytest.MonkeyPatch, _clean_env: Path
) -> None:
    monkeypatch.setenv(USER_ENV, "op")
    args = _args("watch", "--connect", "x")
    options = connect_options(args)
    assert (options["user"], options["password"]) == (None, None)  # reading needs none
    assert args.profile_user == f"op (from ${USER_ENV})"
    with pytest.raises(UsageError, match=r"--user op needs the password in \$BIRIS_PASSWORD"):
        connect_options(_args("watch", "--connect", "x", "--user", "op"))  # a flag does


def test_a_profiles_tls_files_are_checked(_clean_env: Path) -> None:
    file = _write(_clean_env, 'tls_ca = "missing.pem"\n')
    with pytest.raises(SetupError) as refused:
        connect_options(_args("watch", "--connect", "x"))
    missing = file.parent / "missing.pem"
    assert str(refused.value) == f"tls_ca (from {file}) {missing}: no such file"
    key = file.parent / "me.key"
    key.write_text("k")
    key.chmod(0o644)
    (file.parent / "me.pem").write_text("c")
    _write(_clean_env, 'tls_cert = "me.pem"\ntls_key = "me.key"\n')
    with pytest.raises(SetupError, match="mode 0644 lets other users read it"):
        connect_options(_args("watch", "--connect", "x"))
    key.chmod(0o600)
    options = connect_options(_args("watch", "--connect", "x"))
    assert options["zenoh_options"] == {
        "transport/link/tls/connect_certificate": str(file.parent / "me.pem"),
        "transport/link/tls/connect_private_key": str(key),
    }


# -- end to end ------------------------------------------------------------------------------------


@pytest.fixture
def served() -> Iterator[str]:
    fake = FakeSensor()
    sensor: Any = fake  # a Sensor in all that the service uses
    where = endpoint(free_port())
    with serve(sensor, name="p", listen=[where], controllers={"op": "s3cret"}, multicast=False):
        yield where
    fake.free()


def test_a_command_reaches_the_profiles_service(
    monkeypatch: pytest.MonkeyPatch, served: str
) -> None:
    monkeypatch.setenv(CONNECT_ENV, "p")
    monkeypatch.setenv(ENDPOINT_ENV, served)
    monkeypatch.setenv(USER_ENV, "op")
    with open_session(_args("home")) as session:
        assert session.remote and session.server.status()["state"] == "idle"
    with (
        pytest.raises(AccessDenied) as refused,  # as a command sees it: out of its session
        open_session(_args("home")) as session,
        session.server.open() as conn,
    ):
        conn.stop_scan()
    assert str(refused.value).endswith(
        f"(no credentials were sent: user op (from ${USER_ENV}) has no password in ${PASSWORD_ENV})"
    )
    monkeypatch.setenv(PASSWORD_ENV, "s3cret")
    with open_session(_args("home")) as session, session.server.open() as conn:
        conn.stop_scan()  # the profile's user, with its password: a controller

"""Zenoh's own link-level user/password authentication in front of the service (docs/wire-format.md,
"Security", point 2): a peer without the right link credentials never gets a session with the
service, so it can neither read nor even learn that the service is there; the service's own
controller check still applies on top for those who do get in.

Slow: each refused peer is seen as a ``connect`` that times out (Zenoh drops the link during
its handshake and gives the client no reason), so the test waits out two short timeouts.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from biris_hw import BirisServer
from biris_hw.errors import AccessDenied, ConnectionClosed
from biris_hw.io.net import connect, serve
from tests.net_helpers import endpoint, free_port, warm_up_zenoh

pytestmark = [pytest.mark.slow, pytest.mark.realtime]  # the service's own threads

REFUSED_WAIT_S = 1.5
"""How long a refused peer waits for the service before connect() gives up; loopback links
that are accepted come up in milliseconds."""


@pytest.fixture(scope="module", autouse=True)
def _zenoh_runtime() -> None:
    warm_up_zenoh()


def _link(user: str, password: str) -> dict[str, str]:
    return {"transport/auth/usrpwd/user": user, "transport/auth/usrpwd/password": password}


def test_link_credentials_are_required(server: BirisServer, tmp_path: Path) -> None:
    dictionary = tmp_path / "zenoh-users.txt"
    dictionary.write_text("robot:link-pw\n")
    dictionary.chmod(0o600)
    where = endpoint(free_port())
    with serve(
        server,
        name="auth",
        listen=[where],
        controllers={"op": "s3cret"},
        multicast=False,
        options={"transport/auth/usrpwd/dictionary_file": str(dictionary)},
    ):
        with connect("auth", [where], multicast=False, options=_link("robot", "link-pw")) as ok:
            assert ok.status()["state"] == "idle"
            with pytest.raises(AccessDenied):  # in on the link, still not a controller
                ok.open().home()
        for options in ({}, _link("robot", "wrong"), _link("intruder", "link-pw")):
            with pytest.raises(ConnectionClosed, match="no BIRIS service"):
                connect(
                    "auth", [where], multicast=False, options=options, timeout=REFUSED_WAIT_S
                ).close()


def test_cli_reaches_a_service_behind_link_authentication(
    server: BirisServer, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``biris watch --connect ... --link-user robot`` with the password in the environment
    (never on the command line); and what the CLI refuses to take from argv."""
    import argparse
    import io

    from biris_hw.commands import watch
    from biris_hw.commands.failures import UsageError
    from biris_hw.commands.options import LINK_PASSWORD_ENV

    dictionary = tmp_path / "zenoh-users.txt"
    dictionary.write_text("robot:link-pw\n")
    where = endpoint(free_port())
    parser = argparse.ArgumentParser()
    watch.add_arguments(parser)
    base = ["--connect", "auth", "--endpoint", where, "--duration", "0.2", "--interval", "0.1"]

    def run(*extra: str) -> tuple[int, str]:
        args = parser.parse_args([*base, *extra])
        args.command = "watch"
        out = io.StringIO()
        return watch.run(args, out), out.getvalue()

    with serve(
        server,
        name="auth",
        listen=[where],
        multicast=False,
        options={"transport/auth/usrpwd/dictionary_file": str(dictionary)},
    ):
        monkeypatch.setenv(LINK_PASSWORD_ENV, "link-pw")
        code, out = run("--link-user", "robot", "--zenoh-option", "scouting/delay=0")
        assert code == 0 and "idle" in out
        password_file = tmp_path / "link.txt"
        password_file.write_text("link-pw\n")
        password_file.chmod(0o600)  # a secret others may read is refused, as ssh refuses one
        monkeypatch.delenv(LINK_PASSWORD_ENV)
        code, out = run("--link-user", "robot", "--link-password-file", str(password_file))
        assert code == 0 and "idle" in out
        with pytest.raises(UsageError, match="no passwords on the command line"):
            run("--zenoh-option", "transport/auth/usrpwd/password=link-pw")
        with pytest.raises(UsageError, match=LINK_PASSWORD_ENV):
            run("--link-user", "robot")

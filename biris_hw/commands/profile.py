"""A client's profile: the service the ``biris`` commands use, and how to reach it, said once.

Without it every command that uses a service repeats ``--connect biris0 --endpoint
tcp/robot:7447 --user op`` (and ``--tls-ca``). With it, each setting comes from, in order:

1. the command's flag (``--connect``, ``--endpoint``, ``--user``, ``--tls-ca``);
2. the environment: ``$BIRIS_CONNECT`` (the service's name), ``$BIRIS_ENDPOINT`` (one or more
   endpoints, separated by commas or spaces), ``$BIRIS_USER``;
3. the profile file, ``$XDG_CONFIG_HOME/biris/client.toml`` (``~/.config/biris/client.toml``)::

       connect = "biris0"
       endpoint = "tls/robot:7448"          # or a list of them
       user = "op"
       tls_ca = "ca.pem"                    # relative to the file's folder; ~ allowed
       tls_cert = "me.pem"                  # mutual TLS: the client's certificate and key
       tls_key = "me.key"

A password is never part of a profile: the file is a setting others may be shown, and a key
named like one is refused (:class:`~biris_hw.errors.SetupError`) rather than read. The password
stays in ``$BIRIS_PASSWORD`` or a private ``--credentials FILE``. A profile file that other
users may write is refused as well, as ssh refuses such a config: whoever can write it chooses
the service your commands talk to.

This module reads the environment and one small file; it imports nothing of the sensor, so
every command may ask it cheaply.
"""

from __future__ import annotations

import os
import re
import stat
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from biris_hw.errors import SetupError

__all__ = [
    "CONNECT_ENV",
    "ENDPOINT_ENV",
    "PROFILE_KEYS",
    "USER_ENV",
    "ClientProfile",
    "load_profile",
    "profile_path",
]

CONNECT_ENV = "BIRIS_CONNECT"
"""The service's name, as ``--connect`` would give it."""

ENDPOINT_ENV = "BIRIS_ENDPOINT"
"""The service's endpoints, as ``--endpoint`` would give them (commas or spaces between)."""

USER_ENV = "BIRIS_USER"
"""The controller's user, as ``--user`` would give it (its password: ``$BIRIS_PASSWORD``)."""

PROFILE_KEYS = ("connect", "endpoint", "user", "tls_ca", "tls_cert", "tls_key")
"""What the profile file may say."""

_SECRET = re.compile(r"pass|secret", re.IGNORECASE)


@dataclass(frozen=True)
class ClientProfile:
    """The settings found in the environment and the profile file (flags not included)."""

    connect: str | None = None
    endpoints: tuple[str, ...] = ()
    user: str | None = None
    tls_ca: Path | None = None
    tls_cert: Path | None = None
    tls_key: Path | None = None
    sources: Mapping[str, str] = field(default_factory=dict)
    """Where each setting found came from: ``$BIRIS_ENDPOINT`` or the file's path."""

    def source(self, key: str) -> str:
        """Where ``key`` came from, for a message ("from $BIRIS_CONNECT"); "" if not found."""
        where = self.sources.get(key)
        return f" (from {where})" if where else ""


def profile_path(env: Mapping[str, str] | None = None) -> Path:
    """``$XDG_CONFIG_HOME/biris/client.toml``, else ``~/.config/biris/client.toml``."""
    env = os.environ if env is None else env
    base = env.get("XDG_CONFIG_HOME") or ""
    folder = Path(base) if base and os.path.isabs(base) else Path.home() / ".config"
    return folder / "biris" / "client.toml"


def load_profile(env: Mapping[str, str] | None = None, path: Path | None = None) -> ClientProfile:
    """The profile the environment and the file (``path``, default :func:`profile_path`) make,
    the environment first, setting by setting. A missing file is an empty one.

    Raises:
        SetupError: the file cannot be read, is not TOML, holds a password or an unknown key,
            a value of the wrong type, or may be written by other users.
    """
    env = os.environ if env is None else env
    file = path if path is not None else profile_path(env)
    found: dict[str, Any] = {}
    sources: dict[str, str] = {}
    table = _read(file)
    for key, value in table.items():
        found[key] = value
        sources[key] = str(file)
    for key, name in (("connect", CONNECT_ENV), ("endpoint", ENDPOINT_ENV), ("user", USER_ENV)):
        value = env.get(name, "").strip()
        if value:
            found[key] = value
            sources[key] = f"${name}"
    endpoints = found.get("endpoint", ())
    if isinstance(endpoints, str):
        endpoints = tuple(e for e in re.split(r"[\s,]+", endpoints) if e)
    if ("tls_cert" in found) != ("tls_key" in found):
        raise SetupError(f"{file}: tls_cert and tls_key go together (mutual TLS)")
    return ClientProfile(
        connect=found.get("connect"),
        endpoints=tuple(endpoints),
        user=found.get("user"),
        tls_ca=found.get("tls_ca"),
        tls_cert=found.get("tls_cert"),
        tls_key=found.get("tls_key"),
        sources=sources,
    )


def _read(file: Path) -> dict[str, Any]:
    """The file's settings, checked; {} when there is no file."""
    try:
        mode = file.stat().st_mode
    except FileNotFoundError:
        return {}
    except OSError as exc:
        raise SetupError(f"cannot read {file}: {exc.strerror or exc}") from exc
    if os.name == "posix" and mode & (stat.S_IWGRP | stat.S_IWOTH):
        raise SetupError(
            f"{file}: mode {stat.S_IMODE(mode):04o} lets other users write it (and so choose "
            f"the service your commands use): chmod 644 {file}"
        )
    from biris_hw.commands.options import read_toml

    table = read_toml(file)
    for key in table:
        if _SECRET.search(key):
            raise SetupError(
                f"{file}: {key!r}: no passwords in the profile (a file others may read or be "
                "shown); give the password in $BIRIS_PASSWORD, or in a --credentials FILE of "
                "mode 600"
            )
    unknown = sorted(set(table) - set(PROFILE_KEYS))
    if unknown:
        raise SetupError(
            f"{file}: unknown key(s) {', '.join(unknown)}; known: {', '.join(PROFILE_KEYS)}"
        )
    settings: dict[str, Any] = {}
    for key in ("connect", "user"):
        if key in table:
            settings[key] = _text(file, key, table[key])
    if "endpoint" in table:
        value = table["endpoint"]
        if isinstance(value, str) and value.strip():
            settings["endpoint"] = value
        elif isinstance(value, list) and value and all(isinstance(e, str) and e for e in value):
            settings["endpoint"] = tuple(value)
        else:
            raise SetupError(f'{file}: endpoint = "tcp/HOST:PORT" or a list of such strings')
    for key in ("tls_ca", "tls_cert", "tls_key"):
        if key in table:
            given = Path(_text(file, key, table[key])).expanduser()
            settings[key] = given if given.is_absolute() else file.parent / given
    return settings


def _text(file: Path, key: str, value: object) -> str:
    if not isinstance(value, str) or not value.strip():
        raise SetupError(f'{file}: {key} = "..." (a non-empty string)')
    return value.strip()

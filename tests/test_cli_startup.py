"""``biris --help`` and ``biris --version`` start at once: they load nothing of the server, the
hardware, the outside world, the simulator or numpy; a command's own ``--help`` loads its flags,
not a server. Held here by the modules a fresh interpreter has loaded (how long that takes is a
benchmark's business: ``benchmarks/cli_startup.py``)."""

from __future__ import annotations

import json
import subprocess
import sys

from biris_hw.cli import COMMANDS

_PROBE = """
import contextlib, io, json, sys
from biris_hw.cli import main
with contextlib.redirect_stdout(io.StringIO()) as out:
    code = main(sys.argv[1:])
print(json.dumps({"code": code, "out": out.getvalue(), "modules": sorted(sys.modules)}))
"""
"""Runs ``biris ARGS`` in a fresh interpreter and says what it printed and what it loaded."""

NEVER_FOR_HELP = (
    "biris_hw.server",
    "biris_hw.client",
    "biris_hw.protocol",
    "biris_hw.hardware",
    "biris_hw.target",
    "biris_hw.simlink",
    "biris_hw.bus",
    "biris_hw.irq",
    "biris_hw.io",
    "biris_hw.records",
    "biris_hw.data",
    "sim",
    "numpy",
    "matplotlib",
    "zenoh",
    "mcap",
)
"""What ``biris --help`` and ``--version`` must not load: everything that takes time to import."""

NEVER_FOR_A_COMMAND = (
    "biris_hw.server",
    "biris_hw.client",
    "biris_hw.target",
    "biris_hw.simlink",
    "biris_hw.io",
    "sim",
    "matplotlib",
    "zenoh",
    "mcap",
)
"""What a command's ``--help`` must not load: its flags need argument types, not a server (numpy
comes with the samples flag's choices, from the register layout)."""


def _biris(*argv: str) -> tuple[int, str, list[str]]:
    """(exit status, stdout, the modules loaded) of ``biris ARGV`` in a fresh interpreter."""
    done = subprocess.run(
        [sys.executable, "-c", _PROBE, *argv],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    found = json.loads(done.stdout)
    return int(found["code"]), str(found["out"]), list(found["modules"])


def _among(modules: list[str], packages: tuple[str, ...]) -> list[str]:
    return [m for m in modules if any(m == p or m.startswith(p + ".") for p in packages)]


def test_help_lists_the_commands_and_loads_nothing_heavy() -> None:
    code, out, modules = _biris("--help")
    assert code == 0
    assert out.startswith("usage: biris")
    assert all(command.name in out for command in COMMANDS)
    assert _among(modules, NEVER_FOR_HELP) == []
    assert set(modules).isdisjoint(c.module for c in COMMANDS)  # no command's module either


def test_version_loads_nothing_heavy() -> None:
    code, out, modules = _biris("--version")
    assert code == 0
    assert out.startswith("biris-hw ")
    assert _among(modules, NEVER_FOR_HELP) == []


_EVERY_HELP = """
import contextlib, io, json, sys
from biris_hw.cli import main
seen = {}
for name in sys.argv[1:]:
    with contextlib.redirect_stdout(io.StringIO()) as out:
        code = main([name, "--help"])
    seen[name] = {"code": code, "out": out.getvalue()[:80], "modules": sorted(sys.modules)}
print(json.dumps(seen))
"""
"""Runs ``biris NAME --help`` for each NAME in one fresh interpreter, one after the other, and
says what each printed and what was loaded once it had run: a module a command's help loaded
first appears after that command (one interpreter for all: the suite's time, not the check's)."""


def test_a_commands_help_loads_no_server() -> None:
    """``biris sim`` is the simulator: its help may load it."""
    names = [c.name for c in COMMANDS if c.name != "sim"]
    done = subprocess.run(
        [sys.executable, "-c", _EVERY_HELP, *names],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    seen = json.loads(done.stdout)
    assert list(seen) == names
    for name in names:
        assert seen[name]["code"] == 0, name
        assert seen[name]["out"].startswith(f"usage: biris {name}"), seen[name]["out"]
        assert _among(seen[name]["modules"], NEVER_FOR_A_COMMAND) == [], name


def test_opening_a_sensor_costs_nothing_until_one_is_opened() -> None:
    """``biris_hw.opening`` (and the sensor module's open_sensor) reach every kind of sensor
    only when one is opened."""
    probe = (
        "import json, sys\n"
        "from biris_hw.opening import open_sensor\n"
        "print(json.dumps(sorted(sys.modules)))"
    )
    done = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, timeout=60, check=True
    )
    assert _among(json.loads(done.stdout), NEVER_FOR_HELP) == []

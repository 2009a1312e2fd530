"""The argument types of every ``biris`` command, in one place.

Each function here is an argparse ``type=``: it turns one word of the command line into a value
or raises :class:`argparse.ArgumentTypeError` with a short reason, which the dispatcher
(:mod:`biris_hw.cli`) prints as one line, ``biris scan: argument --to: not an angle in degrees:
'ten'``, with exit status 2. Every command uses these, ``biris sim`` (:mod:`sim.process`) and
``biris regdump`` (:mod:`biris_hw.regdump.cli`) included, so a flag that means the same thing
is checked the same way everywhere.

:func:`add_simulator_arguments` declares the simulator's four flags (``--scene``,
``--samples``, ``--time-scale``, ``--seed``) for the commands that start one.

This module imports nothing of the server and nothing of the simulator at import time, so
``biris --help`` stays instant and :mod:`sim.process` may use it. :func:`scene_spec` imports
:mod:`sim.scene` when it is called: the scene is the simulator's to describe
(:meth:`sim.Scene.from_spec` is the one parser), and ``--scene`` is only ever given on the
simulator's path.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

from regs.layout import SAMPLES_CHOICES

__all__ = [
    "DEFAULT_TIME_SCALE",
    "SAMPLES_CHOICES",
    "SAMPLES_METAVAR",
    "SIM_DEFAULTS",
    "add_simulator_arguments",
    "degrees",
    "integer",
    "offset",
    "path",
    "positive_float",
    "positive_int",
    "samples",
    "scene_spec",
    "seconds",
    "seed",
    "time_scale",
    "time_scale_warning",
]

SAMPLES_METAVAR = "|".join(str(c) for c in SAMPLES_CHOICES)
"""How help shows a samples flag: ``64|128``."""

SIM_DEFAULTS: dict[str, Any] = {"scene": "room", "samples": 64, "seed": 0, "clock": "scaled"}
"""The simulator's defaults for ``--scene``, ``--samples``, ``--seed`` and ``--clock``."""

DEFAULT_TIME_SCALE = 4.0
"""The simulator's default speed, the same for every command that starts one (``--sim``,
``biris demo``, ``biris sim``): four hardware seconds per real second keeps a sweep readable on
screen while initialisation (which turns the head to find its zero index) stays short. One
default, so that ``biris sim`` followed by ``biris watch --attach`` looks like ``biris watch
--sim``."""


# -- numbers ---------------------------------------------------------------------------------------


def _number(text: str, what: str = "a number") -> float:
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not {what}: {text!r}") from None


def degrees(text: str) -> float:
    """An angle in degrees; NaN and infinities are refused here, before anything moves."""
    value = _number(text, "an angle in degrees")
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"an angle must be finite, not {text}")
    return value


def positive_float(text: str) -> float:
    """A finite number above 0."""
    value = _number(text)
    if not (math.isfinite(value) and value > 0.0):
        raise argparse.ArgumentTypeError(f"must be a positive number, not {text}")
    return value


seconds = positive_float
"""A duration, an interval or a timeout in (real) seconds: a finite number above 0."""

time_scale = positive_float
"""The simulator's hardware seconds per real second: a finite number above 0."""


def time_scale_warning(lag_s: float, bound_s: float, scale: float) -> str:
    """What every command that runs a simulator says, once, when the host cannot keep up with
    ``--time-scale`` (:meth:`sim.SimulatedBiris.behind`): how late the simulator runs
    (``lag_s``, hardware seconds, beyond ``bound_s``), what that costs, and what to do. Not a
    refusal: the run may still be what the person wanted, but they must not take its timings
    for the robot's."""
    return (
        f"warning: the simulator runs {lag_s * 1e3:.0f} ms of hardware time late "
        f"(more than {bound_s * 1e3:.0f} ms): this machine cannot keep up with "
        f"--time-scale {scale:g}, so timings and faults (motor_stall, timeout) may be "
        f"wrong; use a smaller --time-scale"
    )


def _whole(text: str, what: str) -> int:
    """Decimal (leading zeros allowed) or with a 0x/0o/0b prefix."""
    for base in (0, 10):
        try:
            return int(text, base)
        except ValueError:
            pass
    raise argparse.ArgumentTypeError(f"not {what}: {text!r}")


def integer(text: str) -> int:
    """Any whole number, decimal or 0x hex (register values: their range is checked later,
    against the register)."""
    return _whole(text, "an integer (decimal or 0x hex)")


def positive_int(text: str) -> int:
    """A whole number of at least 1 (counts of things, periods in ms), decimal or 0x hex."""
    value = _whole(text, "a whole number")
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, not {text}")
    return value


def offset(text: str) -> int:
    """A byte offset or address: a whole number of at least 0, decimal or 0x hex."""
    value = _whole(text, "an offset")
    if value < 0:
        raise argparse.ArgumentTypeError(f"an offset must not be negative, not {text}")
    return value


def seed(text: str) -> int:
    """A noise seed: a whole number of at least 0 (numpy's seed sequences refuse negatives)."""
    value = _whole(text, "a whole number")
    if value < 0:
        raise argparse.ArgumentTypeError(f"a seed must not be negative, not {text}")
    return value


def samples(text: str) -> int:
    """Samples per acquisition: one of :data:`SAMPLES_CHOICES` (64 or 128)."""
    choices = ", ".join(str(c) for c in SAMPLES_CHOICES)
    try:
        value = int(text)
    except ValueError:
        value = -1
    if value not in SAMPLES_CHOICES:
        raise argparse.ArgumentTypeError(f"invalid choice: {text!r} (choose from {choices})")
    return value


# -- words -----------------------------------------------------------------------------------------


def path(text: str) -> Path:
    """A file or folder to read or write; whether it exists is the command's business (it says
    so in its own words), only an empty or NUL-containing name is refused here."""
    if not text or "\0" in text:
        raise argparse.ArgumentTypeError(f"not a file name: {text!r}")
    return Path(text)


def scene_spec(text: str) -> str:
    """``room`` or ``circle:R`` (R in metres), checked now by :meth:`sim.Scene.from_spec` and
    built later, so that a bad scene is a usage error before anything starts. Returns the text:
    it names the scene in what the command prints."""
    try:
        from sim.scene import Scene
    except ImportError:
        raise argparse.ArgumentTypeError("the simulator is not installed") from None
    try:
        Scene.from_spec(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return text


# -- the simulator's flags -------------------------------------------------------------------------


def add_simulator_arguments(
    parser: argparse.ArgumentParser | argparse._ArgumentGroup,
    *,
    default_time_scale: float,
    deferred: bool = False,
    clocks: bool = False,
) -> None:
    """``--scene``, ``--samples``, ``--time-scale`` and ``--seed``, with :data:`SIM_DEFAULTS`;
    ``--clock`` too with ``clocks`` (an in-process simulator only: a ``biris sim`` process
    shares its clock with other processes, which only scaled time can do).

    ``deferred`` leaves every default None, so that the command can tell a flag that was given
    from one that was not (``--scene`` without ``--sim`` is a mistake) and fill the defaults in
    itself; the help shows them either way.
    """

    def default(value: Any) -> Any:
        return None if deferred else value

    parser.add_argument(
        "--scene",
        type=scene_spec,
        default=default(SIM_DEFAULTS["scene"]),
        metavar="room|circle:R",
        help="what the sensor looks at: the furnished room (default) or a round wall of R metres",
    )
    parser.add_argument(
        "--samples",
        type=samples,
        default=default(SIM_DEFAULTS["samples"]),
        metavar=SAMPLES_METAVAR,
        help=f"samples per acquisition (default {SIM_DEFAULTS['samples']})",
    )
    parser.add_argument(
        "--time-scale",
        type=time_scale,
        default=default(default_time_scale),
        metavar="X",
        help=f"hardware seconds per real second (default {default_time_scale:g})",
    )
    parser.add_argument(
        "--seed",
        type=seed,
        default=default(SIM_DEFAULTS["seed"]),
        metavar="N",
        help=f"noise seed (default {SIM_DEFAULTS['seed']})",
    )
    if clocks:
        parser.add_argument(
            "--clock",
            choices=("scaled", "virtual"),
            default=default(SIM_DEFAULTS["clock"]),
            help="the simulator's time: scaled real time, --time-scale times faster (default), "
            "or virtual time, which moves only when the driver and the simulator wait: a scan "
            "comes back as soon as it is computed, whatever the host's load",
        )

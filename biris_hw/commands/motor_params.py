"""``biris motor-params``: the pan motor's HCTL-1000 parameters, shown and set.

Two sources are shown side by side: the init record's (what the server loads at start-up, and
what BIRIS_MOTOR_PARAMS replaces) and the chip's own registers, read back from the azimuth
HCTL-1000 once the server has loaded them. They should agree; if they do not, the board is not
taking the writes, which is worth knowing before blaming the filter.

Setting a value (``--gain 0x30``) sends BIRIS_MOTOR_PARAMS, as a client would, and waits until it
is in force. A ``biris`` run lasts one command, so the next run starts from the init record again:
``--save-init FILE`` writes the record with the new values, for ``--init FILE`` from then on;
FILE is checked before the sensor is touched.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from typing import TextIO

from biris_hw.angles import counts_to_deg
from biris_hw.commands.argtypes import integer, path
from biris_hw.commands.failures import UsageError
from biris_hw.commands.options import add_target_arguments, add_timeout_argument, check_output_file
from biris_hw.commands.session import open_session
from biris_hw.errors import RequestError
from biris_hw.records import MotorParams
from regs.hctl1000 import Reg, accel_from_reg, sample_period

__all__ = ["PARAMS", "add_arguments", "describe", "run"]

PARAMS: dict[str, tuple[str, Reg | tuple[Reg, Reg]]] = {
    "sample": ("--sample", Reg.SAMPLE_TIMER),
    "zero": ("--zero", Reg.FILTER_ZERO),
    "pole": ("--pole", Reg.FILTER_POLE),
    "gain": ("--gain", Reg.FILTER_GAIN),
    "max_vel": ("--max-vel", Reg.MAX_VELOCITY),
    "max_accel": ("--max-accel", (Reg.ACCEL_LSB, Reg.ACCEL_MSB)),
}
"""MotorParams field -> (flag, the HCTL-1000 register(s) that hold it, LSB first)."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    new = parser.add_argument_group("set (register values, decimal or 0x hex)")
    helps = {
        "sample": "sample timer T (R0FH): period 16(T+1)/2 MHz",
        "zero": "filter zero A (R20H)",
        "pole": "filter pole B (R21H)",
        "gain": "filter gain K (R22H)",
        "max_vel": "trapezoid maximum velocity, counts/sample (R28H)",
        "max_accel": "trapezoid acceleration, 8.8 counts/sample^2 (R26H/R27H)",
    }
    for name, (flag, _) in PARAMS.items():
        new.add_argument(flag, dest=name, type=integer, default=None, metavar="N", help=helps[name])
    parser.add_argument(
        "--save-init",
        type=path,
        metavar="FILE",
        help="write the init record with these parameters (TOML)",
    )
    parser.add_argument("--json", action="store_true", help="one JSON object")
    add_timeout_argument(parser)
    add_target_arguments(parser)


def describe(name: str, value: int, sample: int) -> str:
    """What a register value means physically (``sample`` gives the period for speeds)."""
    period = sample_period(sample & 0xFF)
    if name == "sample":
        return f"{period * 1e3:.3f} ms per sample"
    if name == "zero":
        return f"A/256 = {value / 256:.4f}"
    if name == "pole":
        return f"B/256 = {value / 256:.4f}"
    if name == "gain":
        return f"K/4 = {value / 4:g}"
    if name == "max_vel":
        return f"{value} counts/sample = {counts_to_deg(value / period):.1f} deg/s"
    accel = accel_from_reg(value)
    return f"{accel:.2f} counts/sample^2 = {counts_to_deg(accel / period**2):.0f} deg/s^2"


def run(args: argparse.Namespace, out: TextIO | None = None) -> int:
    stream = out or sys.stdout
    changes = _changes(args)
    if args.save_init is not None:
        import tomli_w  # noqa: F401  (fail now, not after the run, if the toml extra is missing)

        check_output_file("--save-init", args.save_init)
    with open_session(args) as session:
        if session.hardware is None:  # the chip's registers are read, not just the server asked
            raise UsageError(
                "motor-params reads the HCTL-1000 itself: run it where the sensor is, "
                "not through --connect"
            )
        params = dataclasses.replace(session.record.motor, **changes)
        if changes:
            with session.server.open() as conn:
                conn.set_motor_params(params)
                conn.wait_idle(timeout=args.timeout)
        chip = session.hardware.devices.azimuth.read_params()  # the one driver of the chip
        record = dataclasses.replace(session.record, motor=params)
    if args.save_init is not None:
        record.save(args.save_init)
    _show(params, chip, bool(changes), args, stream)
    if args.save_init is not None:
        print(f"saved the init record to {args.save_init} (use it with --init)", file=stream)
    return 0


def _changes(args: argparse.Namespace) -> dict[str, int]:
    """The values asked for, each checked against its register before anything starts."""
    changes = {name: getattr(args, name) for name in PARAMS if getattr(args, name) is not None}
    for name, value in changes.items():
        try:
            MotorParams(**{name: value})
        except RequestError as exc:
            raise UsageError(f"{PARAMS[name][0]}: {str(exc).partition(': ')[2]}") from None
    return changes


def _show(
    params: MotorParams, chip: dict[str, int], changed: bool, args: argparse.Namespace, out: TextIO
) -> None:
    mine = params.to_dict()
    if args.json:
        print(json.dumps({"record": mine, "chip": chip, "changed": changed}), file=out)
        return
    source = "set now" if changed else "init record"
    print(f"{'parameter':<10} {source:>11} {'chip':>8}  meaning", file=out)
    for name, value in mine.items():
        digits = 4 if name == "max_accel" else 2
        flag = "" if chip[name] == value else "  (chip differs!)"
        print(
            f"{name:<10} {f'0x{value:0{digits}X}':>11} {f'0x{chip[name]:0{digits}X}':>8}  "
            f"{describe(name, value, mine['sample'])}{flag}",
            file=out,
        )

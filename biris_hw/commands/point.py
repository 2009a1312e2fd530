"""``biris point``: the latest acquisition (REQUEST_POINT), making one first if there is none.

BIRIS acquires only while the head scans, and every ``biris`` run starts its own server, so a
fresh server has no point to give. The command therefore runs a short single scan (``--to``,
5 degrees by default: about one acquisition's worth of travel, so the head barely moves) and
asks for the point once the scan has ended, which is the moment its last acquisition is in.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any, TextIO

import numpy as np

from biris_hw.commands.argtypes import degrees
from biris_hw.commands.common import (
    Session,
    add_target_arguments,
    add_timeout_argument,
    open_session,
)
from biris_hw.data import Point

__all__ = ["add_arguments", "point_summary", "point_to_json", "run"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--to",
        type=degrees,
        default=5.0,
        metavar="DEG",
        help="where the short scan that makes the point ends (default 5)",
    )
    parser.add_argument("--profile", action="store_true", help="also print every sample")
    parser.add_argument("--json", action="store_true", help="one JSON object")
    add_timeout_argument(parser)
    add_target_arguments(parser)


def run(args: argparse.Namespace, out: TextIO | None = None) -> int:
    stream = out or sys.stdout
    with open_session(args) as session:
        point = latest_point(session, args.to, args.timeout)
    if args.json:
        print(json.dumps(point_to_json(point)), file=stream)
        return 0
    print(point_summary(point), file=stream)
    if args.profile:
        for k, (r, i) in enumerate(zip(point.profile, point.intensity, strict=True)):
            print(f"  row {k + 1:3d}: {int(r):5d} mm  intensity {int(i):5d}", file=stream)
    return 0


def latest_point(session: Session, to_deg: float, timeout: float) -> Point:
    """The server's latest point; scans to ``to_deg`` first when it has none yet."""
    with session.server.open() as conn:
        point = conn.request_point()
        if point is None:
            conn.single_scan(to_deg)
            conn.wait_idle(timeout=timeout)
            point = conn.request_point()
    if point is None:
        raise TimeoutError("the scan ended without an acquisition")
    return point


def point_summary(point: Point) -> str:
    """Two lines: where and how far, then which acquisition and how the profile looks."""
    valid = point.profile[point.profile > 0]
    spread = f"{valid.size}/{point.profile.size} samples valid"
    if valid.size:
        spread += f", {int(valid.min())}..{int(valid.max())} mm"
    closest = f"closest {point.range_mm} mm" if point.range_mm > 0 else "no return"
    age = "" if point.age is None else f", {point.age:.3f} s old when delivered"
    return (
        f"azimuth {point.azimuth_deg:+.2f} deg ({point.azimuth} counts), {closest}\n"
        f"  acquisition {point.acq} of scan {point.scan_seq} at t = {point.t:.3f} s{age}; {spread}"
    )


def point_to_json(point: Point) -> dict[str, Any]:
    return {
        "azimuth_counts": point.azimuth,
        "azimuth_deg": round(point.azimuth_deg, 4),
        "range_mm": point.range_mm,
        "acq": point.acq,
        "scan_seq": point.scan_seq,
        "t": point.t,
        "t_delivered": point.t_delivered,
        "profile": np.asarray(point.profile).tolist(),
        "intensity": np.asarray(point.intensity).tolist(),
    }

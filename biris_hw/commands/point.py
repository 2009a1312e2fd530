"""``biris point``: the latest acquisition (REQUEST_POINT), making one first if there is none.

BIRIS acquires only while the head scans, and every ``biris`` run starts its own server, so a
fresh server has no point to give. The command therefore runs a short single scan (``--to``,
10 degrees by default: a few acquisitions' worth of travel, so that one is kept even when the
motor starts a period or two after BIRIS's start-up, as a loaded host or a simulator in another
process may make it; the head barely moves) and
asks for the point once the scan has ended, which is the moment its last acquisition is in.
``--continuous`` makes that scan with Appendix D's continuous acquisition; ``--to`` is clamped
and confirmed (``--yes``) as ``biris scan --to`` is. If that scan came out partial (short of
``--to``: a motor that started late, say), the summary says so and why, and ``--json`` gives the
reason as ``"scan_partial_reason"`` (``""`` when the scan was whole or none was made).
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any, TextIO

import numpy as np

from biris_hw.angles import counts_to_deg, destination_counts
from biris_hw.commands.argtypes import degrees
from biris_hw.commands.console import note_clamped
from biris_hw.commands.options import (
    add_continuous_argument,
    add_target_arguments,
    add_timeout_argument,
    add_yes_argument,
)
from biris_hw.commands.session import Session, confirm_moves, open_session
from biris_hw.data import Direction, Point, Scan

__all__ = ["add_arguments", "point_summary", "point_to_json", "run"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--to",
        type=degrees,
        default=10.0,
        metavar="DEG",
        help="where the short scan that makes the point ends (default 10)",
    )
    parser.add_argument("--profile", action="store_true", help="also print every sample")
    parser.add_argument("--json", action="store_true", help="one JSON object")
    add_continuous_argument(parser)
    add_yes_argument(parser)
    add_timeout_argument(parser)
    add_target_arguments(parser)


def run(args: argparse.Namespace, out: TextIO | None = None) -> int:
    stream = out or sys.stdout
    made: list[Scan] = []
    with open_session(args) as session:
        point = latest_point(session, args.to, args.timeout, args, made=made)
    partial = next((scan for scan in made if scan.partial), None)
    if args.json:
        answer = point_to_json(point)
        answer["scan_partial_reason"] = "" if partial is None else partial.partial_reason
        print(json.dumps(answer), file=stream)
        return 0
    print(point_summary(point), file=stream)
    if partial is not None:
        why = partial.partial_reason or "no reason given"
        print(
            f"  the scan that made it ({partial.direction.name} #{partial.seq}) is partial: {why}",
            file=stream,
        )
    if args.profile:
        for k, (r, i) in enumerate(zip(point.profile, point.intensity, strict=True)):
            print(f"  row {k + 1:3d}: {int(r):5d} mm  intensity {int(i):5d}", file=stream)
    return 0


def latest_point(
    session: Session,
    to_deg: float,
    timeout: float,
    args: argparse.Namespace | None = None,
    *,
    made: list[Scan] | None = None,
) -> Point:
    """The server's latest point; scans to ``to_deg`` first when it has none yet (asking for
    ``--yes`` in ``args`` first if that is more than half a turn on a real head). The scan it
    made, if any, is appended to ``made``, so that the caller can say whether it was whole."""
    with session.server.open() as conn:
        point: Point | None = conn.request_point()
        if point is None:
            dest = destination_counts(to_deg, "--to")
            confirm_moves(session, args or argparse.Namespace(), [(f"--to {to_deg:g}", dest)])
            start = int(session.server.status()["azimuth"])
            dest = conn.single_scan(to_deg)
            note_clamped(session.prog, "--to", to_deg, dest)
            conn.wait_idle(timeout=timeout)
            point = conn.request_point()
            if made is not None and dest != start:
                scan = conn.request_scan_data(Direction.of_motion(start, dest))
                if scan is not None:
                    made.append(scan)
            if point is None and dest != start:
                # the scan came back empty (marked partial, with why: its motor started later
                # than its count allowed for); once more, back over the same span
                conn.single_scan(counts_to_deg(start))
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
        "acquisition": point.acquisition,
        "t": point.t,
        "t_delivered": point.t_delivered,
        "profile": np.asarray(point.profile).tolist(),
        "intensity": np.asarray(point.intensity).tolist(),
    }

"""``biris scan``: one scan to an azimuth, or continuous sweeps; a summary, files, a picture.

A single scan (``--to DEG``) is the report's BIRIS_SINGLE_SCAN_RQST: the head turns from where it
stands to DEG while BIRIS acquires, and the command prints that scan. Continuous scanning
(``--cw DEG --ccw DEG --sweeps N``) is BIRIS_CONT_SCAN_RQST read through a DATA connection, so
every completed sweep is received (none skipped, and any that were would be counted); the first
sweep runs from where the head stands to the CW limit, so it is shorter than the others.

``--save PATH`` writes PATH.npz (every scan whole, for programs:
:func:`biris_hw.scanfile.load_scans` reads it back into equal :class:`~biris_hw.Scan` objects)
and PATH.csv (one row per acquisition with its range profile, for spreadsheets); see
:mod:`biris_hw.scanfile`.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from biris_hw import scanfile
from biris_hw.commands.argtypes import degrees, path, positive_int
from biris_hw.commands.common import (
    Session,
    UsageError,
    add_target_arguments,
    add_timeout_argument,
    open_session,
)
from biris_hw.data import Direction, Scan
from biris_hw.plots import closest_points_xy
from biris_hw.sweeps import sweeping

__all__ = ["add_arguments", "run", "save_files", "scan_summary", "scan_to_json"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    how = parser.add_argument_group("what to scan (one of)")
    how.add_argument("--to", type=degrees, metavar="DEG", help="one scan to DEG degrees")
    how.add_argument("--cw", type=degrees, metavar="DEG", help="continuous: clockwise limit")
    how.add_argument(
        "--ccw", type=degrees, metavar="DEG", help="continuous: counter-clockwise limit"
    )
    how.add_argument(
        "--sweeps",
        type=positive_int,
        default=None,
        metavar="N",
        help="continuous: stop after N sweeps (default 2)",
    )
    out = parser.add_argument_group("output")
    out.add_argument("--json", action="store_true", help="one JSON object per scan")
    out.add_argument(
        "--save",
        type=path,
        metavar="PATH",
        help="write PATH.npz (every scan, whole) and PATH.csv (ranges, for spreadsheets)",
    )
    out.add_argument("--plot", type=path, metavar="PATH", help="write a polar picture (PNG)")
    add_timeout_argument(parser)
    add_target_arguments(parser)


def _check(args: argparse.Namespace) -> None:
    continuous = args.cw is not None or args.ccw is not None
    if args.to is not None and continuous:
        raise UsageError("give either --to, or --cw and --ccw, not both")
    if args.to is None and not continuous:
        raise UsageError("say what to scan: --to DEG, or --cw DEG --ccw DEG")
    if continuous and (args.cw is None or args.ccw is None):
        raise UsageError("continuous scanning needs both --cw and --ccw")
    if continuous and args.cw >= args.ccw:
        raise UsageError(f"--cw ({args.cw:g}) must lie clockwise of (below) --ccw ({args.ccw:g})")
    if args.sweeps is not None and not continuous:
        raise UsageError("--sweeps goes with --cw/--ccw")
    if args.plot is not None:
        import matplotlib  # noqa: F401  (fail now, not after the scan, if it is missing)


def run(args: argparse.Namespace, out: TextIO | None = None) -> int:
    """Scan, report, save and draw; 0 when every scan arrived."""
    stream = out or sys.stdout
    _check(args)
    with open_session(args) as session:
        scans = _single(session, args) if args.to is not None else _sweeps(session, args, stream)
        if args.to is not None:
            _report(scans[0], args, stream)
        outline = session.rig.scene.outline_2d() if session.rig is not None else None
    if args.save is not None:
        npz, table = save_files(args.save, scans)
        print(f"saved {npz} and {table}", file=stream)
    if args.plot is not None:
        from biris_hw.plots import save_polar

        latest = {scan.direction: scan for scan in scans}
        picture = save_polar(args.plot, list(latest.values()), outline)
        print(f"picture: {picture}", file=stream)
    return 0


def _single(session: Session, args: argparse.Namespace) -> list[Scan]:
    with session.server.open() as conn:
        start = int(session.server.status()["azimuth"])
        dest = conn.single_scan(args.to)
        conn.wait_idle(timeout=args.timeout)
        scan = conn.request_scan_data(Direction.of_motion(start, dest))
    if scan is None:
        raise TimeoutError("the scan ended without delivering data")
    return [scan]


def _sweeps(session: Session, args: argparse.Namespace, stream: TextIO) -> list[Scan]:
    wanted = args.sweeps or 2
    scans: list[Scan] = []
    # On leaving: STOP (the sweep under way completes), the head at rest, connections closed.
    with sweeping(session.server, args.cw, args.ccw, timeout=args.timeout) as sweeps:
        for scan in sweeps:
            scans.append(scan)
            _report(scan, args, stream)
            if len(scans) == wanted:
                break
    return scans


def _report(scan: Scan, args: argparse.Namespace, stream: TextIO) -> None:
    text = json.dumps(scan_to_json(scan)) if args.json else scan_summary(scan)
    print(text, file=stream, flush=True)


# -- describing scans ------------------------------------------------------------------------------


def scan_summary(scan: Scan) -> str:
    """One line: direction, sequence, extent, the closest return, how much of it is valid."""
    head = f"{scan.direction.name} #{scan.seq}: {scan.n_acq} acquisitions"
    if scan.n_acq == 0:
        return f"{head}, dropped {scan.dropped}"
    az = scan.azimuth_deg
    valid = scan.range_mm > 0
    text = f"{head} over {az[0]:+.1f}..{az[-1]:+.1f} deg"
    closest = scan.closest_mm.astype(np.int64)
    if np.any(closest > 0):
        k = int(np.argmin(np.where(closest > 0, closest, np.iinfo(np.int64).max)))
        text += f", closest {closest[k]} mm at {az[k]:+.1f} deg"
    text += f", {100.0 * valid.mean():.0f}% of samples valid"
    if np.any(valid):
        text += f", median {int(np.median(scan.range_mm[valid]))} mm"
    return f"{text}, dropped {scan.dropped}"


def scan_to_json(scan: Scan) -> dict[str, Any]:
    """Everything in a scan, as plain JSON values (azimuths in counts and degrees)."""
    return {
        "direction": scan.direction.name,
        "seq": scan.seq,
        "n_acq": scan.n_acq,
        "samples": scan.samples,
        "dropped": scan.dropped,
        "azimuth_counts": scan.azimuth.tolist(),
        "azimuth_deg": [round(float(a), 4) for a in scan.azimuth_deg],
        "t": scan.t.tolist(),
        "closest_mm": scan.closest_mm.tolist(),
        "closest_xy_m": np.round(closest_points_xy(scan), 4).tolist(),
        "range_mm": scan.range_mm.tolist(),
        "intensity": scan.intensity.tolist(),
    }


# -- files -----------------------------------------------------------------------------------------


def save_files(path: str | Path, scans: list[Scan]) -> tuple[Path, Path]:
    """``--save PATH``: PATH.npz and PATH.csv (a given .npz or .csv suffix is replaced), in a
    folder made if need be; returns both paths."""
    stem = Path(path)
    if stem.suffix in (".npz", ".csv"):
        stem = stem.with_suffix("")
    stem.parent.mkdir(parents=True, exist_ok=True)
    npz = scanfile.save_scans(stem.with_name(stem.name + ".npz"), scans)
    table = scanfile.export_csv(stem.with_name(stem.name + ".csv"), scans)
    return npz, table

"""``biris scan``: one scan to an azimuth, or continuous sweeps; a summary, files, a picture.

A single scan (``--to DEG``) is the report's BIRIS_SINGLE_SCAN_RQST: the head turns from where it
stands to DEG while BIRIS acquires, and the command prints that scan. Continuous scanning
(``--cw DEG --ccw DEG --sweeps N``) is BIRIS_CONT_SCAN_RQST read through a DATA connection, so
every completed sweep is received (none skipped, and any that were would be counted); the first
sweep runs from where the head stands to the CW limit, so it is shorter than the others.

``--save PATH`` writes PATH.npz (every array of every scan, for programs) and PATH.csv (one row
per acquisition with its range profile, for spreadsheets); :func:`load_scans` reads the .npz back
into :class:`~biris_hw.Scan` objects.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from collections.abc import Sequence
from os import PathLike
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from biris_hw.commands.common import (
    Session,
    UsageError,
    add_target_arguments,
    add_timeout_argument,
    degrees,
    open_session,
)
from biris_hw.data import ConnectionKind, Direction, Scan
from biris_hw.plots import closest_points_xy

__all__ = [
    "add_arguments",
    "load_scans",
    "run",
    "save_scans",
    "scan_summary",
    "scan_to_json",
]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    how = parser.add_argument_group("what to scan (one of)")
    how.add_argument("--to", type=degrees, metavar="DEG", help="one scan to DEG degrees")
    how.add_argument("--cw", type=degrees, metavar="DEG", help="continuous: clockwise limit")
    how.add_argument(
        "--ccw", type=degrees, metavar="DEG", help="continuous: counter-clockwise limit"
    )
    how.add_argument(
        "--sweeps",
        type=_count,
        default=None,
        metavar="N",
        help="continuous: stop after N sweeps (default 2)",
    )
    out = parser.add_argument_group("output")
    out.add_argument("--json", action="store_true", help="one JSON object per scan")
    out.add_argument(
        "--save", metavar="PATH", help="write PATH.npz (all arrays) and PATH.csv (ranges)"
    )
    out.add_argument("--plot", metavar="PATH", help="write a polar picture (PNG)")
    add_timeout_argument(parser)
    add_target_arguments(parser)


def _count(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, not {value}")
    return value


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
        npz, table = save_scans(scans, args.save)
        print(f"saved {npz} and {table}", file=stream)
    if args.plot is not None:
        from biris_hw.plots import save_polar

        latest = {scan.direction: scan for scan in scans}
        path = save_polar(args.plot, list(latest.values()), outline)
        print(f"picture: {path}", file=stream)
    return 0


def _single(session: Session, args: argparse.Namespace) -> list[Scan]:
    conn = session.server.open()
    start = int(session.server.status()["azimuth"])
    dest = conn.single_scan(args.to)
    conn.wait_idle(timeout=args.timeout)
    scan = conn.request_scan_data(Direction.of_motion(start, dest))
    conn.close()
    if scan is None:
        raise TimeoutError("the scan ended without delivering data")
    return [scan]


def _sweeps(session: Session, args: argparse.Namespace, stream: TextIO) -> list[Scan]:
    conn = session.server.open()
    data = session.server.open(ConnectionKind.DATA)
    wanted = args.sweeps or 2
    conn.continuous_scan(args.cw, args.ccw)
    scans: list[Scan] = []
    while len(scans) < wanted:  # on an error the session's close stops the head
        scan = data.ready_for_data(timeout=args.timeout)
        scans.append(scan)
        _report(scan, args, stream)
    conn.stop_scan()  # ends when the sweep under way completes
    conn.wait_idle(timeout=args.timeout)
    data.close()
    conn.close()
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


def _stem(path: str | PathLike[str]) -> Path:
    p = Path(path)
    return p.with_suffix("") if p.suffix in (".npz", ".csv") else p


def save_scans(scans: Sequence[Scan], path: str | PathLike[str]) -> tuple[Path, Path]:
    """Write PATH.npz and PATH.csv (a given .npz or .csv suffix is replaced); returns both.

    The .npz holds the acquisitions of all scans one after the other, ``scan_index`` saying
    which scan each row belongs to, and per scan its ``direction`` (0 CW, 1 CCW), ``seq`` and
    ``dropped``. The .csv has one row per acquisition and one column per sample.
    """
    if not scans:
        raise UsageError("no scans to save")
    stem = _stem(path)
    stem.parent.mkdir(parents=True, exist_ok=True)
    npz, table = stem.with_suffix(".npz"), stem.with_suffix(".csv")
    index = np.concatenate([np.full(s.n_acq, i, dtype=np.int32) for i, s in enumerate(scans)])
    with open(npz, "wb") as f:
        np.savez_compressed(
            f,
            scan_index=index,
            direction=np.array([int(s.direction) for s in scans], dtype=np.int8),
            seq=np.array([s.seq for s in scans], dtype=np.int32),
            dropped=np.array([s.dropped for s in scans], dtype=np.int32),
            azimuth=np.concatenate([s.azimuth for s in scans]),
            azimuth_deg=np.concatenate([s.azimuth_deg for s in scans]),
            t=np.concatenate([s.t for s in scans]),
            closest_mm=np.concatenate([s.closest_mm for s in scans]),
            range_mm=np.concatenate([s.range_mm for s in scans]),
            intensity=np.concatenate([s.intensity for s in scans]),
        )
    samples = scans[0].samples
    with open(table, "w", newline="", encoding="ascii") as f:
        writer = csv.writer(f)
        writer.writerow(
            ["scan", "direction", "seq", "acq", "t_s", "azimuth_counts", "azimuth_deg"]
            + ["closest_mm"]
            + [f"range_{k + 1}_mm" for k in range(samples)]
        )
        for i, scan in enumerate(scans):
            az_deg = scan.azimuth_deg
            for k in range(scan.n_acq):
                writer.writerow(
                    [
                        i,
                        scan.direction.name,
                        scan.seq,
                        k,
                        f"{scan.t[k]:.6f}",
                        int(scan.azimuth[k]),
                        f"{az_deg[k]:.4f}",
                        int(scan.closest_mm[k]),
                        *scan.range_mm[k].tolist(),
                    ]
                )
    return npz, table


def load_scans(path: str | PathLike[str]) -> list[Scan]:
    """The scans a :func:`save_scans` .npz holds, in the order they were saved."""
    with np.load(_stem(path).with_suffix(".npz")) as data:
        index = data["scan_index"]
        scans = []
        for i, (direction, seq, dropped) in enumerate(
            zip(data["direction"], data["seq"], data["dropped"], strict=True)
        ):
            rows = index == i
            scans.append(
                Scan(
                    direction=Direction(int(direction)),
                    seq=int(seq),
                    azimuth=data["azimuth"][rows],
                    range_mm=data["range_mm"][rows],
                    closest_mm=data["closest_mm"][rows],
                    intensity=data["intensity"][rows],
                    t=data["t"][rows],
                    dropped=int(dropped),
                )
            )
    return scans

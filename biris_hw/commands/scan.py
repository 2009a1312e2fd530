"""``biris scan``: one scan to an azimuth, or continuous sweeps; a summary, files, a picture.

A single scan (``--to DEG``) is the report's BIRIS_SINGLE_SCAN_RQST: the head turns from where it
stands to DEG while BIRIS acquires, and the command prints that scan. Continuous scanning
(``--cw DEG --ccw DEG --sweeps N``) is BIRIS_CONT_SCAN_RQST read through a DATA connection, so
every completed sweep is received (none skipped, and any that were would be counted); the first
sweep runs from where the head stands to the CW limit, so it is shorter than the others.

``--save PATH`` writes PATH.npz (every scan whole, for programs:
:func:`biris_hw.io.scanfile.load_scans` reads it back into equal :class:`~biris_hw.Scan` objects)
and PATH.csv (one row per acquisition with its range profile, for spreadsheets); see
:mod:`biris_hw.io.scanfile`. ``--save PATH.mcap`` writes that one MCAP file instead (extra
``.[record]``): each scan's ``sensor_msgs/msg/PointCloud2`` and its lossless record, which
Foxglove, Lichtblick and ``ros2 bag`` open and ``biris replay`` plays back
(:func:`biris_hw.io.record.write_scans`). ``--plot PATH`` draws every scan the command made. Both
are checked before the sensor is touched, so a typo in a folder name costs nothing.

An angle beyond _Scan_limit (+-360 degrees) is clamped by the server and the command says so; on
a real target a move of more than half a turn needs ``--yes``. Ctrl-C during ``--sweeps N``
keeps the sweeps completed so far: they are saved and drawn as asked, the command says how many
of N it wrote, and the exit status is 130.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from biris_hw.angles import destination_counts
from biris_hw.commands.argtypes import degrees, path, positive_int
from biris_hw.commands.console import note_clamped, prog_of
from biris_hw.commands.failures import EXIT_INTERRUPTED, UsageError
from biris_hw.commands.options import (
    add_continuous_argument,
    add_target_arguments,
    add_timeout_argument,
    add_yes_argument,
    check_output_file,
    sweep_chosen,
)
from biris_hw.commands.session import Session, confirm_moves, open_session
from biris_hw.data import Direction, Scan

__all__ = [
    "DEFAULT_SWEEPS",
    "add_arguments",
    "picture_suffixes",
    "run",
    "save_files",
    "save_paths",
    "scan_summary",
    "scan_to_json",
]

DEFAULT_SWEEPS = 2


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
        help=f"continuous: stop after N sweeps (default {DEFAULT_SWEEPS}); Ctrl-C keeps "
        "the sweeps completed so far",
    )
    out = parser.add_argument_group("output")
    out.add_argument("--json", action="store_true", help="one JSON object per scan")
    out.add_argument(
        "--save",
        type=path,
        metavar="PATH",
        help="write PATH.npz (every scan, whole) and PATH.csv (ranges, for spreadsheets); "
        "PATH.mcap: one MCAP file (ROS 2 point clouds, replayable) instead",
    )
    out.add_argument(
        "--plot",
        type=path,
        metavar="PATH",
        help="draw every scan made in one polar picture at PATH (.png, .svg, .pdf...)",
    )
    add_continuous_argument(parser)
    add_yes_argument(parser)
    add_timeout_argument(parser)
    add_target_arguments(parser)


def _check(args: argparse.Namespace) -> None:
    continuous = sweep_chosen(args)
    if args.to is None and not continuous:
        raise UsageError("say what to scan: --to DEG, or --cw DEG --ccw DEG")
    if args.sweeps is not None and not continuous:
        raise UsageError("--sweeps goes with --cw/--ccw")
    if args.save is not None:
        if Path(args.save).is_dir():
            raise UsageError(
                f"--save {args.save}: is a folder; name the files, e.g. {Path(args.save) / 'run1'}"
            )
        for file in save_paths(args.save):
            check_output_file("--save", file)
    if args.plot is not None:
        check_output_file("--plot", args.plot, suffixes=picture_suffixes())


def picture_suffixes() -> frozenset[str]:
    """The extensions ``--plot`` understands: what matplotlib can write (``.png``, ``.svg``,
    ``.pdf``...). Importing matplotlib here also fails now, not after the scan, if it is
    missing."""
    from matplotlib.backend_bases import FigureCanvasBase

    return frozenset(f".{kind}" for kind in FigureCanvasBase.get_supported_filetypes())


def run(args: argparse.Namespace, out: TextIO | None = None) -> int:
    """Scan, report, save and draw; 0 when every scan arrived, 130 after Ctrl-C (with what was
    completed by then saved and drawn)."""
    stream = out or sys.stdout
    _check(args)
    scans: list[Scan] = []
    interrupted = False
    with open_session(args) as session:
        if args.to is not None:
            scans = _single(session, args)
            _report(scans[0], args, stream)
        else:
            interrupted = _sweeps(session, args, stream, scans)
        outline = session.rig.scene.outline_2d() if session.rig is not None else None
        metadata = _mcap_metadata(session, args)
    written: list[Path] = []
    if scans and args.save is not None:
        saved = save_files(args.save, scans, metadata)
        print(f"saved {' and '.join(map(str, saved))}", file=stream)
        written += saved
    if scans and args.plot is not None:
        from biris_hw.io.plots import save_polar

        args.plot.parent.mkdir(parents=True, exist_ok=True)
        picture = save_polar(args.plot, scans, outline)  # every sweep made, in order
        print(f"picture: {picture}", file=stream)
        written.append(picture)
    if interrupted:
        print(f"{prog_of(args)}: {_interrupted(scans, args, written)}", file=sys.stderr)
        return EXIT_INTERRUPTED
    return 0


def _interrupted(scans: list[Scan], args: argparse.Namespace, written: list[Path]) -> str:
    """What Ctrl-C left: how many of the sweeps asked for were completed, and where they are."""
    wanted = args.sweeps or DEFAULT_SWEEPS
    if not scans:
        return f"interrupted before the first of {wanted} sweeps completed: nothing written"
    if not written:
        return f"interrupted after {len(scans)} of {wanted} sweeps (printed above)"
    where = ", ".join(str(p) for p in written[:-1])
    where = f"{where} and {written[-1]}" if where else str(written[-1])
    return f"interrupted: wrote {len(scans)} of {wanted} sweeps to {where}"


def _single(session: Session, args: argparse.Namespace) -> list[Scan]:
    with session.server.open() as conn:
        start = int(session.server.status()["azimuth"])
        confirm_moves(session, args, [(f"--to {args.to:g}", destination_counts(args.to, "--to"))])
        dest = conn.single_scan(args.to)
        note_clamped(session.prog, "--to", args.to, dest)
        conn.wait_idle(timeout=args.timeout)
        scan = conn.request_scan_data(Direction.of_motion(start, dest))
    if scan is None:
        raise TimeoutError("the scan ended without delivering data")
    return [scan]


def _sweeps(session: Session, args: argparse.Namespace, stream: TextIO, scans: list[Scan]) -> bool:
    """Sweep until ``--sweeps`` are in ``scans``; True if Ctrl-C ended it first.

    Ctrl-C is caught here, outside :func:`sweeping`, so the sweep under way is abandoned rather
    than waited for (the server, closed next, stops the head) and the sweeps completed so far
    stay in ``scans`` for the caller to write.
    """
    from biris_hw.io.sweeps import sweeping

    wanted = args.sweeps or DEFAULT_SWEEPS
    limits = [
        (f"--cw {args.cw:g}", destination_counts(args.cw, "--cw")),
        (f"--ccw {args.ccw:g}", destination_counts(args.ccw, "--ccw")),
    ]
    confirm_moves(session, args, limits)
    try:
        # On leaving: STOP (the sweep under way completes), the head at rest, connections closed.
        with sweeping(session.server, args.cw, args.ccw, timeout=args.timeout) as sweeps:
            note_clamped(session.prog, "--cw", args.cw, sweeps.limits[0])
            note_clamped(session.prog, "--ccw", args.ccw, sweeps.limits[1])
            for scan in sweeps:
                scans.append(scan)
                _report(scan, args, stream)
                if len(scans) == wanted:
                    break
    except KeyboardInterrupt:
        return True
    return False


def _report(scan: Scan, args: argparse.Namespace, stream: TextIO) -> None:
    text = json.dumps(scan_to_json(scan)) if args.json else scan_summary(scan)
    print(text, file=stream, flush=True)


# -- describing scans ------------------------------------------------------------------------------


def scan_summary(scan: Scan) -> str:
    """One line: direction, sequence, extent, the closest return, how much of it is valid, and
    whether it is partial (with the reason the scan gives)."""
    partial = ""
    if scan.partial:  # never silent (issue 21): and why, when the data say
        partial = ", partial sweep" + (f" ({scan.partial_reason})" if scan.partial_reason else "")
    head = f"{scan.direction.name} #{scan.seq}: {scan.n_acq} acquisitions"
    if scan.n_acq == 0:
        return f"{head}, dropped {scan.dropped}{partial}"
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
    return f"{text}, dropped {scan.dropped}{partial}"


def scan_to_json(scan: Scan) -> dict[str, Any]:
    """Everything in a scan, as plain JSON values (azimuths in counts and degrees)."""
    from biris_hw.io.plots import closest_points_xy

    return {
        "direction": scan.direction.name,
        "seq": scan.seq,
        "n_acq": scan.n_acq,
        "samples": scan.samples,
        "dropped": scan.dropped,
        "acquisition": scan.acquisition,
        "partial": scan.partial,
        "partial_reason": scan.partial_reason,
        "span_counts": None if scan.span is None else list(scan.span),
        "azimuth_counts": scan.azimuth.tolist(),
        "azimuth_deg": [round(float(a), 4) for a in scan.azimuth_deg],
        "t": scan.t.tolist(),
        "closest_mm": scan.closest_mm.tolist(),
        "closest_xy_m": np.round(closest_points_xy(scan), 4).tolist(),
        "range_mm": scan.range_mm.tolist(),
        "intensity": scan.intensity.tolist(),
    }


# -- files -----------------------------------------------------------------------------------------


def save_paths(path: str | Path) -> tuple[Path, ...]:
    """The files ``--save PATH`` writes: PATH.mcap alone for a ``.mcap`` name, else PATH.npz and
    PATH.csv (a given .npz or .csv suffix is replaced)."""
    stem = Path(path)
    if stem.suffix == ".mcap":
        return (stem,)
    if stem.suffix in (".npz", ".csv"):
        stem = stem.with_suffix("")
    return stem.with_name(stem.name + ".npz"), stem.with_name(stem.name + ".csv")


def save_files(
    path: str | Path, scans: list[Scan], metadata: dict[str, object] | None = None
) -> tuple[Path, ...]:
    """``--save PATH``: the files of :func:`save_paths`, in a folder made if need be; returns
    their paths. An MCAP file gets ``metadata`` in its ``biris`` record (the scene, the
    command)."""
    files = save_paths(path)
    files[0].parent.mkdir(parents=True, exist_ok=True)
    if files[0].suffix == ".mcap":
        from biris_hw.io.record import write_scans

        return (write_scans(files[0], scans, metadata=metadata),)
    from biris_hw.io import scanfile

    npz, table = files
    return scanfile.save_scans(npz, scans), scanfile.export_csv(table, scans)


def _mcap_metadata(session: Session, args: argparse.Namespace) -> dict[str, object] | None:
    """What an MCAP ``--save`` says about the sensor (the simulator's scene and settings, the
    target description), read while the session is open; None for other files."""
    if args.save is None or Path(args.save).suffix != ".mcap":
        return None
    from biris_hw.commands.record import recording_metadata

    return recording_metadata(session, args)

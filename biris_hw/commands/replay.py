"""``biris replay FILE``: play a recording back as a sensor; summaries, JSON, a picture.

The recording is served by :class:`~biris_hw.replay.ReplayServer` through the same client API a
live server offers, read here through a DATA connection that takes every completed scan
(EVERY_BUFFER), so every recorded scan is printed (``--json``: one object per scan, as ``biris
scan --json``) and ``--plot PATH`` draws them all, as ``biris scan --plot`` does for a live run.
``--speed X`` plays at X times the recorded pace (default: as fast as possible). A file damaged
part way is printed up to the damage, then reported on one line with exit status 1 (a file
that is not a recording at all is a usage error, 2).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TextIO

from biris_hw.commands.argtypes import path, positive_float
from biris_hw.commands.common import (
    EXIT_FAULT,
    UsageError,
    add_debug_argument,
    check_output_file,
    prog_of,
    report_error,
)
from biris_hw.data import ConnectionKind, DeliveryPolicy, Scan

__all__ = ["add_arguments", "run"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", type=path, metavar="FILE", help="a recording (.mcap)")
    parser.add_argument(
        "--speed",
        type=positive_float,
        default=None,
        metavar="X",
        help="X times the recorded pace (default: as fast as possible)",
    )
    parser.add_argument("--json", action="store_true", help="one JSON object per scan")
    parser.add_argument(
        "--plot",
        type=path,
        metavar="PATH",
        help="draw every recorded scan in one polar picture at PATH (.png, .svg, .pdf...)",
    )
    add_debug_argument(parser)


def run(args: argparse.Namespace, out: TextIO | None = None) -> int:
    """Play the file; 0 when every scan was read (and drawn, if asked), 1 when the file is
    damaged part way (what came before is printed)."""
    from biris_hw.commands.scan import picture_suffixes, scan_summary, scan_to_json
    from biris_hw.replay import EndOfRecording, ReplayError, ReplayServer

    stream = out or sys.stdout
    if not Path(args.file).is_file():
        raise UsageError(f"{args.file}: no such file")
    if args.plot is not None:
        check_output_file("--plot", args.plot, suffixes=picture_suffixes())
    scans: list[Scan] = []
    with ReplayServer(args.file, speed=args.speed) as replay:
        data = replay.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_BUFFER, depth=64)
        while True:
            try:
                scan = data.ready_for_data(timeout=None)
            except EndOfRecording:
                break
            except ReplayError as exc:  # damaged part way: what came before is printed
                stream.flush()
                report_error(prog_of(args), exc, debug=getattr(args, "debug", False))
                return EXIT_FAULT
            scans.append(scan)
            text = json.dumps(scan_to_json(scan)) if args.json else scan_summary(scan)
            print(text, file=stream, flush=True)
        played = dict(replay.played)
    if not args.json:
        print(
            f"replayed {args.file}: {played['scans']} scans, {played['points']} acquisitions, "
            f"{played['statuses']} status records",
            file=stream,
        )
    if args.plot is not None:
        from biris_hw.plots import save_polar

        args.plot.parent.mkdir(parents=True, exist_ok=True)
        print(f"picture: {save_polar(args.plot, scans)}", file=stream)
    return 0

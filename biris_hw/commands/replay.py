"""``biris replay FILE``: play a recording back as a sensor; summaries, JSON, a picture.

The recording is served by :class:`~biris_hw.io.record.ReplayServer` through the same client API a
live server offers, read here through a DATA connection that takes every completed scan
(EVERY_BUFFER), so every recorded scan is printed (``--json``: one object per scan, as ``biris
scan --json``) and ``--plot PATH`` draws them all, as ``biris scan --plot`` does for a live run.
``--speed X`` plays at X times the recorded pace (default: as fast as possible). A file damaged
part way is printed up to the damage, then reported on one line with exit status 1 (a file
that is not a recording at all is a usage error, 2). A file without a footer (its recorder was
killed) plays up to its last complete chunk with exit status 0: the replay's warning says so on
stderr (``biris: warning: FILE ends without a footer ...``), and the last line adds it.

``--check`` reads every scan instead of printing it and judges the stream by
:mod:`biris_hw.scancheck` (issue 21: no silently short or empty scan, none holding another's
rows): each violation on a line of its own, naming the scan (its place in the file, direction
and ``seq``) and the row, then one summary line, ``FILE: checked N scans: OK`` or ``FILE: N
violations in M scans (of K checked)``; the exit status is 1 if any scan broke a rule (or the
file is damaged part way, after what came before was checked), 0 otherwise. It also takes a
scan file (``.npz``, :mod:`biris_hw.io.scanfile`), which ``biris scan --save`` and ``biris demo``
write.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, TextIO

from biris_hw.commands.argtypes import path, positive_float
from biris_hw.commands.console import prog_of
from biris_hw.commands.failures import EXIT_FAULT, UsageError, report_error
from biris_hw.commands.options import add_debug_argument, check_output_file
from biris_hw.data import ConnectionKind, DeliveryPolicy, Scan

if TYPE_CHECKING:
    from biris_hw.io.record.replay import ReplayServer

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
    parser.add_argument(
        "--check",
        action="store_true",
        help="check every scan against the scan invariants (biris_hw.scancheck) instead of "
        "printing it: each violation, then a summary; exit 1 on any (FILE may be a .npz "
        "scan file too)",
    )
    add_debug_argument(parser)


def run(args: argparse.Namespace, out: TextIO | None = None) -> int:
    """Play the file; 0 when every scan was read (and drawn, if asked), 1 when the file is
    damaged part way (what came before is printed). With ``--check``: 0 when every scan keeps
    the invariants, 1 when one does not (or the file is damaged)."""
    from biris_hw.commands.scan import picture_suffixes, scan_summary, scan_to_json
    from biris_hw.io.record.replay import ReplayError
    from biris_hw.opening import open_sensor

    stream = out or sys.stdout
    if not Path(args.file).is_file():
        raise UsageError(f"{args.file}: no such file")
    if getattr(args, "check", False):
        if args.json or args.plot is not None:
            raise UsageError("--check prints violations and a summary: not with --json or --plot")
        return _check(args, stream)
    if args.plot is not None:
        check_output_file("--plot", args.plot, suffixes=picture_suffixes())
    scans: list[Scan] = []
    with open_sensor(replay=args.file, speed=args.speed) as replay:
        try:
            for scan in _every_scan(replay):
                scans.append(scan)
                text = json.dumps(scan_to_json(scan)) if args.json else scan_summary(scan)
                print(text, file=stream, flush=True)
        except ReplayError as exc:  # damaged part way: what came before is printed
            stream.flush()
            report_error(prog_of(args), exc, debug=getattr(args, "debug", False))
            return EXIT_FAULT
        played = dict(replay.played)
        cut = " (up to its last complete chunk: it has no footer)" if replay.recovered else ""
    if not args.json:
        print(
            f"replayed {args.file}: {played['scans']} scans, {played['points']} acquisitions, "
            f"{played['statuses']} status records{cut}",
            file=stream,
        )
    if args.plot is not None:
        from biris_hw.io.plots import save_polar

        args.plot.parent.mkdir(parents=True, exist_ok=True)
        print(f"picture: {save_polar(args.plot, scans)}", file=stream)
    return 0


def _every_scan(replay: ReplayServer) -> Iterator[Scan]:
    """Every scan of the recording, in the order recorded: an EVERY_BUFFER connection, which
    makes the player wait for it (``speed=None``) so that none is dropped. Raises
    :class:`~biris_hw.io.record.replay.ReplayError` where the file is damaged."""
    from biris_hw.io.record.replay import EndOfRecording

    data = replay.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_BUFFER, depth=64)
    while True:
        try:
            yield data.ready_for_data(timeout=None)
        except EndOfRecording:
            return


def _check(args: argparse.Namespace, stream: TextIO) -> int:
    """``--check``: judge every scan of the file; 1 on any violation or a damaged file."""
    from biris_hw.io.record.replay import ReplayError
    from biris_hw.opening import open_sensor
    from biris_hw.scancheck import ScanChecker

    checker = ScanChecker()

    def judge(scan: Scan) -> None:
        for text in checker.add(scan):
            print(f"scan {checker.scans}, {text}", file=stream, flush=True)

    if Path(args.file).suffix == ".npz":
        from biris_hw.io import scanfile

        try:
            scans = scanfile.load_scans(args.file)
        except (OSError, ValueError) as exc:  # load_scans names the file in its message
            text = str(exc) if str(exc).startswith(str(args.file)) else f"{args.file}: {exc}"
            raise UsageError(f"not a scan file: {text}") from exc
        for scan in scans:
            judge(scan)
    else:
        with open_sensor(replay=args.file, speed=args.speed) as replay:
            try:
                for scan in _every_scan(replay):
                    judge(scan)
            except ReplayError as exc:  # damaged part way: what came before was judged
                print(f"{args.file}: {checker.summary()} before the damage", file=stream)
                stream.flush()
                report_error(prog_of(args), exc, debug=getattr(args, "debug", False))
                return EXIT_FAULT
    print(f"{args.file}: {checker.summary()}", file=stream, flush=True)
    return 0 if checker.ok else EXIT_FAULT

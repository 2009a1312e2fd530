"""``biris record``: record a sensor to MCAP (ROS 2 message types) while it scans.

``biris record --sim --out run.mcap --duration 10 --cw -45 --ccw 45`` starts a server (or uses
the sensor named by the session flags), opens a :class:`~biris_hw.io.record.Recorder` on it, sweeps
between the limits (``--to DEG``: one scan; neither: nothing is commanded, whatever the sensor
does is recorded) and stops after ``--duration`` seconds or at Ctrl-C. The file is checked
before the sensor is touched, and an existing file is refused (exit 2, the file untouched)
unless ``--force`` is given. The file is closed with its summary however the run ends, within
:data:`~biris_hw.io.record.recorder.CLOSE_TIMEOUT_S` (what the recorder then had no time to write
is dropped and counted), and the command prints what it holds and what was dropped however the
run ends too: after Ctrl-C or SIGTERM (exit 130 or 143, the file complete: :mod:`biris_hw.cli`
turns SIGTERM into the same KeyboardInterrupt), and before the error's line when a
fault, a timeout, a full disk or a network to the service lost for longer than
:data:`~biris_hw.io.feed.LOST_LIMIT_S` stops the run (exit 1, or 2 for a full disk, with a
valid, shorter file). A shorter loss of the network is ridden out: the summary names the span.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, TextIO

from biris_hw.commands.argtypes import degrees, path, positive_float
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
from biris_hw.commands.session import Session, confirm_moves, open_session, quiet_collector

if TYPE_CHECKING:
    from biris_hw.io.record import Recorder

__all__ = ["add_arguments", "recording_metadata", "run"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    out = parser.add_argument_group("recording")
    out.add_argument(
        "--out",
        type=path,
        required=True,
        metavar="FILE",
        help="the .mcap file (an existing one is refused without --force)",
    )
    out.add_argument(
        "--force", action="store_true", help="overwrite FILE if it exists (default: refuse)"
    )
    out.add_argument(
        "--duration",
        type=positive_float,
        default=None,
        metavar="S",
        help="stop after S real seconds (default: after --to's scan, else at Ctrl-C)",
    )
    out.add_argument(
        "--frame",
        choices=("vehicle", "sensor"),
        default="vehicle",
        help="frame of the scan clouds on /biris/points (default vehicle)",
    )
    out.add_argument(
        "--no-profiles",
        action="store_true",
        help="leave out the per-acquisition profile clouds (the lossless data stay)",
    )
    how = parser.add_argument_group("what to scan meanwhile (optional)")
    how.add_argument("--to", type=degrees, metavar="DEG", help="one scan to DEG degrees")
    how.add_argument("--cw", type=degrees, metavar="DEG", help="sweep: clockwise limit")
    how.add_argument("--ccw", type=degrees, metavar="DEG", help="sweep: counter-clockwise limit")
    add_continuous_argument(parser)
    add_yes_argument(parser)
    add_timeout_argument(parser)
    add_target_arguments(parser)


def _check(args: argparse.Namespace) -> None:
    sweep_chosen(args)
    if args.to is None and args.duration is None:
        raise UsageError("say how long to record: --duration S (or --to DEG for one scan)")
    out = check_output_file("--out", Path(args.out), suffixes={".mcap"})
    if (out.exists() or out.is_symlink()) and not getattr(args, "force", False):
        raise UsageError(
            f"--out {out}: the file exists; give another name, or --force to overwrite it"
        )


def recording_metadata(session: Session, args: argparse.Namespace) -> dict[str, object]:
    """What the file's ``biris`` metadata says about the sensor: the simulator's scene and
    settings, or the target description's text."""
    meta: dict[str, object] = {"command": " ".join(sys.argv[1:]) or "biris record"}
    if session.rig is not None:
        rig = session.rig
        meta["scene"] = repr(rig.scene)
        meta["simulator"] = {
            "scene": getattr(args, "scene", None),
            "samples": rig.samples,
            "time_scale": rig.time_scale,
            "seed": rig.seed,
        }
    target = getattr(args, "target", None)
    if target is not None:
        try:
            meta["target_description"] = Path(target).read_text()
        except OSError as exc:
            meta["target_description"] = f"unreadable: {exc}"
    return meta


def run(args: argparse.Namespace, out: TextIO | None = None) -> int:
    """Record; 0 when done, 130 after Ctrl-C (the file complete either way)."""
    from biris_hw.io.record import Recorder

    stream = out or sys.stdout
    _check(args)
    interrupted = False
    recorder: Recorder | None = None
    try:
        with open_session(args) as session:
            quiet_collector()
            recorder = Recorder(
                session.server,
                args.out,
                frame=args.frame,
                profiles=not args.no_profiles,
                metadata=recording_metadata(session, args),
                overwrite=getattr(args, "force", False),
            )
            try:
                with recorder:
                    _scan(session, args, recorder)
            except KeyboardInterrupt:  # Ctrl-C (or SIGTERM), even a second one during close
                interrupted = True
    finally:  # however the run ended (a fault, a full disk): what the file holds, then the error
        summary = None
        if recorder is not None:
            summary = recorder.summary
            if summary is None:  # close() was interrupted (a second Ctrl-C): once more
                summary = recorder.close()
        if summary is not None:
            print(f"recorded {summary}", file=stream, flush=True)
    if interrupted:
        print(f"{prog_of(args)}: interrupted: {args.out} is complete up to then", file=sys.stderr)
        return EXIT_INTERRUPTED
    return 0


def _scan(session: Session, args: argparse.Namespace, recorder: Recorder) -> None:
    """Command the head as asked while ``recorder`` runs, until the duration is over."""
    from biris_hw.angles import destination_counts
    from biris_hw.io.sweeps import sweeping

    end = None if args.duration is None else time.monotonic() + args.duration

    def left() -> float | None:
        return None if end is None else max(0.0, end - time.monotonic())

    if args.cw is not None:
        limits = [
            (f"--cw {args.cw:g}", destination_counts(args.cw, "--cw")),
            (f"--ccw {args.ccw:g}", destination_counts(args.ccw, "--ccw")),
        ]
        confirm_moves(session, args, limits)
        with sweeping(session.server, args.cw, args.ccw, timeout=args.timeout) as sweeps:
            note_clamped(session.prog, "--cw", args.cw, sweeps.limits[0])
            note_clamped(session.prog, "--ccw", args.ccw, sweeps.limits[1])
            while not recorder.failed.is_set() and (left() or 0.0) > 0.0:
                sweeps.next(timeout=min(left() or 0.0, args.timeout))
    elif args.to is not None:
        with session.server.open() as conn:
            confirm_moves(
                session, args, [(f"--to {args.to:g}", destination_counts(args.to, "--to"))]
            )
            dest = conn.single_scan(args.to)
            note_clamped(session.prog, "--to", args.to, dest)
            conn.wait_idle(timeout=args.timeout)
        if args.duration is not None:
            recorder.failed.wait(left())
    else:
        recorder.failed.wait(left())

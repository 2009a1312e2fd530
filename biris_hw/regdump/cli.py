"""``biris regdump``'s command line: its options, and one dump or a ``--watch`` of them."""

from __future__ import annotations

import argparse
import json
import sys
import traceback
from typing import TextIO

from biris_hw import regdump as package
from biris_hw.commands.argtypes import SAMPLES_METAVAR, offset, positive_int, samples
from biris_hw.errors import BirisError
from biris_hw.regdump.decode import snapshot, snapshot_hardware
from biris_hw.regdump.images import image_layout, images
from biris_hw.regdump.model import Dump, DumpError, changed_rows
from biris_hw.regdump.render import format_table, to_json
from regs.layout import BirisMemoryMap, TargetImage

__all__ = ["add_arguments", "run"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The ``regdump`` options (the caller owns the parser)."""
    src = parser.add_mutually_exclusive_group(required=True)
    src.add_argument("--file", metavar="PATH", help="a raw image file")
    src.add_argument("--mmap", metavar="PATH", help="map a file or device (see --offset)")
    src.add_argument("--shm", metavar="NAME", help="a shared-memory segment (the simulator's)")
    src.add_argument(
        "--target",
        metavar="FILE",
        help="the windows of a target file, any kind (mmap, vmusb, ...): docs/target-example.toml",
    )
    parser.add_argument(
        "--offset", type=offset, default=0, metavar="N", help="where the image starts (bytes)"
    )
    img = TargetImage()
    mm = img.biris
    for flag, default, what in (
        ("--coupler-at", img.coupler_offset, "Bit 3 coupler registers"),
        ("--motion-at", img.motion_offset, "Model 7600 board"),
        ("--biris-at", img.biris_offset, "BIRIS memory"),
    ):
        parser.add_argument(
            flag, type=offset, default=default, metavar="N", help=f"image offset of the {what}"
        )
    parser.add_argument(
        "--samples", type=samples, default=mm.samples, metavar=SAMPLES_METAVAR,
        help="samples per frame",
    )  # fmt: skip
    parser.add_argument(
        "--biexec-offset", type=offset, default=mm.biexec_offset, metavar="N",
        help="BIEXEC_COM's offset in the BIRIS window",
    )  # fmt: skip
    parser.add_argument(
        "--range-base", type=offset, default=mm.range_offset, metavar="N",
        help="range array's offset in the BIRIS window",
    )  # fmt: skip
    parser.add_argument(
        "--frame-size", type=positive_int, default=None, metavar="N",
        help="bytes per frame (default: from --samples)",
    )  # fmt: skip
    parser.add_argument("--json", action="store_true", help="one JSON object per dump")
    parser.add_argument(
        "--watch",
        type=positive_int,
        default=None,
        metavar="MS",
        help="dump every MS ms, marking changes with *",
    )
    parser.add_argument(
        "--count", type=positive_int, default=None, metavar="K", help="stop after K dumps"
    )
    parser.add_argument(
        "--debug", action="store_true", default=argparse.SUPPRESS, help="show tracebacks"
    )


def _emit(
    dump: Dump, changed: frozenset[tuple[str, str]], n: int, args: argparse.Namespace, out: TextIO
) -> None:
    if args.json:
        data = to_json(dump, changed)
        data["dump"] = n
        text = json.dumps(data, separators=(",", ":")) if args.watch else json.dumps(data, indent=2)
        out.write(text + "\n")
    else:
        if args.watch:
            out.write(f"=== dump {n}: {len(changed)} changed ===\n")
        out.write(format_table(dump, changed))
    out.flush()


def _target_loop(args: argparse.Namespace, out: TextIO) -> int:
    """``--target``: the three windows a target file opens (a VM-USB's too), dumped where the
    file puts them; its interrupt lines are opened with it and touched by nothing."""
    from biris_hw.target import load_target  # only when asked: it opens devices

    hardware = load_target(args.target)
    try:
        memory_map = BirisMemoryMap(
            samples=args.samples,
            biris_base=hardware.biris_base,
            biexec_offset=hardware.biexec_offset,
            range_offset=args.range_base,
        )
        previous: Dump | None = None
        n = 0
        while True:
            n += 1
            dump = snapshot_hardware(hardware, memory_map, frame_size=args.frame_size)
            dump = Dump(f"target {args.target}", dump.layout, dump.sections)
            _emit(dump, changed_rows(previous, dump), n, args, out)
            previous = dump
            if args.watch is None or (args.count is not None and n >= args.count):
                return 0
            package._sleep(args.watch / 1000.0)
    finally:
        hardware.close()


def _dump_loop(args: argparse.Namespace, out: TextIO) -> int:
    if args.count is not None and args.watch is None:
        raise DumpError("--count needs --watch")
    if getattr(args, "target", None) is not None:
        return _target_loop(args, out)
    image = image_layout(args)
    context, base, label = images(args, image.size)
    with context as next_window:
        previous: Dump | None = None
        n = 0
        while True:
            n += 1
            window = next_window()
            try:
                dump = snapshot(window, image, base=base, frame_size=args.frame_size, source=label)
            finally:
                if args.file is not None:
                    window.close()
            _emit(dump, changed_rows(previous, dump), n, args, out)
            previous = dump
            if args.watch is None or (args.count is not None and n >= args.count):
                return 0
            package._sleep(args.watch / 1000.0)  # looked up each time: tests replace it


def run(args: argparse.Namespace, out: TextIO | None = None) -> int:
    """Run ``biris regdump``: 0 when done (or on Ctrl-C), 2 with one line on stderr on error."""
    try:
        return _dump_loop(args, out or sys.stdout)
    except KeyboardInterrupt:
        return 0
    except (BirisError, OSError, ValueError, LookupError) as exc:
        if getattr(args, "debug", False):
            traceback.print_exc(file=sys.stderr)
        message = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        print(f"biris regdump: {message}", file=sys.stderr)
        return 2

"""The ``biris`` command."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from typing import NoReturn

from biris_hw import regdump

__all__ = ["main"]


class _OneLineParser(argparse.ArgumentParser):
    """Reports a usage error as one line (``biris regdump: ...``) and exit status 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="biris", description=__doc__)
    parser.add_argument("--debug", action="store_true", help="show tracebacks")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_OneLineParser)
    sub.add_parser("demo", help="the simulated robot at work (main job)")
    regdump.add_arguments(
        sub.add_parser(
            "regdump",
            help="decode the registers of a target image (file, mmap or shared memory)",
            description="Decode the coupler, Model 7600 and BIRIS registers of a target image.",
        )
    )
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help, or a usage error already reported
        return exc.code if isinstance(exc.code, int) else 2
    if args.command == "demo":
        print("biris demo: the simulator and server demo arrives with the demo issue.")
        return 0
    if args.command == "regdump":
        return regdump.run(args)
    parser.print_help()
    return 2


if __name__ == "__main__":
    sys.exit(main())

"""``make test-under-load``: run a command with CPU-bound processes beside it (sim.hostload).

    tools/under_load.py [--processes N] -- COMMAND [ARG...]

The exit status is the command's (128 + the signal's number if a signal ended it), so make and
CI read it as they would read the command's own. The load starts before the command and is
stopped and reaped after it, whatever ends it (Ctrl-C reaches both; SIGTERM is passed on to
the command); if this script is killed outright, the load processes notice and stop by
themselves (see sim.hostload).
"""

from __future__ import annotations

import argparse
import signal
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path
from types import FrameType

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from sim.hostload import busy_processes  # this checkout's (the line above)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="tools/under_load.py",
        description="Run COMMAND with N CPU-bound processes beside it; exit with its status.",
    )
    parser.add_argument(
        "--processes", type=int, default=3, metavar="N", help="load processes (default 3)"
    )
    parser.add_argument("command", nargs=argparse.REMAINDER, help="the command, after --")
    args = parser.parse_args(argv)
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not command:
        parser.error("no command given (tools/under_load.py -- COMMAND ...)")
    if args.processes < 0:
        parser.error("--processes must be 0 or more")

    with busy_processes(args.processes) as load:
        pids = " ".join(map(str, load.pids)) or "none"
        print(
            f"under_load: {load.count} CPU-bound processes (pids {pids}) beside: "
            + " ".join(command),
            file=sys.stderr,
            flush=True,
        )
        child = subprocess.Popen(command)

        def forward(signum: int, frame: FrameType | None) -> None:
            child.send_signal(signum)  # the command ends as it would alone; then the load

        signal.signal(signal.SIGTERM, forward)
        while True:
            try:
                returncode = child.wait()
                break
            except KeyboardInterrupt:
                continue  # Ctrl-C reached the command too (same process group): let it finish
    status = returncode if returncode >= 0 else 128 - returncode
    print(f"under_load: load stopped; the command's exit status: {status}", file=sys.stderr)
    return status


if __name__ == "__main__":
    sys.exit(main())

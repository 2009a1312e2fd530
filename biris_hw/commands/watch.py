"""``biris watch``: the server's status, refreshed, for a while or until Ctrl-C.

What ``BirisServer.status()`` says (state, azimuth, counters, interrupts per logical line,
connections) is redrawn in place with rich when a person is watching, and printed as one line
per refresh otherwise, so the same command feeds a log. With ``--cw``/``--ccw`` the head sweeps
while it is watched (a server at rest has little to show); at the end the sweep under way is
allowed to finish. A hardware fault seen while watching makes the exit status 1.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import threading
import time
from collections.abc import Mapping
from typing import Any, TextIO

from biris_hw.angles import counts_to_deg
from biris_hw.commands.argtypes import degrees, seconds
from biris_hw.commands.common import (
    UsageError,
    add_target_arguments,
    add_timeout_argument,
    is_terminal,
    open_session,
)
from biris_hw.sweeps import sweeping

__all__ = ["add_arguments", "run", "status_line", "status_table"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--duration",
        type=seconds,
        default=None,
        metavar="S",
        help="stop after S real seconds (default: at Ctrl-C)",
    )
    parser.add_argument(
        "--interval",
        type=seconds,
        default=0.5,
        metavar="S",
        help="seconds between refreshes (default 0.5)",
    )
    parser.add_argument("--cw", type=degrees, metavar="DEG", help="sweep while watching: CW limit")
    parser.add_argument(
        "--ccw", type=degrees, metavar="DEG", help="sweep while watching: CCW limit"
    )
    add_timeout_argument(parser)
    add_target_arguments(parser)


def run(args: argparse.Namespace, out: TextIO | None = None) -> int:
    stream = out or sys.stdout
    if (args.cw is None) != (args.ccw is None):
        raise UsageError("sweeping while watching needs both --cw and --ccw")
    with open_session(args) as session:
        server = session.server
        with contextlib.ExitStack() as stack:
            if args.cw is not None:  # on leaving: STOP, the sweep under way completes, idle
                stack.enter_context(sweeping(server, args.cw, args.ccw, timeout=args.timeout))
            show = stack.enter_context(_Live(stream) if is_terminal(stream) else _Lines(stream))
            pause = threading.Event()  # never set: waiting on it paces the refreshes
            started = time.monotonic()
            while True:
                elapsed = time.monotonic() - started
                show.update(server.status(), elapsed)
                if args.duration is not None and elapsed >= args.duration:
                    break
                left = None if args.duration is None else args.duration - elapsed
                pause.wait(args.interval if left is None else min(args.interval, left))
        with server.open() as conn:
            conn.wait_idle(timeout=args.timeout)  # raises the fault, if the server is in one
    return 0


# -- rendering -------------------------------------------------------------------------------------


def _deg(counts: int | None) -> str:
    """Counts as degrees, or "-" when the server could not say (not homed, board unreadable)."""
    if counts is None:
        return "-"
    return f"{counts_to_deg(float(counts)):+.2f}deg"


def status_line(status: Mapping[str, Any], elapsed: float) -> str:
    """One line per refresh: for logs and pipes."""
    counters = status.get("counters", {})
    irq = status.get("interrupts", {})
    parts = [
        f"{elapsed:6.1f} s",
        f"state={status.get('state')}",
        f"azimuth={_deg(status.get('azimuth_live'))}",
        f"destination={_deg(status.get('azimuth'))}",
        f"elevation={_deg(status.get('elevation_live'))}",
        f"continuous={'yes' if status.get('continuous') else 'no'}",
        *(f"{k}={v}" for k, v in counters.items()),
        *(f"irq.{k}={v}" for k, v in irq.items()),
        f"connections={len(status.get('connections', {}))}",
    ]
    return " ".join(parts)


def status_table(status: Mapping[str, Any], elapsed: float) -> Any:
    """The status as a rich table: one section per kind of figure."""
    from rich.table import Table

    table = Table(title=f"BIRIS server status ({elapsed:.1f} s)", show_header=False, expand=False)
    table.add_column(style="bold cyan", justify="right")
    table.add_column()
    state = str(status.get("state"))
    colour = "red" if state.startswith("fault") else "green"
    table.add_row("state", f"[{colour}]{state}[/]")
    for label, key in (
        ("azimuth", "azimuth_live"),
        ("destination", "azimuth"),
        ("elevation", "elevation_live"),
    ):
        counts = status.get(key)
        text = "-" if counts is None else f"{_deg(counts)} ({int(counts)} counts)"
        table.add_row(label, text)
    table.add_row("continuous", "yes" if status.get("continuous") else "no")
    table.add_section()
    for key, value in status.get("counters", {}).items():
        table.add_row(key.replace("_", " "), str(value))
    table.add_section()
    for key, value in status.get("interrupts", {}).items():
        table.add_row(key, str(value))
    table.add_section()
    for ident, conn in status.get("connections", {}).items():
        figures = ", ".join(  # plain figures only: nested tables would swamp the view
            f"{k} {v}" for k, v in conn.items() if k != "kind" and not isinstance(v, (dict, list))
        )
        table.add_row(f"connection {ident}", f"{conn.get('kind')}: {figures}")
    return table


class _Lines:
    def __init__(self, out: TextIO) -> None:
        self._out = out

    def __enter__(self) -> _Lines:
        return self

    def __exit__(self, *exc: object) -> None:
        return None

    def update(self, status: Mapping[str, Any], elapsed: float) -> None:
        print(status_line(status, elapsed), file=self._out, flush=True)


class _Live(_Lines):
    def __init__(self, out: TextIO) -> None:
        super().__init__(out)
        from rich.console import Console
        from rich.live import Live

        self._live = Live(console=Console(file=out), auto_refresh=False)

    def __enter__(self) -> _Live:
        self._live.__enter__()
        return self

    def __exit__(self, *exc: object) -> None:
        self._live.__exit__(None, None, None)

    def update(self, status: Mapping[str, Any], elapsed: float) -> None:
        self._live.update(status_table(status, elapsed), refresh=True)

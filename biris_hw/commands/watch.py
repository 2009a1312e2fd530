"""``biris watch``: the server's status, refreshed, for a while or until Ctrl-C.

What ``BirisServer.status()`` says (state, azimuth, counters, interrupts per logical line,
connections) is redrawn in place with rich when a person is watching, and printed as one line
per refresh otherwise, so the same command feeds a log. With ``--cw``/``--ccw`` the head sweeps
while it is watched (a server at rest has little to show); at the end the sweep under way is
allowed to finish.

A server in a fault (``state=fault:<kind>``) stays in it until it is reset, and nothing in a
``biris watch`` run resets it: watching on would print the same fault for ever. So the command
shows that last status, says what the fault is (the server's own message) and that it gives
up, and exits 1.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import threading
import time
from collections.abc import Mapping
from typing import Any, TextIO

from biris_hw.angles import counts_to_deg, destination_counts
from biris_hw.commands.argtypes import degrees, seconds
from biris_hw.commands.common import (
    Sensor,
    UsageError,
    add_continuous_argument,
    add_target_arguments,
    add_timeout_argument,
    add_yes_argument,
    confirm_moves,
    is_terminal,
    note_clamped,
    open_session,
)
from biris_hw.errors import BirisError, HardwareFault
from biris_hw.status import ServerState, ServerStatus
from biris_hw.sweeps import sweeping
from regs.wiener_crate import CrateReading

__all__ = ["add_arguments", "crate_summary", "run", "status_line", "status_table"]


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
    add_continuous_argument(parser)
    add_yes_argument(parser)
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
                limits = [
                    (f"--cw {args.cw:g}", destination_counts(args.cw, "--cw")),
                    (f"--ccw {args.ccw:g}", destination_counts(args.ccw, "--ccw")),
                ]
                confirm_moves(session, args, limits)
                sweeps = stack.enter_context(
                    sweeping(server, args.cw, args.ccw, timeout=args.timeout)
                )
                note_clamped(session.prog, "--cw", args.cw, sweeps.limits[0])
                note_clamped(session.prog, "--ccw", args.ccw, sweeps.limits[1])
            show = stack.enter_context(_Live(stream) if is_terminal(stream) else _Lines(stream))
            pause = threading.Event()  # never set: waiting on it paces the refreshes
            started = time.monotonic()
            while True:
                elapsed = time.monotonic() - started
                status = server.status()
                show.update(status, elapsed)
                if status.state is ServerState.FAULT:
                    raise _giving_up(server, status)
                if args.duration is not None and elapsed >= args.duration:
                    break
                left = None if args.duration is None else args.duration - elapsed
                pause.wait(args.interval if left is None else min(args.interval, left))
        with server.open() as conn:
            conn.wait_idle(timeout=args.timeout)  # raises the fault, if the server is in one
    return 0


def _giving_up(server: Sensor, status: ServerStatus) -> HardwareFault:
    """The fault the server is in, with its own message (a poll raises it), and why watching
    stops: nothing in this run will reset the server, so the status would never change."""
    kind = status.fault or "internal"
    message = "reported by the server's status"
    try:
        with server.open() as conn:
            conn.wait_idle(timeout=0)
    except HardwareFault as exc:
        kind, message = exc.kind, exc.message
    except (BirisError, TimeoutError):
        pass
    return HardwareFault(
        kind,
        f"{message}; the server stays in this fault until it is reset, so watch gives up "
        f"(check the sensor, then run the command again)",
    )


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
        f"acquisition={status.get('acquisition', '-')}",
        *(f"{k}={v}" for k, v in counters.items()),
        *(f"irq.{k}={v}" for k, v in irq.items()),
        f"connections={len(status.get('connections', {}))}",
    ]
    down = status.get("tasks_down") or ()
    if down:
        parts.append(f"tasks_down={','.join(down)}")
    crate = crate_summary(status)
    if crate is not None:
        parts.append(f"crate={crate.replace(' ', '_')}")
    return " ".join(parts)


def crate_summary(status: Mapping[str, Any]) -> str | None:
    """The VME crate in a few words (None without a crate monitor): ``ok``, its alarms, or
    ``unreachable`` when its last poll failed."""
    reading, error = status.get("crate"), status.get("crate_error")
    if error:
        return "unreachable"
    if not isinstance(reading, CrateReading):
        return None
    alarms = reading.alarms()
    return "; ".join(alarms) if alarms else "ok"


def _crate_rows(status: Mapping[str, Any]) -> list[tuple[str, str]]:
    """The crate's section of the table: its state, fitted channels, fans, temperatures."""
    summary = crate_summary(status)
    if summary is None:
        return []
    colour = "green" if summary == "ok" else "red"
    rows = [("VME crate", f"[{colour}]{summary}[/]")]
    error = status.get("crate_error")
    if error:
        rows.append(("crate error", str(error)))
    reading = status.get("crate")
    if isinstance(reading, CrateReading):
        supplies = ", ".join(f"{volts:+.2f} V {amps:.2f} A" for _, volts, amps in reading.fitted())
        rows.append(("crate supplies", supplies or "-"))
        rows.append(("crate fans", " ".join(f"{rps * 60}" for rps in reading.fans_rps) + " rpm"))
        rows.append(("crate temperatures", " ".join(f"{c}" for c in reading.temperatures_c) + " C"))
    return rows


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
    table.add_row("acquisition", str(status.get("acquisition", "-")))
    down = status.get("tasks_down") or ()
    if down:  # a failed task waits for a reset: the fault says what, this says where
        table.add_row("tasks down", f"[red]{', '.join(down)}[/] (until reset)")
    crate = _crate_rows(status)
    if crate:
        table.add_section()
        for label, text in crate:
            table.add_row(label, text)
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

"""``biris watch``: the server's status, refreshed, for a while or until Ctrl-C.

What ``BirisServer.status()`` says (state, azimuth, counters, interrupts per logical line,
connections) is redrawn in place with rich when a person is watching, and printed as one line
per refresh otherwise, so the same command feeds a log. With ``--cw``/``--ccw`` the head sweeps
while it is watched (a server at rest has little to show); at the end the sweep under way is
allowed to finish.

A server in a fault (``state=fault:<kind>``) keeps running and answering ``status()``, and
stays in the fault until it is reset: ``watch`` goes on showing its status, with the fault,
says once on stderr what the fault is (the server's own message) and how to recover, and shows
the server live again once someone has reset it (a sweep asked for with ``--cw``/``--ccw`` is
abandoned at the fault and started again once the server is idle after the reset). The run ends
at ``--duration`` or Ctrl-C as always; its exit status says whether the server was still in a
fault then (:class:`~biris_hw.commands.faults.FaultNotice`): 0 if not, 1 if so, 130 after
Ctrl-C.

A service watched with ``--connect`` that cannot be reached (a partition, a router or the service
restarting: :class:`~biris_hw.errors.ConnectionLost`) is waited for, up to :data:`RIDE_OUT_S`:
``watch`` says on stderr when the link is lost and when it is back (and for how long it was
away), and goes on; a sweep asked for goes on in the service meanwhile and is stopped as usual
at the end. A link still lost after :data:`RIDE_OUT_S`, or when the run ends, is exit status 1,
with the span during which no status could be read.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any, TextIO

from biris_hw.angles import counts_to_deg, destination_counts
from biris_hw.commands.argtypes import degrees, seconds
from biris_hw.commands.console import is_terminal, note_clamped
from biris_hw.commands.failures import EXIT_FAULT, UsageError
from biris_hw.commands.faults import FaultNotice
from biris_hw.commands.options import (
    add_continuous_argument,
    add_target_arguments,
    add_timeout_argument,
    add_yes_argument,
)
from biris_hw.commands.session import confirm_moves, open_session, quiet_collector
from biris_hw.errors import RIDE_OUT_S, ConnectionLost, HardwareFault
from biris_hw.status import ServerState, ServerStatus
from regs.wiener_crate import CrateReading

if TYPE_CHECKING:
    from biris_hw.sensor import Sensor

__all__ = ["RIDE_OUT_S", "add_arguments", "crate_summary", "run", "status_line", "status_table"]


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


def run(
    args: argparse.Namespace, out: TextIO | None = None, stop: threading.Event | None = None
) -> int:
    """Watch until ``--duration`` is over (or ``stop``, if given, is set: an embedding program,
    the tests) or Ctrl-C; 0, or 1 if the server was in a fault at the end."""
    stream = out or sys.stdout
    if (args.cw is None) != (args.ccw is None):
        raise UsageError("sweeping while watching needs both --cw and --ccw")
    with open_session(args) as session:
        quiet_collector()
        server = session.server
        if args.cw is not None:
            limits = [
                (f"--cw {args.cw:g}", destination_counts(args.cw, "--cw")),
                (f"--ccw {args.ccw:g}", destination_counts(args.ccw, "--ccw")),
            ]
            confirm_moves(session, args, limits)
        with _Live(stream) if is_terminal(stream) else _Lines(stream) as show:
            watcher = _Watcher(session.prog, server, args, show, stop or threading.Event())
            try:
                watcher.run()
            except _LinkGone as gone:
                print(f"{session.prog}: {gone}", file=sys.stderr, flush=True)
                return EXIT_FAULT
        if watcher.link.since is not None:
            print(f"{session.prog}: {watcher.link.unfinished()}", file=sys.stderr, flush=True)
            return EXIT_FAULT
        if watcher.notice.faulted:
            return watcher.notice.exit_status()
        try:
            with server.open() as conn:
                conn.wait_idle(timeout=args.timeout)  # raises a fault that came since the last look
        except ConnectionLost:
            watcher.link.begin()
            print(f"{session.prog}: {watcher.link.unfinished()}", file=sys.stderr, flush=True)
            return EXIT_FAULT
    return 0


class _LinkGone(Exception):
    """The service stayed out of reach longer than :data:`RIDE_OUT_S`; says the span."""


class _Link:
    """Whether the watched sensor can be reached; says on stderr when it is lost and back.

    Only a :class:`~biris_hw.errors.ConnectionLost` (a remote sensor's) makes it lost; a
    local server never raises one. An outage is counted from the last status read, so the
    span it names is the one without a status, and the bound applies to that span.
    """

    def __init__(self, prog: str, bound: float) -> None:
        self._prog = prog
        self._bound = bound
        self.since: float | None = None
        """time.monotonic() of the last status read before the outage under way, else None."""
        self._since_wall = 0.0
        self._last = time.monotonic()
        self._last_wall = time.time()
        self.outages = 0

    def ok(self) -> None:
        """A status was read: an outage under way ends (said, with its span)."""
        now, now_wall = time.monotonic(), time.time()
        if self.since is not None:
            self._say(
                f"the link to the service is back after {now - self.since:.1f} s (no status "
                f"from {_clock(self._since_wall)} to {_clock(now_wall)})"
            )
            self.since = None
        self._last, self._last_wall = now, now_wall

    def lost(self, exc: ConnectionLost) -> None:
        """A look failed with ``exc``: the first says so; past the bound, :class:`_LinkGone`."""
        now = time.monotonic()
        if self.begin():
            self._say(
                f"the link to the service is lost ({exc}); waiting up to {self._bound:g} s "
                "for it to come back"
            )
        since = self._last if self.since is None else self.since
        if now - since >= self._bound:
            raise _LinkGone(
                f"the service could not be reached for {now - since:.1f} s: no status "
                f"from {_clock(self._since_wall)} to {_clock(time.time())}; giving up ({exc})"
            )

    def begin(self) -> bool:
        """An outage begins (at the last status read), unless one is under way; True if new."""
        if self.since is not None:
            return False
        self.since, self._since_wall = self._last, self._last_wall
        self.outages += 1
        return True

    def unfinished(self) -> str:
        """What to say when the run ends while the service is lost."""
        away = 0.0 if self.since is None else time.monotonic() - self.since
        return (
            f"the run ended with the service out of reach for {away:.1f} s: no status from "
            f"{_clock(self._since_wall)} to {_clock(time.time())}"
        )

    def _say(self, text: str) -> None:
        print(f"{self._prog}: {text}", file=sys.stderr, flush=True)


def _clock(t: float) -> str:
    """Wall-clock time of day, to the second: what a person compares with a log."""
    return time.strftime("%H:%M:%S", time.localtime(t))


class _Abandon(Exception):
    """Raised inside a :func:`sweeping` block to leave it without waiting for the sweep: the
    server is in a fault, so the sweep has ended already and nothing would come."""


class _Watcher:
    """The refresh loop: a look at the status every ``--interval``, sweeping meanwhile if asked.

    A sweep runs in a :func:`sweeping` block that the fault ends (abandoned: stop asked, nothing
    waited for); while the server is in the fault the status is shown without a sweep, and
    once it is idle again after a reset a new block sweeps between the same limits.
    """

    def __init__(
        self,
        prog: str,
        server: Sensor,
        args: argparse.Namespace,
        show: _Lines,
        stop: threading.Event,
    ) -> None:
        self._prog = prog
        self._server = server
        self._args = args
        self._show = show
        self._stop = stop  # waited on between looks: it paces the refreshes, and ends them
        self._started = time.monotonic()
        self._status: ServerStatus | None = None
        self._sweeps = 0
        self.notice = FaultNotice(server, args, "watch goes on showing the status")
        self.link = _Link(prog, RIDE_OUT_S)

    def run(self) -> None:
        sweep = self._args.cw is not None
        while not self._over():
            if sweep and not self.notice.faulted and (self._sweeps == 0 or self._idle()):
                self._sweep()
            else:
                self._watch_until(lambda: sweep and self._idle(), look_first=self._sweeps == 0)

    def _sweep(self) -> None:
        from biris_hw.io.sweeps import sweeping

        args = self._args
        first = self._sweeps == 0
        self._sweeps += 1
        try:
            with sweeping(self._server, args.cw, args.ccw, timeout=args.timeout) as sweeps:
                if first:
                    note_clamped(self._prog, "--cw", args.cw, sweeps.limits[0])
                    note_clamped(self._prog, "--ccw", args.ccw, sweeps.limits[1])
                else:
                    print(f"{self._prog}: sweeping again", file=sys.stderr, flush=True)
                self._watch_until(lambda: self.notice.faulted, look_first=first)
                if self.notice.faulted:
                    raise _Abandon
        except _Abandon:
            pass
        except ConnectionLost as exc:  # met starting or stopping the sweep: waited for, as a
            self.link.lost(exc)  # look's; the next sweep starts once the service is idle again
            self._status = None
            self._wait()
        except HardwareFault:  # met starting the sweep or waiting for its end: the status
            self._look()  # shows it (and the notice says it), like a fault seen by a look
            if not self.notice.faulted:  # reset meanwhile: the next sweep waits its turn
                self._wait()

    def _watch_until(self, done: Callable[[], bool], look_first: bool = True) -> None:
        """Look at the status, and wait between looks, until ``done()`` or the run is over
        (with a last look then: the status as the run ends is shown, and decides the exit
        status)."""
        if not look_first:
            self._wait()
        while True:
            self._look()
            if done() or self._over():
                return
            self._wait()

    def _look(self) -> None:
        try:
            status = self._server.status()
        except ConnectionLost as exc:  # a remote service out of reach: waited for (bounded)
            self.link.lost(exc)
            return
        self.link.ok()
        self._show.update(status, time.monotonic() - self._started)
        self.notice.observe(status)
        self._status = status

    def _idle(self) -> bool:
        return self._status is not None and self._status.state is ServerState.IDLE

    def _over(self) -> bool:
        if self._stop.is_set():
            return True
        duration = self._args.duration
        return duration is not None and time.monotonic() - self._started >= duration

    def _wait(self) -> None:
        wait = self._args.interval
        if self._args.duration is not None:
            left = self._args.duration - (time.monotonic() - self._started)
            wait = min(wait, max(0.0, left))
        self._stop.wait(wait)


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

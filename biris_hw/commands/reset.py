"""Resetting a sensor after a fault: ``biris reset --connect NAME``, and a service's own resets.

A fault (parity, bus, timeout, a stalled motor...) leaves the server in that fault until it is
reset: its initialisation run again (DESIGN.md, report section 5). On a robot the sensor runs as
a service (``biris serve``), so the reset is asked for over the network:

* ``biris reset --connect NAME`` is a controller's request (it needs a controller's
  credentials, as motion does): exit 0 once the sensor is back, 1 with the fault's line when
  the reset failed (the sensor is still in a fault), 2 for what the caller must fix (no
  credentials, a wrong password, a replay that cannot be reset).
* ``biris serve --auto-reset N`` resets the sensor itself after a fault (:class:`AutoReset`):
  at most N tries, after a pause that doubles from one to the next (``--reset-delay``); the
  service exits with status 1 when the sensor is still in a fault after the last one, so that
  its supervisor (systemd's ``Restart=on-failure``) starts it again: a lost link that a reset
  cannot bring back needs a new process. Without ``--auto-reset`` a faulted service stays up in
  its fault, as before, and waits for a controller's reset. Either way :class:`AutoReset`
  watches the sensor's state and says, in the service's log, when the sensor enters a fault
  (kind and words), when it is being reset, and when it is back.

Only the flags' modules are imported here: ``biris reset --help`` loads no server and no network.
"""

from __future__ import annotations

import argparse
import logging
import sys
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, TextIO

from biris_hw.commands.argtypes import seconds
from biris_hw.commands.failures import UsageError
from biris_hw.commands.options import (
    PASSWORD_ENV,
    add_debug_argument,
    add_quiet_argument,
    add_service_client_arguments,
    add_timeout_argument,
    client_profile,
    connect_options,
)
from biris_hw.errors import BirisError, ConnectionClosed, HardwareFault, RequestError

if TYPE_CHECKING:
    from biris_hw.sensor import Connection, Sensor
    from biris_hw.status import ServerStatus

__all__ = [
    "MAX_RESET_DELAY_S",
    "RESET_DELAY_S",
    "STABLE_S",
    "AutoReset",
    "add_arguments",
    "add_auto_reset_arguments",
    "check_auto_reset",
    "run",
]

log = logging.getLogger(__name__)

RESET_DELAY_S = 1.0
"""``--reset-delay``'s default: real seconds between a fault and the first reset; the pause
doubles before each further try (a link that is coming back gets the time to)."""

MAX_RESET_DELAY_S = 60.0
"""The longest pause between two tries, however many."""

STABLE_S = 60.0
"""Real seconds a sensor must run without a fault after a reset brought it back before a new
fault gets a fresh set of tries: a fault that comes back at once after every successful reset
(a stalled shaft met at the first move) uses up the tries as one that no reset cures does."""

WATCH_S = 60.0
"""The longest a watcher waits for a status change before it asks again (real seconds)."""


# -- biris reset -----------------------------------------------------------------------------------


def add_arguments(parser: argparse.ArgumentParser) -> None:
    where = parser.add_argument_group("sensor")
    where.add_argument(
        "--connect",
        metavar="NAME",
        help="the service (`biris serve --name NAME`) whose sensor to reset (default: "
        "$BIRIS_CONNECT, or the profile's)",
    )
    add_service_client_arguments(parser)
    add_timeout_argument(parser)
    add_quiet_argument(parser)
    add_debug_argument(parser)


def run(args: argparse.Namespace, out: TextIO | None = None) -> int:
    """Reset the sensor of service ``--connect``; 0 once it is back (its state said on stdout).

    Raises:
        UsageError: no controller's credentials given (nothing is sent).
        HardwareFault: the reset failed: the sensor is (still, or again) in a fault.
        AccessDenied: the credentials are not a controller's.
        TimeoutError: another client's reset was under way and did not end within --timeout.
    """
    from biris_hw.commands.session import check_reachable
    from biris_hw.opening import open_sensor

    stream = out or sys.stdout
    if args.connect is None:
        args.connect = client_profile(args).connect
        if args.connect is None:
            raise UsageError("say which service: --connect NAME (or set BIRIS_CONNECT)")
    options = connect_options(args)
    check_reachable(args.connect, options)  # a refused link or a wrong name said at once
    if options["user"] is None:
        raise UsageError(
            f"a reset is a controller's request: give --user USER (the password in "
            f"${PASSWORD_ENV}) or --credentials FILE"
        )
    with open_sensor(connect=args.connect, **options) as remote:
        before = str(remote.status()["state"])
        with remote.open() as conn:
            try:
                conn.reset()
            except RequestError:
                # an initialisation under way already (another controller's reset): its end
                # is the answer; anything else is the service's refusal, said as it is
                if not str(remote.status()["state"]).startswith("initialising"):
                    raise
                _wait_for_the_end(remote, args.timeout)
            status = remote.status()
    state = str(status["state"])
    if state.startswith("fault") or state == "initialising":
        raise HardwareFault(status.fault or "internal", f"the sensor is {state} after the reset")
    print(f"{args.connect}: {state} after the reset (it was {before})", file=stream, flush=True)
    return 0


def _wait_for_the_end(remote: Sensor, timeout: float) -> None:
    """Wait, up to ``timeout`` real seconds, until the sensor has left ``initialising``."""
    end = time.monotonic() + timeout
    status = remote.status()
    while str(status["state"]) == "initialising":
        left = end - time.monotonic()
        if left <= 0:
            raise TimeoutError(f"the reset under way did not end within {timeout:g} s")
        try:
            status = remote.status(newer_than=status.change, timeout=min(left, 1.0))
        except TimeoutError:
            status = remote.status()


# -- a service's own resets ------------------------------------------------------------------------


def _faulted(status: ServerStatus) -> bool:
    return str(status["state"]).startswith("fault")


class AutoReset:
    """Watches a sensor's state from a thread of its own, says its faults, resets and recoveries
    in the log, and with ``tries`` resets it after a fault.

    On a fault: wait ``delay_s`` (doubled before each further try, at most
    :data:`MAX_RESET_DELAY_S`), reset, and look: back (any state but a fault) ends the episode;
    still in a fault, the next try. Another client's reset meanwhile is taken as it comes
    (nothing is reset twice). After ``tries`` failed resets the watcher gives up:
    :attr:`gave_up` holds the fault and ``on_give_up`` is called with it (``biris serve`` then
    ends, with status 1). A new fault within :data:`STABLE_S` of a recovery continues the
    episode, so a fault that every reset only hides for a moment uses up the tries too.
    ``tries`` 0: the watcher only says what happens (a controller resets).

    The watcher waits on the sensor's status pushes (``status(newer_than=...)``): it asks
    nothing while nothing changes. :meth:`stop` ends it; :meth:`join` waits for its thread,
    which a reset under way holds until the reset ends or the sensor closes.
    """

    def __init__(
        self,
        sensor: Sensor,
        *,
        tries: int = 0,
        delay_s: float = RESET_DELAY_S,
        stable_s: float = STABLE_S,
        on_give_up: Callable[[HardwareFault], None] | None = None,
        name: str = "the sensor",
    ) -> None:
        if tries < 0:
            raise ValueError(f"tries must be 0 or more, not {tries}")
        if not delay_s >= 0:
            raise ValueError(f"delay_s must be 0 or more, not {delay_s}")
        self.sensor = sensor
        self.tries = tries
        self.delay_s = delay_s
        self.stable_s = stable_s
        self.name = name
        self._on_give_up = on_give_up
        self.faults = 0
        """Faults the sensor entered while watched."""
        self.resets = 0
        """Resets this watcher made."""
        self.recoveries = 0
        """Faults a reset of this watcher's ended."""
        self.gave_up: HardwareFault | None = None
        """The fault the sensor was still in after the last try (then nothing more is tried)."""
        self._used = 0
        """Tries used in the episode under way."""
        self._back_at: float | None = None
        """When a reset of ours last brought the sensor back (monotonic seconds)."""
        self._state: str | None = None
        """The state last said in the log."""
        self._stop = threading.Event()
        self._conn: Connection[Any] | None = None
        self._thread: threading.Thread | None = None

    def start(self) -> AutoReset:
        """Open the watcher's connection (ConnectionClosed: the sensor is closed) and start."""
        self._conn = self.sensor.open()
        self._thread = threading.Thread(target=self._run, name="biris-auto-reset", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """End the watch (a wait for a change ends at once; a reset under way is not cut)."""
        self._stop.set()
        conn = self._conn
        if conn is not None:
            try:
                conn.close()
            except BirisError as exc:
                log.debug("auto-reset connection not closed: %s", exc)

    def join(self, timeout: float | None = None) -> None:
        """Wait for the watcher's thread to end (after :meth:`stop`, or the sensor closing)."""
        if self._thread is not None:
            self._thread.join(timeout)

    def __enter__(self) -> AutoReset:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
        self.join()

    # -- the watcher's thread ------------------------------------------------------------------
    def _run(self) -> None:
        conn = self._conn
        assert conn is not None
        try:
            status = conn.status()
            self._observe(status)
            while not self._stop.is_set():
                if _faulted(status) and self.tries and self.gave_up is None:
                    status = self._recover(conn, status)
                    continue
                try:
                    status = conn.status(newer_than=status.change, timeout=WATCH_S)
                except TimeoutError:
                    continue
                self._observe(status)
        except ConnectionClosed:
            return  # stopped, or the sensor closed
        except BirisError as exc:  # the sensor cannot say any more (a lost link): said once
            log.warning("%s's state is no longer watched: %s", self.name, exc)
        except Exception:  # a bug here must not pass unseen, nor take the service down
            log.exception("watching %s's state failed", self.name)

    def _observe(self, status: ServerStatus) -> None:
        """Say a change of state worth a line: a fault entered, a reset begun, back again."""
        state = str(status["state"])
        before, self._state = self._state, state
        if state == before:
            return
        if state.startswith("fault"):
            fault = self._fault(status)
            if self.tries and self.gave_up is None:
                what = f"resetting it (at most {self.tries} tries)"
            else:
                what = "waiting for a controller's reset (biris reset --connect)"
            log.error("%s is in a fault (%s): %s; %s", self.name, fault.kind, fault.message, what)
            self.faults += 1  # once said
        elif state == "initialising":
            if before is not None:
                log.warning("%s is being reset (its initialisation runs again)", self.name)
        elif before is not None and (before.startswith("fault") or before == "initialising"):
            log.info("%s is back (%s)", self.name, state)

    def _fault(self, status: ServerStatus) -> HardwareFault:
        """The fault the sensor is in, in its own words: a poll on a connection of our own
        raises it (the watcher's has heard it already); one of the status's kind otherwise."""
        kind = status.fault or str(status["state"]).partition(":")[2] or "internal"
        try:
            with self.sensor.open() as probe:
                probe.wait_idle(timeout=0)
        except HardwareFault as exc:
            return exc
        except (BirisError, TimeoutError):
            pass
        return HardwareFault(kind, "the server is in a fault")  # type: ignore[arg-type]

    def _recover(self, conn: Connection[Any], status: ServerStatus) -> ServerStatus:
        """Reset until the sensor is back or the tries are used up; the status after."""
        if self._back_at is not None and time.monotonic() - self._back_at >= self.stable_s:
            self._used = 0  # a new episode
        while self._used < self.tries:
            pause = min(MAX_RESET_DELAY_S, self.delay_s * 2**self._used)
            if self._stop.wait(pause):
                return status
            status = conn.status()
            if not _faulted(status):  # another client's reset has brought it back
                self._observe(status)
                return status
            self._used += 1
            self.resets += 1
            log.warning("resetting %s (try %d of %d)", self.name, self._used, self.tries)
            try:
                conn.reset()
            except HardwareFault as exc:
                self._state = f"fault:{exc.kind}"
                log.error(
                    "reset %d of %d failed (%s): %s", self._used, self.tries, exc.kind, exc.message
                )
                continue
            except RequestError as exc:  # an initialisation under way (a controller's reset)
                self._used -= 1
                log.info("%s: not reset: %s", self.name, exc)
                status = self._settled(conn)
                if not _faulted(status):
                    self._observe(status)
                    return status
                continue
            status = conn.status()
            if not _faulted(status):
                self.recoveries += 1
                self._back_at = time.monotonic()
                self._state = str(status["state"])
                log.info("%s is back (%s) after %d reset(s)", self.name, self._state, self._used)
                return status
        fault = self._fault(status)
        self.gave_up = HardwareFault(
            fault.kind, f"{fault.message} (still so after {self._used} reset(s): gave up)"
        )
        log.error(
            "%s is still in a fault (%s) after %d reset(s): giving up",
            self.name,
            fault.kind,
            self._used,
        )
        if self._on_give_up is not None:
            self._on_give_up(self.gave_up)
        return status

    def _settled(self, conn: Connection[Any]) -> ServerStatus:
        """The status once the initialisation under way has ended (or the watch stopped)."""
        status = conn.status()
        while str(status["state"]) == "initialising" and not self._stop.is_set():
            try:
                status = conn.status(newer_than=status.change, timeout=WATCH_S)
            except TimeoutError:
                status = conn.status()
        return status


def add_auto_reset_arguments(parser: argparse.ArgumentParser) -> None:
    """``biris serve``'s ``--auto-reset N`` and ``--reset-delay S``."""
    group = parser.add_argument_group("recovery")
    group.add_argument(
        "--auto-reset",
        type=_tries,
        default=0,
        metavar="N",
        help="after a fault, reset the sensor at most N times (default 0: wait for a "
        "controller's `biris reset`); still in a fault after the last, the service exits with "
        "status 1 so that its supervisor restarts it",
    )
    group.add_argument(
        "--reset-delay",
        type=seconds,
        default=RESET_DELAY_S,
        metavar="S",
        help=f"with --auto-reset: S real seconds before the first reset, doubled before each "
        f"further one, at most {MAX_RESET_DELAY_S:g} (default {RESET_DELAY_S:g})",
    )


def _tries(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be 0 or more, not {value}")
    return value


def check_auto_reset(args: argparse.Namespace, playback: bool) -> None:
    """--auto-reset goes with a sensor, not a recording (which cannot be reset)."""
    if playback and int(getattr(args, "auto_reset", 0)) > 0:
        raise UsageError("--auto-reset goes with a sensor: a recording cannot be reset")

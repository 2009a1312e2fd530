"""A simulated Wiener VME crate on a CAN bus: what :mod:`biris_hw.crate` reads, and a fault panel.

:class:`SimulatedCrate` opens a python-can bus of its own (``virtual`` by default, any interface
python-can has) and answers, from a thread, every remote frame of its crate id for a read
function with the 8-byte frame :mod:`regs.wiener_crate` lays out, built from its state at that
moment. It starts as a healthy crate (:data:`DEFAULT_VOLTAGES_V`...): on, +5 V, +12 V, +3.3 V
and -12 V fitted, six fans at :data:`DEFAULT_FAN_RPS`, temperatures round 30 C.

What is modelled:

* A crate that is off reports the power bit clear, no voltage, no current and its fans
  stopped (they run from the supply); its other flags are unchanged.
* Commands (function 1): on, off, SYSRESET (counted: :attr:`SimulatedCrate.sysresets`), the
  nominal fan speed (every fan that has not failed runs at it). Every well-formed command is
  appended to :attr:`SimulatedCrate.commands`; while byte 1 says CAN access is read-only, it is
  recorded and audited but not obeyed.
* Trip-off: with ``trip_on_fan_failure`` a failed fan switches the crate off, with
  ``trip_on_error`` an over-current or over-temperature does.
* The fault panel: :meth:`~SimulatedCrate.fail_fan`, :meth:`~SimulatedCrate.overheat`,
  :meth:`~SimulatedCrate.over_current`, :meth:`~SimulatedCrate.power_off` /
  :meth:`~SimulatedCrate.power_on`, :meth:`~SimulatedCrate.go_silent` /
  :meth:`~SimulatedCrate.answer_again` (a crate unplugged from its CAN bus: it neither answers
  nor hears), :meth:`~SimulatedCrate.clear_all`. The other flags are plain attributes.

Not modelled: the crate's own timing (it answers at once), bit 0 of status byte 1, the
EEPROM, and what a SYSRESET does to the boards in the crate.

The crate's audit (:attr:`SimulatedCrate.violations`, :class:`CrateRule`) records a host that
misuses the protocol: a remote frame for a function nobody reads, a remote frame whose dlc is
not 8 (answered all the same: **our reading**, the crate goes by the id), a data frame sent to
a read function, a malformed command, and a command while access is read-only.
"""

from __future__ import annotations

import enum
import logging
import threading
import time
from types import TracebackType

import can

from regs.wiener_crate import (
    CHANNELS,
    FAN_SPEED_MAX_RPS,
    FANS,
    FRAME_DLC,
    PAIR_FUNCTIONS,
    READ_FUNCTIONS,
    Command,
    Function,
    Status1,
    check_crate_id,
    encode_channels,
    encode_fans,
    encode_status,
    encode_temperatures,
    function_name,
    split_id,
)
from sim.audit import Audit, Violation

__all__ = [
    "DEFAULT_CURRENTS_A",
    "DEFAULT_FAN_RPS",
    "DEFAULT_TEMPERATURES_C",
    "DEFAULT_VOLTAGES_V",
    "RECV_CYCLE_S",
    "CrateRule",
    "SimulatedCrate",
]

log = logging.getLogger(__name__)

RECV_CYCLE_S = 0.02
"""How long the crate's thread blocks in one receive: how long :meth:`SimulatedCrate.close`
waits for it at most."""

DEFAULT_VOLTAGES_V = (5.0, 12.0, 0.0, 3.3, 0.0, -12.0, 0.0, 0.0)
"""Channels 0-7 of a typical VME supply: +5 V, +12 V, +3.3 V (channel 3), -12 V (channel 5);
the others are not fitted."""
DEFAULT_CURRENTS_A = (20.0, 2.5, 0.0, 6.0, 0.0, 0.8, 0.0, 0.0)
"""A crate with a few boards in it (BIRIS's among them)."""
DEFAULT_FAN_RPS = 50
"""Nominal and actual fan speed (3000 rpm)."""
DEFAULT_TEMPERATURES_C = (30, 31, 29, 32, 30, 31, 28, 30)

_COMMANDS = frozenset(int(command) for command in Command)


class CrateRule(str, enum.Enum):
    """The simulated crate's audit rules; the value is the name used in reports."""

    UNKNOWN_FUNCTION = "UNKNOWN_FUNCTION"
    """A remote frame for a function that is not read (1, or 8-15), or a data frame to 8-15."""
    BAD_REMOTE_DLC = "BAD_REMOTE_DLC"
    """A read request whose dlc is not 8."""
    DATA_TO_READ_FUNCTION = "DATA_TO_READ_FUNCTION"
    """A data frame sent with a read function's id: the crate's answers are the only ones."""
    BAD_COMMAND = "BAD_COMMAND"
    """A command frame that is empty, of an unknown command, or a fan speed beyond 0..64."""
    COMMAND_WHILE_READ_ONLY = "COMMAND_WHILE_READ_ONLY"
    """A command while status byte 1 says CAN access is read-only (ignored by the crate)."""


class SimulatedCrate:
    """Crate ``crate_id`` on python-can ``channel`` of ``interface``, answering from now on.

    State (plain attributes, read when a request comes): ``on``, ``inhibit``, ``supply_ok``,
    ``power_supply_error``, ``sysfail``, ``trip_on_fan_failure``, ``trip_on_error``,
    ``status1`` (byte 1), the channel masks of status bytes 2-7 (``under_voltage``,
    ``over_voltage``, ``external_temperature``, ``over_current_mask``,
    ``over_voltage_protection``, ``supply_temperature``: ``over_current`` is the fault panel's
    method), ``voltages_v`` and ``currents_a`` (what each channel delivers while on),
    ``fan_nominal_rps``, ``temperatures_c``. Fans turn at the nominal speed unless failed
    (:meth:`fail_fan`). A value no frame can carry (a temperature beyond 255 C) is logged
    and that request goes unanswered.
    """

    def __init__(self, channel: str, crate_id: int = 1, *, interface: str = "virtual") -> None:
        self.crate_id = check_crate_id(crate_id)
        self.channel = channel
        self._lock = threading.Lock()
        self._audit = Audit(time.monotonic)
        self.commands: list[tuple[Command, int | None]] = []
        """Every well-formed command received, oldest first: the command and, for the fan
        speed, its argument (read-only or not: the host sent it)."""
        self.sysresets = 0
        """SYSRESET commands obeyed."""
        self.requests = 0
        """Read requests answered."""
        self.frames_seen = 0
        """Frames the crate's thread has taken off the bus and dealt with, whatever they were
        (a test's way to know a frame it sent has been heard, or dropped)."""
        self._reset_state()
        self._bus = can.Bus(interface=interface, channel=channel)
        self._closed = False
        self._stop = threading.Event()
        self._thread = threading.Thread(
            target=self._run, name=f"wiener-crate-{self.crate_id}", daemon=True
        )
        self._thread.start()

    def _reset_state(self) -> None:
        self.on = True
        self.inhibit = False
        self.supply_ok = True
        self.power_supply_error = False
        self.sysfail = False
        self.trip_on_fan_failure = False
        self.trip_on_error = False
        self.status1 = Status1(0)
        self.under_voltage = 0
        self.over_voltage = 0
        self.external_temperature = 0
        self.over_current_mask = 0
        self.over_voltage_protection = 0
        self.supply_temperature = 0
        self.voltages_v = list(DEFAULT_VOLTAGES_V)
        self.currents_a = list(DEFAULT_CURRENTS_A)
        self.fan_nominal_rps = DEFAULT_FAN_RPS
        self.temperatures_c = list(DEFAULT_TEMPERATURES_C)
        self._failed_fans: set[int] = set()
        self._silent = False

    # -- fault panel ------------------------------------------------------------------------------
    def fail_fan(self, index: int) -> None:
        """Fan ``index`` (0-5: fans 1-6) stops; the fans-OK bit clears (and the crate trips off
        if ``trip_on_fan_failure``)."""
        if index not in range(FANS):
            raise ValueError(f"fan index {index!r} is not 0..{FANS - 1}")
        with self._lock:
            self._failed_fans.add(index)
            if self.trip_on_fan_failure:
                self.on = False

    def overheat(self, channel: int) -> None:
        """The supply of ``channel`` (0-7) reports over-temperature (status byte 7)."""
        bit = _channel_bit(channel)
        with self._lock:
            self.supply_temperature |= bit
            self._trip_on_error()

    def over_current(self, channel: int) -> None:
        """``channel`` (0-7) reports over-current (status byte 5)."""
        bit = _channel_bit(channel)
        with self._lock:
            self.over_current_mask |= bit
            self._trip_on_error()

    def power_off(self) -> None:
        """The crate is switched off (at its front panel, or by a trip)."""
        with self._lock:
            self.on = False

    def power_on(self) -> None:
        with self._lock:
            self.on = True

    def go_silent(self) -> None:
        """Unplugged from CAN: no answer, nothing heard (no command, no audit)."""
        with self._lock:
            self._silent = True

    def answer_again(self) -> None:
        with self._lock:
            self._silent = False

    def clear_all(self) -> None:
        """Back to the healthy crate it started as (on, answering, nothing failed, default
        values). The commands, counters and audit are kept."""
        with self._lock:
            self._reset_state()

    def _trip_on_error(self) -> None:
        if self.trip_on_error:
            self.on = False

    @property
    def read_only(self) -> bool:
        """Status byte 1 says CAN access is read-only: commands are ignored."""
        return Status1.READ_ONLY in self.status1

    @property
    def fans_rps(self) -> tuple[int, ...]:
        """What each fan turns at now (0 for a failed fan, and all of them while off)."""
        with self._lock:
            return self._fans()

    def _fans(self) -> tuple[int, ...]:
        if not self.on:
            return (0,) * FANS
        return tuple(0 if n in self._failed_fans else self.fan_nominal_rps for n in range(FANS))

    # -- the crate's answers ----------------------------------------------------------------------
    def _payload(self, function: Function) -> bytes:
        """The answer to ``function`` from the state now (holding the lock)."""
        if function is Function.STATUS:
            return encode_status(
                power_on=self.on,
                inhibit=self.inhibit,
                supply_ok=self.supply_ok,
                power_supply_error=self.power_supply_error,
                fans_ok=not self._failed_fans,
                trip_on_fan_failure=self.trip_on_fan_failure,
                trip_on_error=self.trip_on_error,
                sysfail=self.sysfail,
                status1=int(self.status1),
                under_voltage=self.under_voltage,
                over_voltage=self.over_voltage,
                external_temperature=self.external_temperature,
                over_current=self.over_current_mask,
                over_voltage_protection=self.over_voltage_protection,
                supply_temperature=self.supply_temperature,
            )
        if function in PAIR_FUNCTIONS:
            n = PAIR_FUNCTIONS.index(function)
            live = 1.0 if self.on else 0.0
            return encode_channels(
                n,
                live * self.voltages_v[n],
                live * self.currents_a[n],
                live * self.voltages_v[n + 4],
                live * self.currents_a[n + 4],
            )
        if function is Function.FANS:
            fans = self._fans()
            return encode_fans(round(sum(fans) / FANS), self.fan_nominal_rps, fans)
        return encode_temperatures(self.temperatures_c)

    def _command(self, data: bytes) -> None:
        """A command frame (holding the lock)."""
        if not data or data[0] not in _COMMANDS:
            self._violation(CrateRule.BAD_COMMAND, f"command frame {data.hex() or '(empty)'}")
            return
        command = Command(data[0])
        argument: int | None = None
        if command is Command.FAN_SPEED:
            if len(data) < 2 or data[1] > FAN_SPEED_MAX_RPS:
                self._violation(
                    CrateRule.BAD_COMMAND,
                    f"fan speed frame {data.hex()}: no speed 0..{FAN_SPEED_MAX_RPS}",
                )
                return
            argument = data[1]
        self.commands.append((command, argument))
        if self.read_only:
            self._violation(CrateRule.COMMAND_WHILE_READ_ONLY, f"{command.name} ignored")
            return
        if command is Command.ON:
            self.on = True
        elif command is Command.OFF:
            self.on = False
        elif command is Command.SYSRESET:
            self.sysresets += 1
        else:
            assert argument is not None
            self.fan_nominal_rps = argument

    def _on_frame(self, msg: can.Message) -> can.Message | None:
        """What the crate does with ``msg``: the answer to send, if any."""
        if msg.is_extended_id or msg.is_error_frame or not msg.is_rx:
            return None
        function, crate_id = split_id(msg.arbitration_id)
        if crate_id != self.crate_id:
            return None
        with self._lock:
            if self._silent:
                return None
            if not msg.is_remote_frame:
                if function == Function.COMMAND:
                    self._command(bytes(msg.data))
                elif function in READ_FUNCTIONS:
                    self._violation(
                        CrateRule.DATA_TO_READ_FUNCTION,
                        f"data frame {bytes(msg.data).hex()} to {function_name(function)}",
                    )
                else:
                    self._violation(
                        CrateRule.UNKNOWN_FUNCTION, f"data frame to function {function}"
                    )
                return None
            if function not in READ_FUNCTIONS:
                self._violation(
                    CrateRule.UNKNOWN_FUNCTION, f"read request for {function_name(function)}"
                )
                return None
            if msg.dlc != FRAME_DLC:
                self._violation(
                    CrateRule.BAD_REMOTE_DLC,
                    f"read request for {function_name(function)} with dlc {msg.dlc}",
                )
            payload = self._payload(Function(function))
            self.requests += 1
        return can.Message(arbitration_id=msg.arbitration_id, is_extended_id=False, data=payload)

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                msg = self._bus.recv(timeout=RECV_CYCLE_S)
                if msg is None:
                    continue
                try:
                    answer = self._on_frame(msg)
                finally:
                    with self._lock:
                        self.frames_seen += 1
                if answer is not None:
                    self._bus.send(answer)
            except ValueError as exc:  # state no frame can carry: the crate's fault, not the host's
                log.error("simulated crate %d: %s", self.crate_id, exc)
            except can.CanError as exc:
                if not self._stop.is_set():
                    log.warning("simulated crate %d: %s", self.crate_id, exc)
                return

    # -- audit ------------------------------------------------------------------------------------
    @property
    def violations(self) -> list[Violation]:
        """A copy of this crate's broken rules (CrateRule), oldest first."""
        return self._audit.violations

    def _violation(self, rule: CrateRule, detail: str) -> None:
        detail = f"crate {self.crate_id}: {detail}"
        log.warning("%s %s", rule.value, detail)
        self._audit.record(rule, detail)

    # -- life -------------------------------------------------------------------------------------
    def close(self) -> None:
        """Stop answering, join the thread, shut the bus down. Idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
        self._stop.set()
        if self._thread is not threading.current_thread():
            self._thread.join()
        self._bus.shutdown()

    @property
    def closed(self) -> bool:
        return self._closed

    @property
    def running(self) -> bool:
        """The crate's thread is alive."""
        return self._thread.is_alive()

    def __enter__(self) -> SimulatedCrate:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"<SimulatedCrate {self.crate_id} on {self.channel}>"


def _channel_bit(channel: int) -> int:
    if isinstance(channel, bool) or channel not in range(CHANNELS):
        raise ValueError(f"channel {channel!r} is not 0..{CHANNELS - 1}")
    return 1 << channel

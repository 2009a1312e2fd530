"""BIEXEC_COM commands: seen at vertical sync, executed one at a time, completed in order.

**Vertical sync.** COMMAND is read at every video field (an idle thread runs the fields it slept
through together, and a write wakes it: :data:`~sim.supervisor.supervisor.IDLE_CHECK_FIELDS`). A
non-zero COMMAND while idle is accepted; it completes after a field-synchronised delay plus a
seeded jitter of 20 us .. 2 ms (BI_BOOT two fields later, BI_LOAD_LUT one), so from the host's
write to completion takes from tens of microseconds to tens of milliseconds. Completion writes
STATUS, the answer into PARAM (NUL-terminated ASCII: addresses ``0x%08X``, sizes decimal; a
short message on error), clears COMMAND, then raises the command interrupt if
``_Biris_cmd_int_enable`` is set.

**Busy.** From acceptance to completion the supervisor is busy. A COMMAND value that changes
meanwhile is recorded as ``CMD_WHILE_BUSY`` and the new command is lost (completion clears
COMMAND). Field-rate polling cannot see a rewrite of the same value, nor a second write before
the first was accepted: an in-process rig can call :meth:`Commands.note_command_write` from a
write hook, *after* the write has landed, to catch those too.
"""

from __future__ import annotations

from regs.biexec import (
    BIEXEC_PARAM_SIZE,
    OFF_CMD_INT_ENABLE,
    OFF_COMMAND,
    OFF_PARAM,
    OFF_STATUS,
    BiCommand,
    BiStatus,
    encode_param,
)
from sim.audit import Rule
from sim.clock import FIELD_PERIOD
from sim.supervisor.state import SupervisorState, signed16

__all__ = ["Commands"]

_EXTRA_FIELDS = {BiCommand.BI_BOOT: 2, BiCommand.BI_LOAD_LUT: 1}
_QUERIES = frozenset(
    {BiCommand.BI_GET_VME_ADDR_DIST, BiCommand.BI_GET_VME_ADDR_AZIM, BiCommand.BI_GET_VME_INC_FRAME}
)
_NOT_HEX = str.maketrans("0123456789ABCDEFabcdef", "GHIJKLMNOPQRSTUVWXYZgh")


class Commands(SupervisorState):
    """COMMAND polling and the driver's write hook, dispatch, queries, and completion."""

    def note_command_write(self, value: int) -> None:
        """Tell the supervisor that the driver has just written ``value`` to COMMAND.

        Call it from a write hook after the write landed. It catches what vsync polling cannot:
        a rewrite of the same code while busy, and a second write before the first was accepted.
        A vsync may fall between the write and the hook: a note matching a command accepted
        since the last note is that command's own write, not a second one.
        """
        value = signed16(value & 0xFFFF)
        with self._lock:
            if self._accepted_unnoted and value == self._executing:
                self._accepted_unnoted = False
                return
            if self._executing or self._outstanding_write:
                self._command_while_busy(
                    value, "COMMAND written before the previous command completed"
                )
            landed = self._get(OFF_COMMAND) != 0
            self._outstanding_write = value != 0 and landed and not self._executing
        self.wake_idle()

    def _command_while_busy(self, value: int, detail: str) -> None:
        """CMD_WHILE_BUSY: the new command is lost; ``value`` is what COMMAND now holds."""
        self._record(Rule.CMD_WHILE_BUSY, detail, COMMAND=value, EXECUTING=self._executing)
        self._last_seen = value

    def _poll_command(self, field: int, t: float) -> None:
        value = self._get(OFF_COMMAND)
        if self._executing:
            if value != self._last_seen:
                self._command_while_busy(value, "COMMAND changed while a command executed")
            return
        if value != 0:
            self._accept(value, field, t)

    def _accept(self, code: int, field: int, t: float) -> None:
        """Take command ``code`` at vsync ``field`` and arrange its completion."""
        self._executing = code
        self._last_seen = code
        self._accepted_unnoted = not self._outstanding_write
        self._outstanding_write = False
        try:
            command: BiCommand | None = BiCommand(code)
        except ValueError:
            command = None
        if command is None:
            self._finish_later(t, BiStatus.UNKNOWN_COMMAND, f"unknown command {code}")
            return
        done = t + _EXTRA_FIELDS.get(command, 0) * FIELD_PERIOD
        if command is BiCommand.BI_BOOT:
            self._cmd_boot(done)
        elif command in _QUERIES:
            self._finish_later(done, BiStatus.OK, self._query_answer(command), query=True)
        elif command is BiCommand.BI_ACQUIRE:
            self._cmd_acquire(field, t)
        elif command is BiCommand.BI_START_CONTINUOUS:
            self._cmd_start_continuous(field, t)
        elif command is BiCommand.BI_STOP_CONTINUOUS:
            self._cmd_stop_continuous(done)
        else:
            self._cmd_load_lut(done)

    def _query_answer(self, command: BiCommand) -> str:
        if command is BiCommand.BI_GET_VME_ADDR_DIST:
            return f"0x{self._map.address(self._map.range_offset):08X}"
        if command is BiCommand.BI_GET_VME_ADDR_AZIM:
            return f"0x{self._map.address(self._map.azimuth_offset):08X}"
        return str(self._map.frame_size)

    def _complete(self, status: BiStatus, answer: str, *, query: bool) -> None:
        """STATUS, PARAM, clear COMMAND, then the command interrupt: the driver's order."""
        self._set(OFF_STATUS, int(status))
        self._mem.write(self._base + OFF_PARAM, self._param_bytes(answer, query))
        self._set(OFF_COMMAND, 0)
        self._executing = 0
        self._last_seen = 0
        self._outstanding_write = False
        self._accepted_unnoted = False
        self._commands_completed += 1
        if self._get(OFF_CMD_INT_ENABLE):
            self._gate.raise_irq("cmd")

    def _param_bytes(self, answer: str, query: bool) -> bytes:
        """PARAM's bytes for ``answer``; malformed when a garbage_param fault is armed."""
        text = answer[: BIEXEC_PARAM_SIZE - 1]
        if not (query and self._garbage_armed):
            return encode_param(text)
        kind = self._garbage
        if kind is None:
            kind = "unterminated" if self._rng.integers(2) == 0 else "bad_digits"
        self._garbage_armed = False
        self._garbage = None
        if kind == "bad_digits":
            head, body = (text[:2], text[2:]) if text.startswith("0x") else ("", text)
            return encode_param(head + body.translate(_NOT_HEX))
        return (text.encode("ascii") + b"#" * BIEXEC_PARAM_SIZE)[:BIEXEC_PARAM_SIZE]

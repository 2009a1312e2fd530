"""The Wiener VME crate monitor over CAN (issue 13 B.3): wire format, driver, simulated crate.

Every test runs on a python-can ``virtual`` channel of its own (a uuid): the driver's
:class:`CrateMonitor` on one bus, the :class:`SimulatedCrate` (or a test's raw bus playing a
crate, for answers the simulator never gives) on another. Nothing sleeps to synchronise: a
read waits for its answers, and the simulator's reactions are waited for with ``until``. Every
test is leak-checked (``no_leaks``): its buses are shut down and its threads joined.
"""

from __future__ import annotations

import errno
import json
import struct
import threading
import uuid
from collections.abc import Callable, Iterator, Mapping, Sequence
from typing import Any

import can
import pytest

from biris_hw.crate import CrateMonitor
from biris_hw.errors import BusError
from regs.wiener_crate import (
    CRATE_IDS,
    HEALTHY_STATUS0,
    PAIR_FUNCTIONS,
    READ_FUNCTIONS,
    Command,
    CrateReading,
    Function,
    Status1,
    can_id,
    encode_channels,
    encode_fans,
    encode_status,
    encode_temperatures,
    split_id,
)
from sim.wiener_crate import (
    DEFAULT_CURRENTS_A,
    DEFAULT_FAN_RPS,
    DEFAULT_TEMPERATURES_C,
    DEFAULT_VOLTAGES_V,
    CrateRule,
    SimulatedCrate,
)
from tests.conftest import WAIT, until

pytestmark = pytest.mark.usefixtures("no_leaks")

CRATE = 5
FAST_TIMEOUT_S = 0.05
"""A short answer timeout, for the tests where no answer comes."""

ANSWERED_TIMEOUT_S = 1.0
"""The answer timeout of a test where some answers come (from a fake crate's thread, late on a
loaded host) and one does not (it then costs this)."""


@pytest.fixture
def channel() -> str:
    return f"crate-{uuid.uuid4().hex}"


@pytest.fixture
def crate(channel: str) -> Iterator[SimulatedCrate]:
    with SimulatedCrate(channel, CRATE) as sim:
        yield sim


@pytest.fixture
def monitor(channel: str) -> Iterator[CrateMonitor]:
    # a crate that answers is waited for as long as a loaded host may take to run its thread
    with CrateMonitor.open(
        interface="virtual", channel=channel, crate_id=CRATE, timeout_s=WAIT
    ) as mon:
        yield mon


@pytest.fixture
def raw(channel: str) -> Iterator[can.BusABC]:
    """A bus of the test's own on the channel: to play the host, or a crate."""
    bus = can.Bus(interface="virtual", channel=channel)
    yield bus
    bus.shutdown()


def frames_of(
    *,
    status: bytes | None = None,
    voltages: Sequence[float] = DEFAULT_VOLTAGES_V,
    currents: Sequence[float] = DEFAULT_CURRENTS_A,
    fans: bytes | None = None,
    temperatures: Sequence[int] = DEFAULT_TEMPERATURES_C,
) -> dict[int, bytes]:
    """The seven answers of a crate, built with the encoders."""
    frames = {Function.STATUS.value: encode_status() if status is None else status}
    for n, function in enumerate(PAIR_FUNCTIONS):
        frames[function] = encode_channels(
            n, voltages[n], currents[n], voltages[n + 4], currents[n + 4]
        )
    frames[Function.FANS] = encode_fans(50, 50, [50] * 6) if fans is None else fans
    frames[Function.TEMPERATURES] = encode_temperatures(temperatures)
    return frames


class FakeCrate:
    """A raw bus answering read requests for ``crate_id`` from ``answers`` (function -> data,
    any length; a function it has no answer for goes unanswered), sending ``noise`` before each
    answer: what the simulator never does, for the driver's error paths."""

    def __init__(
        self,
        channel: str,
        crate_id: int,
        answers: Mapping[int, bytes],
        noise: Callable[[int], list[can.Message]] = lambda _id: [],
    ) -> None:
        self.crate_id = crate_id
        self.answers = dict(answers)
        self.noise = noise
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.notifier = can.Notifier(self.bus, [self._on_message], timeout=0.01)

    def _on_message(self, msg: can.Message) -> None:
        if not msg.is_remote_frame or msg.is_extended_id:
            return
        function, crate_id = split_id(msg.arbitration_id)
        if crate_id != self.crate_id or function not in self.answers:
            return
        for frame in self.noise(msg.arbitration_id):
            self.bus.send(frame)
        answer = can.Message(
            arbitration_id=msg.arbitration_id, is_extended_id=False, data=self.answers[function]
        )
        self.bus.send(answer)

    def close(self) -> None:
        self.notifier.stop()
        self.bus.shutdown()


NOISY_CRATE = 100
"""A crate no test reads, whose frames are only ever noise."""


def noise_for(wanted: int) -> list[can.Message]:
    """Frames a monitor waiting for ``wanted`` must skip."""
    function, crate_id = split_id(wanted)
    garbage = bytes(range(0xF0, 0xF8))
    return [
        # the same function of another crate
        can.Message(
            arbitration_id=can_id(function, NOISY_CRATE), is_extended_id=False, data=garbage
        ),
        # the wanted number as an extended id
        can.Message(arbitration_id=wanted, is_extended_id=True, data=garbage),
        # the request itself, echoed
        can.Message(arbitration_id=wanted, is_extended_id=False, is_remote_frame=True, dlc=8),
        # a command to this crate from another host, of another length
        can.Message(
            arbitration_id=can_id(Function.COMMAND, crate_id),
            is_extended_id=False,
            data=bytes([Command.SYSRESET]),
        ),
        # another device altogether, and an error frame
        can.Message(arbitration_id=0x7FF, is_extended_id=False, data=b"\x01\x02"),
        can.Message(is_error_frame=True),
    ]


# -- identifiers -----------------------------------------------------------------------------------


def test_can_id_arithmetic() -> None:
    assert can_id(Function.STATUS, 1) == 0x001
    assert can_id(Function.FANS, 5) == 0x305
    assert can_id(Function.TEMPERATURES, 126) == 0x3FE
    assert can_id(Function.COMMAND, 0x40) == 0x0C0
    for function in Function:
        for crate_id in (1, 2, 63, 64, 125, 126):
            assert split_id(can_id(function, crate_id)) == (function, crate_id)
    assert split_id(0x7FF) == (15, 127)
    assert READ_FUNCTIONS == (0, 2, 3, 4, 5, 6, 7)
    assert (CRATE_IDS.start, CRATE_IDS.stop) == (1, 127)


@pytest.mark.parametrize(
    ("function", "crate_id"),
    [(0, 0), (0, 127), (0, -1), (8, 1), (-1, 1), (0, True), (True, 1), (2.0, 1), (0, 1.0)],
)
def test_bad_ids_are_refused(function: object, crate_id: object) -> None:
    with pytest.raises(ValueError, match="not"):
        can_id(function, crate_id)  # type: ignore[arg-type]


@pytest.mark.parametrize("arbitration_id", [0x800, -1, 0x1FFFFFFF])
def test_split_id_refuses_what_is_not_standard(arbitration_id: int) -> None:
    with pytest.raises(ValueError, match="11-bit"):
        split_id(arbitration_id)


@pytest.mark.parametrize("crate_id", [0, 127, -3, True])
def test_monitor_refuses_bad_crate_ids(crate_id: int, raw: can.BusABC) -> None:
    with pytest.raises(ValueError, match="crate id"):
        CrateMonitor(raw, crate_id)
    # checked before any bus is opened: the interface does not exist
    with pytest.raises(ValueError, match="crate id"):
        CrateMonitor.open(interface="no-such-interface", channel="x", crate_id=crate_id)


@pytest.mark.parametrize("timeout_s", [0.0, -1.0, float("inf"), float("nan"), True])
def test_monitor_refuses_a_bad_timeout(raw: can.BusABC, timeout_s: float) -> None:
    with pytest.raises(ValueError, match="timeout"):
        CrateMonitor(raw, 1, timeout_s=timeout_s)
    with pytest.raises(ValueError, match="timeout"):  # before any bus is opened
        CrateMonitor.open(interface="no-such-interface", crate_id=1, timeout_s=timeout_s)


def test_an_unknown_interface_is_a_bus_error() -> None:
    with pytest.raises(BusError, match="Wiener crate 3: cannot open CAN no-such-interface"):
        CrateMonitor.open(interface="no-such-interface", channel="x", crate_id=3)


def test_open_passes_only_what_is_given(monkeypatch: pytest.MonkeyPatch, raw: can.BusABC) -> None:
    """Without interface, channel or bitrate, python-can's own configuration supplies them."""
    seen: list[dict[str, Any]] = []

    def fake_bus(**options: Any) -> can.BusABC:
        seen.append(options)
        return raw

    monkeypatch.setattr(can, "Bus", fake_bus)
    with CrateMonitor.open(crate_id=4) as monitor:
        assert seen[-1] == {"can_filters": [{"can_id": 4, "can_mask": 0x7F, "extended": False}]}
        assert monitor.channel_info == raw.channel_info
    with CrateMonitor.open(
        interface="socketcan", channel="can0", bitrate=125_000, crate_id=4
    ) as monitor:
        assert {k: seen[-1][k] for k in ("interface", "channel", "bitrate")} == {
            "interface": "socketcan",
            "channel": "can0",
            "bitrate": 125_000,
        }
        assert monitor.channel_info == "CAN socketcan channel can0"


# -- the wire format -------------------------------------------------------------------------------


def test_channel_words_are_signed_little_endian_hundredths() -> None:
    data = encode_channels(1, 12.0, 2.5, -12.0, 0.8)
    assert data == struct.pack("<4h", 1200, 250, -1200, 80)
    assert data[4:6] == b"\x50\xfb"  # -1200, two's complement, low byte first
    reading = CrateReading.from_frames(
        1, {**frames_of(), PAIR_FUNCTIONS[1]: data, PAIR_FUNCTIONS[3]: b"\x00\x80\xff\x7f" * 2}, 0.0
    )
    assert (reading.voltages_v[1], reading.currents_a[1]) == (12.0, 2.5)
    assert (reading.voltages_v[5], reading.currents_a[5]) == (-12.0, 0.8)
    assert (reading.voltages_v[3], reading.currents_a[3]) == (-327.68, 327.67)


def test_round_trip_of_every_frame() -> None:
    voltages = (5.01, 12.0, -5.0, 3.3, 0.0, -12.0, 327.67, -327.68)
    currents = (20.5, 1.0, 0.0, 6.25, -0.01, 0.8, 0.0, 1.5)
    temperatures = (0, 25, 30, 31, 45, 60, 99, 255)
    status = encode_status(
        over_current=0x02,
        supply_temperature=0x81,
        under_voltage=0x10,
        over_voltage=0x20,
        external_temperature=0x40,
        over_voltage_protection=0x08,
        status1=Status1.SOFT_START | Status1.BIN_ERROR,
    )
    frames = frames_of(
        status=status,
        voltages=voltages,
        currents=currents,
        fans=encode_fans(41, 45, [40, 41, 42, 43, 0, 64]),
        temperatures=temperatures,
    )
    reading = CrateReading.from_frames(7, frames, 12.5)
    assert reading.crate_id == 7
    assert reading.read_at == 12.5
    assert reading.voltages_v == voltages
    assert reading.currents_a == currents
    assert reading.temperatures_c == temperatures
    assert (reading.fan_average_rps, reading.fan_nominal_rps) == (41, 45)
    assert reading.fans_rps == (40, 41, 42, 43, 0, 64)
    assert reading.status_bytes == status
    assert (reading.under_voltage, reading.over_voltage) == (0x10, 0x20)
    assert (reading.external_temperature, reading.over_current) == (0x40, 0x02)
    assert (reading.over_voltage_protection, reading.supply_temperature) == (0x08, 0x81)
    assert reading.status1 == Status1.SOFT_START | Status1.BIN_ERROR


def test_a_healthy_status_byte_and_each_flag_alone() -> None:
    assert encode_status() == bytes([HEALTHY_STATUS0, 0, 0, 0, 0, 0, 0, 0])
    assert HEALTHY_STATUS0 == 0x9F
    healthy = CrateReading.from_frames(1, frames_of(), 0.0)
    flags = ("power_on", "inhibit", "supply_ok", "power_supply_error", "fans_ok", "sysfail")
    assert [getattr(healthy, f) for f in flags] == [True, False, True, False, True, False]
    # each fault clears (or sets) one bit of byte 0, and decodes to its field alone
    for flag, argument, bit in [
        ("power_on", {"power_on": False}, 0x01),
        ("inhibit", {"inhibit": True}, 0x02),
        ("supply_ok", {"supply_ok": False}, 0x04),
        ("power_supply_error", {"power_supply_error": True}, 0x08),
        ("fans_ok", {"fans_ok": False}, 0x10),
        ("sysfail", {"sysfail": True}, 0x80),
    ]:
        status = encode_status(**argument)
        assert status[0] == HEALTHY_STATUS0 ^ bit, flag
        reading = CrateReading.from_frames(1, frames_of(status=status), 0.0)
        changed = [f for f in flags if getattr(reading, f) != getattr(healthy, f)]
        assert changed == [flag]
    assert encode_status(trip_on_fan_failure=True, trip_on_error=True)[0] == 0xFF


@pytest.mark.parametrize(
    "encode",
    [
        lambda: encode_channels(4, 0, 0, 0, 0),
        lambda: encode_channels(-1, 0, 0, 0, 0),
        lambda: encode_channels(0, 327.68, 0, 0, 0),
        lambda: encode_channels(0, 0, 0, -327.69, 0),
        lambda: encode_channels(0, float("nan"), 0, 0, 0),
        lambda: encode_fans(256, 50, [50] * 6),
        lambda: encode_fans(50, 50, [50] * 5),
        lambda: encode_fans(50, 50, [50, 50, 50, 50, 50, -1]),
        lambda: encode_temperatures([30] * 7),
        lambda: encode_temperatures([30] * 7 + [256]),
        lambda: encode_status(over_current=0x100),
        lambda: encode_status(status1=-1),
    ],
)
def test_encoders_refuse_what_no_frame_carries(encode: Callable[[], bytes]) -> None:
    with pytest.raises(ValueError):
        encode()


def test_from_frames_names_the_missing_or_short_function() -> None:
    frames = frames_of()
    del frames[Function.FANS]
    with pytest.raises(ValueError, match=r"fans \(function 6\)"):
        CrateReading.from_frames(1, frames, 0.0)
    frames = {**frames_of(), Function.CHANNELS_2_6.value: b"\x00" * 7}
    with pytest.raises(ValueError, match=r"channels 2/6 \(function 4\) frame is 7 bytes"):
        CrateReading.from_frames(1, frames, 0.0)


def test_alarms_name_each_problem() -> None:
    status = encode_status(
        power_on=False,
        inhibit=True,
        over_current=0b0000_0110,
        supply_temperature=0b1000_0000,
        status1=Status1.CHECKSUM_ERROR | Status1.READ_ONLY | Status1.WRITE_PROTECT,
    )
    reading = CrateReading.from_frames(1, frames_of(status=status), 0.0)
    assert reading.alarms() == (
        "crate power is off",
        "external power inhibit is active",
        "over-current on channel 1",
        "over-current on channel 2",
        "power-supply over-temperature on channel 7",
        "checksum error",
    )
    assert not reading.ok
    # the modes of byte 1 are no alarm
    quiet = encode_status(status1=Status1.READ_ONLY | Status1.SOFT_START | Status1.WRITE_PROTECT)
    assert CrateReading.from_frames(1, frames_of(status=quiet), 0.0).ok


# -- to_dict / from_dict ---------------------------------------------------------------------------


def test_dict_round_trip_through_json() -> None:
    status = encode_status(over_current=0x02, status1=Status1.BIN_ERROR)
    reading = CrateReading.from_frames(9, frames_of(status=status), 3.25)
    d = reading.to_dict()
    assert d["status_bytes"] == status.hex()
    assert d["voltages_v"] == list(DEFAULT_VOLTAGES_V)
    assert d["alarms"] == ["over-current on channel 1", "bin error"]
    assert d["ok"] is False
    back = CrateReading.from_dict(json.loads(json.dumps(d)))
    assert back == reading
    assert back.alarms() == reading.alarms()
    # what a reader ignores: its derived keys (recomputed), and keys it does not know
    assert CrateReading.from_dict({**d, "ok": True, "alarms": [], "newer": 1}) == reading


def _garbled(**changes: object) -> dict[str, object]:
    d = CrateReading.from_frames(1, frames_of(), 0.0).to_dict()
    d.update(changes)
    return d


@pytest.mark.parametrize(
    ("d", "words"),
    [
        ({k: v for k, v in _garbled().items() if k != "fans_rps"}, "without fans_rps"),
        (_garbled(power_on=1), "power_on"),
        (_garbled(crate_id=True), "crate_id"),
        (_garbled(crate_id=0), "crate id"),
        (_garbled(over_current=256), "over_current"),
        (_garbled(voltages_v=[5.0] * 7), "voltages_v has 7"),
        (_garbled(voltages_v=["5"] + [0.0] * 7), "voltages_v"),
        (_garbled(fans_rps=[50] * 5 + [300]), "fan speed"),
        (_garbled(temperatures_c="30"), "temperatures_c"),
        (_garbled(status_bytes="9f00"), "status is 2 bytes"),
        (_garbled(status_bytes="not hex!"), "not hex"),
        (_garbled(read_at=None), "read_at"),
        (_garbled(read_at=float("inf")), "read_at"),
    ],
)
def test_from_dict_refuses_garbage(d: dict[str, object], words: str) -> None:
    with pytest.raises(ValueError, match=words):
        CrateReading.from_dict(d)


def test_from_dict_refuses_what_is_not_a_mapping() -> None:
    with pytest.raises(ValueError, match="mapping"):
        CrateReading.from_dict([1, 2, 3])  # type: ignore[arg-type]


# -- the driver against the simulated crate --------------------------------------------------------


def test_a_healthy_crate_reads_ok(crate: SimulatedCrate, channel: str) -> None:
    with CrateMonitor.open(
        interface="virtual", channel=channel, crate_id=CRATE, timeout_s=WAIT, clock=lambda: 12.5
    ) as monitor:
        reading = monitor.read()
    assert reading.read_at == 12.5
    assert reading.ok, reading.alarms()
    assert reading.alarms() == ()
    assert reading.crate_id == CRATE
    assert reading.power_on and reading.supply_ok and reading.fans_ok
    assert not (reading.inhibit or reading.sysfail or reading.power_supply_error)
    assert reading.voltages_v == DEFAULT_VOLTAGES_V
    assert reading.voltages_v[5] == -12.0
    assert reading.currents_a == DEFAULT_CURRENTS_A
    assert reading.fans_rps == (DEFAULT_FAN_RPS,) * 6
    assert reading.fan_average_rps == reading.fan_nominal_rps == DEFAULT_FAN_RPS
    assert reading.temperatures_c == DEFAULT_TEMPERATURES_C
    assert crate.requests == len(READ_FUNCTIONS)
    assert crate.violations == []
    assert "virtual" in monitor.channel_info and channel in monitor.channel_info


def test_the_clock_given_stamps_the_reading(crate: SimulatedCrate, raw: can.BusABC) -> None:
    ticks = iter([100.0, 200.0])
    monitor = CrateMonitor(raw, CRATE, timeout_s=WAIT, clock=lambda: next(ticks))
    assert monitor.read().read_at == 100.0
    assert monitor.read().read_at == 200.0
    monitor.close()


def _fail_fan(c: SimulatedCrate) -> None:
    c.fail_fan(2)


def _overheat(c: SimulatedCrate) -> None:
    c.overheat(3)


def _over_current(c: SimulatedCrate) -> None:
    c.over_current(1)


def _set(attribute: str, value: object) -> Callable[[SimulatedCrate], None]:
    return lambda c: setattr(c, attribute, value)


@pytest.mark.parametrize(
    ("fault", "alarm"),
    [
        (_fail_fan, "fan failure"),
        (_overheat, "power-supply over-temperature on channel 3"),
        (_over_current, "over-current on channel 1"),
        (SimulatedCrate.power_off, "crate power is off"),
        (_set("inhibit", True), "external power inhibit is active"),
        (_set("supply_ok", False), "power supply reports a power fail"),
        (_set("power_supply_error", True), "power-supply error"),
        (_set("sysfail", True), "VME SYSFAIL is asserted"),
        (_set("under_voltage", 0x08), "under-voltage on channel 3"),
        (_set("over_voltage", 0x01), "over-voltage on channel 0"),
        (_set("external_temperature", 0x04), "external over-temperature on channel 2"),
        (_set("over_voltage_protection", 0x20), "over-voltage protection tripped on channel 5"),
        (_set("status1", Status1.BIN_ERROR), "bin error"),
        (_set("status1", Status1.CHECKSUM_ERROR), "checksum error"),
        (_set("status1", Status1.INCOMPATIBLE), "power supply and bin not compatible"),
    ],
)
def test_each_fault_is_its_alarm(
    crate: SimulatedCrate,
    monitor: CrateMonitor,
    fault: Callable[[SimulatedCrate], None],
    alarm: str,
) -> None:
    assert monitor.read().ok
    fault(crate)
    reading = monitor.read()
    assert reading.alarms() == (alarm,)
    assert not reading.ok
    crate.clear_all()
    assert monitor.read().ok


def test_what_each_fault_reports(crate: SimulatedCrate, monitor: CrateMonitor) -> None:
    crate.fail_fan(2)
    reading = monitor.read()
    assert not reading.fans_ok
    assert reading.fans_rps == (50, 50, 0, 50, 50, 50)
    assert reading.fan_average_rps == round(250 / 6)
    assert reading.power_on  # no trip-off unless enabled
    crate.clear_all()
    crate.overheat(3)
    crate.over_current(0)
    crate.over_current(6)
    reading = monitor.read()
    assert (reading.supply_temperature, reading.over_current) == (0x08, 0x41)
    assert reading.voltages_v == DEFAULT_VOLTAGES_V  # flags alone: the supply still delivers
    crate.clear_all()
    crate.power_off()
    reading = monitor.read()
    assert not reading.power_on
    assert reading.voltages_v == (0.0,) * 8
    assert reading.currents_a == (0.0,) * 8
    assert reading.fans_rps == (0,) * 6 and reading.fan_average_rps == 0
    assert reading.fan_nominal_rps == DEFAULT_FAN_RPS
    assert reading.temperatures_c == DEFAULT_TEMPERATURES_C
    crate.power_on()
    reading = monitor.read()
    assert reading.ok and reading.voltages_v == DEFAULT_VOLTAGES_V


def test_trip_off_on_fan_failure_and_on_error(crate: SimulatedCrate, monitor: CrateMonitor) -> None:
    crate.trip_on_fan_failure = True
    reading = monitor.read()
    assert reading.ok and reading.status_bytes[0] == HEALTHY_STATUS0 | 0x20
    crate.fail_fan(0)
    assert monitor.read().alarms() == ("crate power is off", "fan failure")
    crate.clear_all()
    crate.trip_on_error = True
    crate.over_current(2)
    assert monitor.read().alarms() == ("crate power is off", "over-current on channel 2")


def test_fault_panel_refuses_what_is_not_there(crate: SimulatedCrate) -> None:
    with pytest.raises(ValueError, match="fan index"):
        crate.fail_fan(6)
    with pytest.raises(ValueError, match="channel"):
        crate.overheat(8)
    with pytest.raises(ValueError, match="channel"):
        crate.over_current(-1)


def test_a_silent_crate_is_a_bus_error_naming_the_function(
    crate: SimulatedCrate, channel: str
) -> None:
    with CrateMonitor.open(
        interface="virtual", channel=channel, crate_id=CRATE, timeout_s=FAST_TIMEOUT_S
    ) as monitor:
        crate.go_silent()
        with pytest.raises(BusError) as caught:
            monitor.read()
        message = str(caught.value)
        assert f"Wiener crate {CRATE}" in message
        assert "status (function 0)" in message and "no answer within 0.05 s" in message
        assert caught.value.errno == errno.ETIMEDOUT
        assert isinstance(caught.value, OSError)
        assert crate.requests == 0
        crate.answer_again()
        assert monitor.read().ok
        assert crate.requests == len(READ_FUNCTIONS)


def test_a_missing_answer_names_its_function(channel: str, raw: can.BusABC) -> None:
    answers = frames_of()
    del answers[Function.TEMPERATURES]
    fake = FakeCrate(channel, CRATE, answers)
    try:
        # the functions before it are answered by the fake crate's thread: a timeout that
        # thread meets on a loaded host (0.05 s once was not), and that the missing one costs
        with pytest.raises(BusError, match=r"temperatures \(function 7\), CAN id 0x385"):
            CrateMonitor(raw, CRATE, timeout_s=ANSWERED_TIMEOUT_S).read()
    finally:
        fake.close()


def test_a_malformed_answer_is_a_bus_error(channel: str, raw: can.BusABC) -> None:
    fake = FakeCrate(channel, CRATE, {**frames_of(), Function.FANS.value: b"\x32\x32\x32\x32"})
    try:
        with pytest.raises(BusError) as caught:
            CrateMonitor(raw, CRATE, timeout_s=WAIT).read()
    finally:
        fake.close()
    assert "malformed answer to the read of fans (function 6): dlc 4" in str(caught.value)
    assert caught.value.errno == errno.EPROTO


@pytest.mark.parametrize("filtered", [True, False], ids=["open-filtered", "raw-bus"])
def test_other_crates_and_other_traffic_are_skipped(channel: str, filtered: bool) -> None:
    """Crate 5 is a fake that sends noise before every answer; crate 6, on the same channel,
    is a simulated one in another state. Each monitor reads its own crate, exactly."""
    status = encode_status(over_voltage=0x02)
    voltages = (5.1, 11.9, 0.0, 3.31, 0.0, -11.95, 0.0, 0.0)
    fake = FakeCrate(channel, CRATE, frames_of(status=status, voltages=voltages), noise_for)
    other = SimulatedCrate(channel, CRATE + 1)
    other.over_current(4)
    bus: can.BusABC | None = None
    if filtered:
        mine = CrateMonitor.open(
            interface="virtual", channel=channel, crate_id=CRATE, timeout_s=WAIT
        )
        theirs = CrateMonitor.open(
            interface="virtual", channel=channel, crate_id=CRATE + 1, timeout_s=WAIT
        )
    else:
        bus = can.Bus(interface="virtual", channel=channel)
        mine = CrateMonitor(bus, CRATE, timeout_s=WAIT)
        theirs = CrateMonitor.open(
            interface="virtual", channel=channel, crate_id=CRATE + 1, timeout_s=WAIT
        )
    try:
        for _ in range(3):
            reading = mine.read()
            assert reading.crate_id == CRATE
            assert reading.alarms() == ("over-voltage on channel 1",)
            assert reading.voltages_v == voltages
            assert reading.fans_rps == (50,) * 6
            theirs_reading = theirs.read()
            assert theirs_reading.crate_id == CRATE + 1
            assert theirs_reading.alarms() == ("over-current on channel 4",)
            assert theirs_reading.voltages_v == DEFAULT_VOLTAGES_V
    finally:
        mine.close()
        theirs.close()
        if bus is not None:
            bus.shutdown()
        other.close()
        fake.close()
    assert other.requests == 3 * len(READ_FUNCTIONS)
    assert other.violations == []  # crate 5's traffic is none of crate 6's business


def test_two_threads_reading_at_once_both_get_whole_readings(
    crate: SimulatedCrate, channel: str
) -> None:
    crate.fail_fan(4)
    crate.temperatures_c[7] = 61
    rounds = 20
    start = threading.Barrier(2)
    results: list[CrateReading] = []
    errors: list[BaseException] = []
    lock = threading.Lock()
    with CrateMonitor.open(
        interface="virtual", channel=channel, crate_id=CRATE, timeout_s=WAIT
    ) as monitor:

        def reader() -> None:
            try:
                start.wait(WAIT)
                for _ in range(rounds):
                    reading = monitor.read()
                    with lock:
                        results.append(reading)
            except BaseException as exc:  # handed to the test's thread
                errors.append(exc)

        threads = [threading.Thread(target=reader) for _ in range(2)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(WAIT * 4)
        assert not any(thread.is_alive() for thread in threads)
    assert errors == []
    assert len(results) == 2 * rounds
    expected_fans = (50, 50, 50, 50, 0, 50)
    for reading in results:
        assert reading.alarms() == ("fan failure",)
        assert reading.fans_rps == expected_fans
        assert reading.voltages_v == DEFAULT_VOLTAGES_V
        assert reading.temperatures_c[7] == 61
    assert crate.requests == 2 * rounds * len(READ_FUNCTIONS)


# -- the simulated crate's commands and audit ------------------------------------------------------


def _send(
    bus: can.BusABC, function: int, data: bytes = b"", *, remote: bool = False, dlc: int = -1
) -> None:
    """A frame of crate CRATE's ``function`` (0-15: functions no crate has as well) from the
    test's bus (dlc -1: the data's length)."""
    frame = can.Message(
        arbitration_id=function << 7 | CRATE,
        is_extended_id=False,
        is_remote_frame=remote,
        data=None if remote else data,
        dlc=len(data) if dlc < 0 else dlc,
    )
    bus.send(frame)


def test_the_crate_obeys_commands(
    crate: SimulatedCrate, monitor: CrateMonitor, raw: can.BusABC
) -> None:
    _send(raw, Function.COMMAND, bytes([Command.OFF]))
    until(lambda: not crate.on)
    assert not monitor.read().power_on
    _send(raw, Function.COMMAND, bytes([Command.ON]))
    until(lambda: crate.on)
    _send(raw, Function.COMMAND, bytes([Command.SYSRESET]))
    until(lambda: crate.sysresets == 1)
    _send(raw, Function.COMMAND, bytes([Command.FAN_SPEED, 40]))
    until(lambda: crate.fan_nominal_rps == 40)
    reading = monitor.read()
    assert reading.ok
    assert reading.fan_nominal_rps == 40 and reading.fans_rps == (40,) * 6
    assert crate.commands == [
        (Command.OFF, None),
        (Command.ON, None),
        (Command.SYSRESET, None),
        (Command.FAN_SPEED, 40),
    ]
    assert crate.violations == []


@pytest.mark.parametrize(
    ("frame", "rule"),
    [
        ({"function": Function.STATUS, "remote": True, "dlc": 0}, CrateRule.BAD_REMOTE_DLC),
        ({"function": Function.COMMAND, "remote": True, "dlc": 8}, CrateRule.UNKNOWN_FUNCTION),
        ({"function": 9, "remote": True, "dlc": 8}, CrateRule.UNKNOWN_FUNCTION),
        ({"function": 12, "data": b"\x01"}, CrateRule.UNKNOWN_FUNCTION),
        ({"function": Function.FANS, "data": bytes(8)}, CrateRule.DATA_TO_READ_FUNCTION),
        ({"function": Function.COMMAND, "data": b""}, CrateRule.BAD_COMMAND),
        ({"function": Function.COMMAND, "data": b"\x99"}, CrateRule.BAD_COMMAND),
        ({"function": Function.COMMAND, "data": bytes([0xC0, 65])}, CrateRule.BAD_COMMAND),
        ({"function": Function.COMMAND, "data": bytes([0xC0])}, CrateRule.BAD_COMMAND),
    ],
)
def test_the_audit_records_protocol_misuse(
    crate: SimulatedCrate, raw: can.BusABC, frame: dict[str, Any], rule: CrateRule
) -> None:
    _send(raw, **frame)
    until(lambda: len(crate.violations) == 1)
    violation = crate.violations[0]
    assert violation.rule is rule
    assert f"crate {CRATE}" in violation.detail
    if rule is CrateRule.BAD_REMOTE_DLC:  # answered all the same, with 8 bytes
        answer = raw.recv(WAIT)
        assert answer is not None and answer.dlc == 8 and not answer.is_remote_frame
        assert crate.requests == 1
    else:
        assert crate.requests == 0
    assert crate.commands == []
    assert crate.on and crate.fan_nominal_rps == DEFAULT_FAN_RPS


def test_a_read_only_crate_audits_and_ignores_commands(
    crate: SimulatedCrate, raw: can.BusABC
) -> None:
    crate.status1 = Status1.READ_ONLY
    assert crate.read_only
    _send(raw, Function.COMMAND, bytes([Command.OFF]))
    until(lambda: len(crate.violations) == 1)
    assert crate.violations[0].rule is CrateRule.COMMAND_WHILE_READ_ONLY
    assert crate.commands == [(Command.OFF, None)]
    assert crate.on


def test_a_silent_crate_hears_nothing(crate: SimulatedCrate, raw: can.BusABC) -> None:
    crate.go_silent()
    _send(raw, Function.COMMAND, bytes([Command.OFF]))
    _send(raw, Function.STATUS, remote=True, dlc=0)
    _send(raw, Function.STATUS, remote=True, dlc=8)
    until(lambda: crate.frames_seen == 3)
    assert crate.requests == 0
    assert crate.on and crate.commands == [] and crate.violations == []
    assert raw.recv(0.0) is None  # nothing was answered
    crate.answer_again()
    _send(raw, Function.STATUS, remote=True, dlc=8)
    answer = raw.recv(WAIT)
    assert answer is not None and answer.arbitration_id == can_id(Function.STATUS, CRATE)
    assert crate.requests == 1


# -- closing ---------------------------------------------------------------------------------------


def test_close_is_idempotent_and_stops_everything(channel: str) -> None:
    crate = SimulatedCrate(channel, CRATE)
    monitor = CrateMonitor.open(interface="virtual", channel=channel, crate_id=CRATE)
    started = crate.running
    assert started
    assert monitor.read().ok
    monitor.close()
    monitor.close()
    assert monitor.closed
    with pytest.raises(BusError, match="closed"):
        monitor.read()
    with pytest.raises(can.CanOperationError):  # the monitor's own bus is shut down
        monitor.bus.send(can.Message(arbitration_id=1, is_extended_id=False))
    crate.close()
    crate.close()
    assert crate.closed and not crate.running
    with SimulatedCrate(channel, CRATE) as again:  # the channel is free for the next one
        started = again.running
        assert started
    assert not again.running


def test_a_monitor_leaves_a_bus_it_does_not_own_open(
    crate: SimulatedCrate, raw: can.BusABC
) -> None:
    with CrateMonitor(raw, CRATE, timeout_s=WAIT) as monitor:
        assert monitor.read().ok
    _send(raw, Function.STATUS, remote=True, dlc=8)  # still usable
    answer = raw.recv(WAIT)
    assert answer is not None and answer.dlc == 8

"""The initialisation record and motor parameters (biris_hw.records; report Appendices A-C)."""

from __future__ import annotations

import dataclasses
import math
import sys
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from biris_hw import BirisInitRecord, MotorParams
from biris_hw.errors import RequestError
from biris_hw.records import acq_rate_counts_per_acq, acquisitions_for


def test_defaults_are_appendix_b() -> None:
    record = BirisInitRecord()
    assert record.name == "BIRISSERV:"
    assert record.boot_file == "/dd/users/biris/binitlal.par"
    motor = record.motor
    assert (motor.sample, motor.zero, motor.pole, motor.gain, motor.max_vel, motor.max_accel) == (
        0xAF,
        0x7F,
        0xEF,
        0x3F,
        0x2,
        0x3322,
    )
    assert record.data_rate_ms == 30
    assert record.max_range == 0x7FFF
    assert record == BirisInitRecord(motor=MotorParams())


def test_later_fields_have_safe_defaults() -> None:
    record = BirisInitRecord()
    assert record.timeout_s == 4.0
    assert record.timeout_enabled is True  # a hung BIRIS is a fault unless the record says not
    assert record.home_index_timeout_revs == 1.0
    assert record.continuous_acquisition is False
    assert record.elevation_limits_counts == (-512, 512)
    assert record.mount_offset_m == (0.0, 0.0, 0.0)


def test_records_are_frozen() -> None:
    record = BirisInitRecord()
    with pytest.raises(dataclasses.FrozenInstanceError):
        record.max_range = 1  # type: ignore[misc]
    with pytest.raises(dataclasses.FrozenInstanceError):
        record.motor.gain = 1  # type: ignore[misc]


def test_motor_physical_units_at_2_mhz() -> None:
    motor = MotorParams()
    assert motor.sample_period_s == pytest.approx(1.408e-3)  # 16 * (0xAF + 1) / 2 MHz
    assert motor.max_velocity_counts_per_s == pytest.approx(2 / 1.408e-3)
    assert motor.max_velocity_counts_per_s * 360 / 4096 == pytest.approx(124.8, abs=0.1)
    assert motor.accel_counts_per_s2 == pytest.approx((0x3322 / 256) / 1.408e-3**2)


@pytest.mark.parametrize(
    ("key", "value"),
    [
        ("sample", 256),
        ("zero", -1),
        ("pole", 0x100),
        ("gain", 1000),
        ("max_vel", 128),
        ("max_accel", 0x8000),
        ("gain", 1.5),
        ("gain", True),
        ("gain", "0x3F"),
        ("gain", None),
        ("gain", np.float32(63)),
        ("max_vel", 10**400),
    ],
)
def test_motor_validation_names_the_field(key: str, value: Any) -> None:
    with pytest.raises(RequestError, match=key):
        MotorParams(**{key: value})


@pytest.mark.parametrize(
    ("key", "why"),
    [("gain", "no torque"), ("max_vel", "never leaves its start"), ("max_accel", "never speeds")],
)
def test_a_motor_that_can_never_move_is_refused_up_front(key: str, why: str) -> None:
    for zero in (0, np.int64(0)):
        with pytest.raises(RequestError, match=rf"{key}: 0 .*{why}.*can never move; use 1\.\."):
            MotorParams(**{key: zero})
    with pytest.raises(RequestError, match=f"motor.{key}: 0"):
        BirisInitRecord.from_dict({"motor": {key: 0}})
    with pytest.raises(RequestError, match=f"elevation_motor.{key}: 0"):
        BirisInitRecord.from_toml(f"[elevation_motor]\n{key} = 0\n")


def test_motor_limits_inclusive_and_numpy_ints_accepted() -> None:
    motor = MotorParams(sample=0, zero=255, pole=255, gain=255, max_vel=127, max_accel=0x7FFF)
    assert motor.max_accel == 0x7FFF
    lowest = MotorParams(sample=0, zero=0, pole=0, gain=1, max_vel=1, max_accel=1)
    assert (lowest.gain, lowest.max_vel, lowest.max_accel) == (1, 1, 1)
    from_numpy = MotorParams(gain=np.uint8(0x3F))
    assert from_numpy.gain == 0x3F and type(from_numpy.gain) is int
    assert from_numpy == MotorParams()


@pytest.mark.parametrize(
    ("key", "value"),
    [
        ("name", ""),
        ("name", "X" * 32),
        ("name", "caf\u00e9"),
        ("name", "a\x00b"),
        ("boot_file", "/" + "d" * 31),
        ("boot_file", 7),
        ("motor", (0xAF, 0x7F)),
        ("data_rate_ms", 0),
        ("data_rate_ms", 30.5),
        ("data_rate_ms", 0x8000),
        ("max_range", 0),
        ("max_range", 0x10000),
        ("timeout_s", 0.0),
        ("timeout_s", math.inf),
        ("timeout_s", math.nan),
        ("timeout_s", "4"),
        ("timeout_s", 10**400),  # finite, but no float holds it
        ("timeout_s", None),
        ("timeout_enabled", 1),
        ("timeout_enabled", "false"),
        ("timeout_enabled", None),
        ("home_index_timeout_revs", -1.0),
        ("home_index_timeout_revs", 0),
        ("home_index_timeout_revs", math.nan),
        ("home_index_timeout_revs", math.inf),
        ("home_index_timeout_revs", 2.5),  # more than a revolution either way winds the cable
        ("home_index_timeout_revs", True),
        ("continuous_acquisition", 1),
        ("elevation_limits_counts", (10, -10)),
        ("elevation_limits_counts", (0, 0x1001)),
        ("elevation_limits_counts", (0,)),
        ("elevation_limits_counts", "ab"),
        ("mount_offset_m", (0.0, 0.0)),
        ("mount_offset_m", (0.0, math.nan, 0.0)),
    ],
)
def test_record_validation_names_the_field(key: str, value: Any) -> None:
    with pytest.raises(RequestError, match=key):
        BirisInitRecord(**{key: value})


def test_record_limits_inclusive_and_sequences_normalised() -> None:
    record = BirisInitRecord(
        name="N" * 31,
        boot_file="/b",
        data_rate_ms=0x7FFF,
        max_range=0xFFFF,
        timeout_s=1,
        elevation_limits_counts=[-0x1000, 0x1000],  # type: ignore[arg-type]
        mount_offset_m=[1, 2, 3],  # type: ignore[arg-type]
    )
    assert record.elevation_limits_counts == (-0x1000, 0x1000)
    assert record.mount_offset_m == (1.0, 2.0, 3.0)
    assert isinstance(record.timeout_s, float)
    assert record == BirisInitRecord.from_dict(record.to_dict())


def test_record_numbers_of_any_real_type() -> None:
    numbers: dict[str, Any] = {  # what the record's annotations call float and int
        "timeout_s": np.float32(2.5),
        "home_index_timeout_revs": np.float64(2.0),  # the most it may be
        "head_height_m": Fraction(1, 4),
        "mount_offset_m": (np.float16(0.5), np.int64(1), Fraction(1, 4)),
        "data_rate_ms": np.int32(33),
        "elevation_limits_counts": (np.int16(-100), np.uint16(300)),
    }
    record = BirisInitRecord(**numbers)
    assert (record.timeout_s, record.home_index_timeout_revs, record.head_height_m) == (
        2.5,
        2.0,
        0.25,
    )
    assert record.mount_offset_m == (0.5, 1.0, 0.25)
    assert record.data_rate_ms == 33 and type(record.data_rate_ms) is int
    assert record.elevation_limits_counts == (-100, 300)
    for value in (*record.mount_offset_m, record.timeout_s, *record.elevation_limits_counts):
        assert type(value) in (int, float)  # plain types: TOML and the server see no numpy
    assert record == BirisInitRecord.from_dict(record.to_dict())


def test_the_biris_timeout_switch_round_trips(tmp_path: Path) -> None:
    record = BirisInitRecord(timeout_enabled=False)
    assert record.to_dict()["timeout_enabled"] is False
    assert BirisInitRecord.from_dict(record.to_dict()) == record
    assert "timeout_enabled = false" in record.to_toml()
    record.save(tmp_path / "init.toml")
    assert BirisInitRecord.load(tmp_path / "init.toml").timeout_enabled is False
    assert BirisInitRecord.from_toml("timeout_enabled = true\n") == BirisInitRecord()
    with pytest.raises(RequestError, match="timeout_enabled: must be true or false"):
        BirisInitRecord.from_toml('timeout_enabled = "off"\n')


def test_dict_round_trip_and_plain_types() -> None:
    record = BirisInitRecord(
        motor=MotorParams(gain=0x20, max_vel=4),
        data_rate_ms=50,
        continuous_acquisition=True,
        mount_offset_m=(0.1, -0.2, 0.75),
    )
    data = record.to_dict()
    assert data["motor"] == {
        "sample": 0xAF,
        "zero": 0x7F,
        "pole": 0xEF,
        "gain": 0x20,
        "max_vel": 4,
        "max_accel": 0x3322,
    }
    assert data["mount_offset_m"] == [0.1, -0.2, 0.75]
    assert BirisInitRecord.from_dict(data) == record


def test_from_dict_missing_keys_keep_defaults() -> None:
    record = BirisInitRecord.from_dict({"max_range": 3500, "motor": {"max_vel": 3}})
    assert record == BirisInitRecord(max_range=3500, motor=MotorParams(max_vel=3))


@pytest.mark.parametrize(
    ("data", "named"),
    [
        ({"bootfile": "/x"}, "bootfile"),
        ({"tasks": []}, "tasks"),
        ({"motor": {"velocity": 3}}, "velocity"),
        ({"motor": {"max_vel": 300}}, "motor.max_vel"),
        ({"motor": [1, 2]}, "motor"),
        ({"elevation_motor": {"max_vel": 300}}, "elevation_motor.max_vel"),
        ({"elevation_motor": {"speed": 1}}, "elevation_motor: unknown key 'speed'"),
        ({"elevation_motor": 3}, "elevation_motor: must be a table"),
        ({"max_range": "big"}, "max_range"),
    ],
)
def test_from_dict_rejects_unknown_keys_and_bad_values(data: dict[str, Any], named: str) -> None:
    with pytest.raises(RequestError, match=named):
        BirisInitRecord.from_dict(data)


def test_toml_round_trip(tmp_path: Path) -> None:
    record = BirisInitRecord(
        name="BIRIS2:",
        motor=MotorParams(sample=0x7F, gain=0x40, max_accel=0x0100),
        max_range=3500,
        timeout_s=2.5,
        elevation_limits_counts=(-100, 300),
        mount_offset_m=(0.2, 0.0, 1.1),
    )
    path = tmp_path / "birisinit.toml"
    record.save(path)
    text = path.read_text(encoding="utf-8")
    assert "[motor]" in text and "sample = 0x7F" in text and "max_accel = 0x0100" in text
    assert BirisInitRecord.load(path) == record
    assert BirisInitRecord.load(str(path)) == record


def test_a_tilt_tuned_apart_round_trips_and_none_is_the_pans(tmp_path: Path) -> None:
    record = BirisInitRecord(elevation_motor=MotorParams(gain=0x30, max_accel=0x1000))
    text = record.to_toml()
    assert "[elevation_motor]" in text and "max_accel = 0x1000" in text
    assert BirisInitRecord.from_toml(text) == record
    assert record.tilt_motor == MotorParams(gain=0x30, max_accel=0x1000)
    plain = BirisInitRecord()
    assert "elevation_motor" not in plain.to_toml() and "elevation_motor" not in plain.to_dict()
    assert plain.tilt_motor is plain.motor
    with pytest.raises(RequestError, match="elevation_motor: must be MotorParams or None"):
        BirisInitRecord(elevation_motor={"gain": 1})  # type: ignore[arg-type]


def test_default_toml_shows_appendix_b_in_hex() -> None:
    text = BirisInitRecord().to_toml()
    for line in ("sample = 0xAF", "zero = 0x7F", "pole = 0xEF", "gain = 0x3F", "max_vel = 0x02"):
        assert line in text
    assert "max_accel = 0x3322" in text
    assert BirisInitRecord.from_toml(text) == BirisInitRecord()


def test_hand_written_toml_with_hex_motor_table() -> None:
    text = """
name = "BIRISSERV:"
data_rate_ms = 30
max_range = 0x7FFF

[motor]
sample = 0xAF
gain = 0x30
"""
    record = BirisInitRecord.from_toml(text)
    assert record.motor == MotorParams(gain=0x30)
    assert record.max_range == 0x7FFF


def test_toml_errors_are_request_errors(tmp_path: Path) -> None:
    with pytest.raises(RequestError, match="TOML"):
        BirisInitRecord.from_toml("name = ")
    path = tmp_path / "bad.toml"
    path.write_text("data_rate_ms = 30\nspeed = 3\n[motor]\nmax_vel = 0x2\n", encoding="utf-8")
    with pytest.raises(RequestError, match="speed") as info:
        BirisInitRecord.load(path)
    assert str(path) in str(info.value)
    with pytest.raises(FileNotFoundError):
        BirisInitRecord.load(tmp_path / "missing.toml")


def test_saving_without_tomli_w_names_the_extra(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setitem(sys.modules, "tomli_w", None)  # makes `import tomli_w` fail
    with pytest.raises(ImportError, match=r"biris-hw\[toml\]"):
        BirisInitRecord().save(tmp_path / "x.toml")
    assert not (tmp_path / "x.toml").exists()


def test_get_acq_rate_for_the_defaults() -> None:
    # 2 counts per 1.408 ms sample, 30 ms per acquisition.
    rate = acq_rate_counts_per_acq(BirisInitRecord())
    assert rate == pytest.approx(2 / 1.408e-3 * 0.030)
    assert rate == pytest.approx(42.61, abs=0.01)


@pytest.mark.parametrize(
    ("scan_counts", "expected"),
    [
        (0, 0),
        (1, 1),
        (-1, 1),
        (42, 1),  # under one acquisition's travel: still one
        (43, 2),
        (1024, 25),  # 90 degrees: 24.03 -> 25, ends as the motor arrives
        (-1024, 25),
        (2048, 49),  # 48.06
        (8192, 193),  # the full +-360 degree sweep: 192.2
    ],
)
def test_acquisitions_for_defaults(scan_counts: int, expected: int) -> None:
    assert acquisitions_for(scan_counts, BirisInitRecord()) == expected


def test_acquisitions_for_exact_multiple_does_not_round_up() -> None:
    # sample 0x7C: 1 ms; max_vel 2: 2000 counts/s; 30 ms: exactly 60 counts per acquisition.
    record = BirisInitRecord(motor=MotorParams(sample=0x7C, max_vel=2))
    assert acq_rate_counts_per_acq(record) == pytest.approx(60.0)
    assert acquisitions_for(600, record) == 10
    assert acquisitions_for(601, record) == 11


@given(
    scan=st.integers(min_value=1, max_value=0x2000),
    sample=st.integers(min_value=0, max_value=255),
    max_vel=st.integers(min_value=1, max_value=127),
    rate_ms=st.integers(min_value=1, max_value=200),
)
def test_acquisitions_cover_the_scan(scan: int, sample: int, max_vel: int, rate_ms: int) -> None:
    record = BirisInitRecord(
        motor=MotorParams(sample=sample, max_vel=max_vel), data_rate_ms=rate_ms
    )
    n = acquisitions_for(scan, record)
    rate = acq_rate_counts_per_acq(record)
    assert n >= 1
    assert n * rate >= scan * (1 - 1e-12)  # enough acquisitions to last the whole move
    assert n == 1 or (n - 1) * rate < scan * (1 + 1e-12)  # and not one more than that


def test_acquisitions_for_the_slowest_motor_there_can_be() -> None:
    # max_vel 0 cannot be asked for any more (MotorParams refuses it), so 1 is the slowest.
    record = BirisInitRecord(motor=MotorParams(max_vel=1))
    assert acquisitions_for(0, record) == 0
    assert acquisitions_for(100, record) == 5  # 21.3 counts per acquisition


def test_acquisitions_for_rejects_non_integers() -> None:
    with pytest.raises(RequestError, match="scan_counts"):
        acquisitions_for(10.5, BirisInitRecord())  # type: ignore[arg-type]

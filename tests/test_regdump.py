"""``biris regdump``: decoding a known target image, every source, change marking, errors."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import pytest

from biris_hw import regdump
from biris_hw.bus import open_window
from biris_hw.bus.memory import MemoryWindow
from biris_hw.bus.shm import SharedMemoryWindow
from biris_hw.cli import main
from biris_hw.errors import BusError
from biris_hw.hardware import BirisHardware
from biris_hw.irq.eventfd import EventFdLine
from regs.biexec import BiCommand, BiexecCom, encode_param
from regs.bit3 import Bit3Reg
from regs.hctl1000 import Reg
from regs.layout import BirisMemoryMap, TargetImage
from regs.tech80 import Axis, BoardReg, axis_register

IMAGE = TargetImage()
MM = IMAGE.biris


# -- the test image ---------------------------------------------------------------------------


def _frame(closest: int, samples: list[int]) -> bytes:
    return struct.pack(f">{len(samples) + 1}h", closest, *samples)


def _hctl(img: bytearray, axis: Axis, reg: int, value: int) -> None:
    img[IMAGE.motion_offset + axis_register(axis, reg)] = value


def build_image() -> bytearray:
    """A target in the middle of an acquisition: ACQ_LINE 5, frames 0..4 complete, 5 poisoned."""
    img = bytearray(IMAGE.size)
    com = BiexecCom.from_buffer(img, IMAGE.biris_offset + MM.biexec_offset)
    com.COMMAND = BiCommand.BI_ACQUIRE
    com.STATUS = 0
    com.ACQ_LINE = 5
    com.PARAM = encode_param("12")
    com.CURRENT_FRAME = 5
    com.CURRENT_PROJ = 17
    com._Biris_cmd_int_enable = 1
    com._Biris_data_int_enable = 1
    com._Biris_motor_access = 0
    del com  # release the buffer export
    n = MM.samples
    biris = IMAGE.biris_offset
    for k in range(5):
        samples = [1500 + 100 * k + 10 * i for i in range(1, n + 1)]
        samples[:4] = [0, 0, 0, 0]  # four samples without a return
        frame = _frame(min(s for s in samples if s), samples)
        at = biris + MM.addressing.range_frame(k)
        img[at : at + len(frame)] = frame
        inten = MM.addressing.intensity_frame(k)
        img[biris + inten : biris + inten + len(frame)] = _frame(77, [77] * n)
    poison = _frame(0x7A7A, [0x7A7A] * n)
    at = biris + MM.addressing.range_frame(5)
    img[at : at + len(poison)] = poison

    az = Axis.AZIMUTH
    for reg, value in [
        (Reg.FLAG, 0xAB),  # write-only: must not be shown
        (Reg.STATUS, 0xD0),  # LIMIT/STOP clear, profile running
        (Reg.MOTOR_COMMAND, 0x90),
        (Reg.CMD_POS_MSB, 0x00),
        (Reg.CMD_POS_MID, 0x03),
        (Reg.CMD_POS_LSB, 0xE8),  # 1000
        (Reg.SAMPLE_TIMER, 0xAF),
        (Reg.ACT_POS_MSB, 0x00),
        (Reg.ACT_POS_MID, 0x04),
        (Reg.ACT_POS_LSB, 0x00),  # 1024 = +90 degrees
        (Reg.FILTER_ZERO, 0x7F),
        (Reg.FILTER_POLE, 0xEF),
        (Reg.FILTER_GAIN, 0x3F),
        (Reg.ACCEL_LSB, 0x22),
        (Reg.ACCEL_MSB, 0x33),
        (Reg.MAX_VELOCITY, 0x02),
        (Reg.FINAL_POS_LSB, 0x00),
        (Reg.FINAL_POS_MID, 0xF8),
        (Reg.FINAL_POS_MSB, 0xFF),  # -2048 = -180 degrees
    ]:
        _hctl(img, az, reg, value)
    el = Axis.ELEVATION
    for reg, value in [
        (Reg.STATUS, 0xE0),  # init/idle
        (Reg.SAMPLE_TIMER, 0xAF),
        (Reg.ACT_POS_MSB, 0xFF),
        (Reg.ACT_POS_MID, 0xFF),
        (Reg.ACT_POS_LSB, 0xFF),  # -1
    ]:
        _hctl(img, el, reg, value)
    motion = IMAGE.motion_offset
    img[motion + BoardReg.IRQ_VECTOR] = 0x70
    img[motion + BoardReg.IRQ_ENABLE] = 0x01
    img[motion + BoardReg.IRQ_STATUS] = 0x01
    img[motion + BoardReg.CHIP_RESET] = 0x5A
    img[motion + BoardReg.IRQ_LEVEL] = 0x03
    coupler = IMAGE.coupler_offset
    img[coupler + Bit3Reg.LOCAL_STATUS] = 0x90  # parity error, card ready
    img[coupler + Bit3Reg.LOCAL_INT_STATUS] = 0x04  # remote IRQ2
    img[coupler + Bit3Reg.LEVEL2_VECTOR] = 0x40
    return img


@pytest.fixture
def image_file(tmp_path: Path) -> Path:
    path = tmp_path / "target.img"
    path.write_bytes(build_image())
    return path


def _lines(text: str) -> dict[str, str]:
    """Table rows by name (first word after the change mark), last one wins."""
    rows = {}
    for line in text.splitlines():
        parts = line[2:].split()
        if line[:2] in ("  ", "* ") and parts:
            rows[parts[0]] = line
    return rows


# -- the table ------------------------------------------------------------------------------------


def test_table_decodes_every_area(image_file: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["regdump", "--file", str(image_file)]) == 0
    out = capsys.readouterr().out
    for heading in (
        "BIEXEC_COM",
        "Frames",
        "HCTL-1000 axis 0 (azimuth)",
        "HCTL-1000 axis 1 (elevation)",
        "Model 7600 board",
        "Bit 3 Model 412",
    ):
        assert heading in out
    assert "5 (BI_ACQUIRE)" in out
    assert '"12"' in out
    assert "4 (ACQ_LINE - 1)" in out
    assert "range(4): closest 1950 mm; 60/64 valid, 1950..2540 mm" in out
    assert "range(5): 0x7A7A everywhere" in out
    assert "1024 counts (+90.00 deg)" in out
    assert "-2048 counts (-180.00 deg)" in out
    assert "-1 counts (-0.09 deg)" in out
    assert "0xAF (1.408 ms)" in out
    assert "0x3322 (51.1328 counts/sample^2)" in out
    assert "2 counts/sample = 124.8 deg/s at 1.408 ms" in out
    assert "trapezoidal profile running" in out
    assert "init/idle" in out
    assert "PARITY_ERROR" in out
    assert "0x04 [IRQ 2]" in out
    assert "0xAB" not in out and "0x5A" not in out  # write-only registers are not shown


def test_table_columns_are_aligned(image_file: Path, capsys: pytest.CaptureFixture[str]) -> None:
    main(["regdump", "--file", str(image_file)])
    out = capsys.readouterr().out
    headers = [line for line in out.splitlines() if line.split()[:3] == ["name", "offset", "raw"]]
    assert len(headers) == 6 and len(set(headers)) == 1  # one column layout for every section
    off_col, raw_col = headers[0].index("offset"), headers[0].index("raw")
    rows = _lines(out)
    for name in ("COMMAND", "ACT_POS_LSB", "IRQ_VECTOR", "LEVEL2_VECTOR", "last_frame"):
        line = rows[name]
        assert line[off_col : off_col + 2] == "0x" and line[off_col - 2 : off_col] == "  "
    assert rows["IRQ_VECTOR"][raw_col:].split()[0] == "0x70"
    status = rows["STATUS"]  # the last STATUS row: the elevation chip's
    assert status.split()[1:3] == ["0x0047", "0xE0"]
    assert rows["FLAG"].split()[1:] == ["0x0040", "(write-only)"]
    assert rows["REMOTE_IACK"].endswith("(not read: reading it has side effects)")


def test_write_only_and_side_effect_registers_are_never_read() -> None:
    reads: list[int] = []

    class Recording(MemoryWindow):
        def read8(self, offset: int) -> int:
            reads.append(offset)
            return super().read8(offset)

        def read16(self, offset: int) -> int:
            reads.append(offset)
            return super().read16(offset)

        def write8(self, offset: int, value: int) -> None:  # pragma: no cover - must not happen
            raise AssertionError("a dump wrote to the target")

    img = build_image()
    dump = regdump.snapshot(Recording(len(img), buffer=img), IMAGE)
    motion = IMAGE.motion_offset
    for axis in Axis:
        for reg in (Reg.FLAG, Reg.PROGRAM_COUNTER, Reg.PRESET_MSB, Reg.PRESET_MID, Reg.PRESET_LSB):
            assert motion + axis_register(axis, reg) not in reads
        lsb, mid, msb = (
            reads.index(motion + axis_register(axis, r))
            for r in (Reg.ACT_POS_LSB, Reg.ACT_POS_MID, Reg.ACT_POS_MSB)
        )
        assert lsb < mid < msb and mid == lsb + 1 and msb == mid + 1  # R14H latches first
    assert len(reads) == len(set(reads))  # every register is read once
    assert motion + BoardReg.CHIP_RESET not in reads
    assert IMAGE.coupler_offset + Bit3Reg.REMOTE_IACK not in reads
    assert dump.section("coupler").row("REMOTE_IACK").raw is None


# -- JSON -----------------------------------------------------------------------------------------


def test_json_has_the_numbers(image_file: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["regdump", "--file", str(image_file), "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["layout"] == {
        "coupler": 0,
        "motion": 0x100,
        "biris": 0x1000,
        "biris_base": 0xC0_0000,
        "biexec_offset": 0x100,
        "range_base": 0x1000,
        "frame_size": 132,
        "samples": 64,
    }
    biexec = data["biexec"]
    assert biexec["registers"]["COMMAND"]["raw"] == int(BiCommand.BI_ACQUIRE)
    assert biexec["registers"]["ACQ_LINE"]["value"] == 5
    assert biexec["registers"]["ACQ_LINE"]["offset"] == 4
    assert biexec["PARAM"] == {"text": "12", "hex": "3132"}
    frames = data["frames"]
    assert frames["acq_line"] == 5
    assert frames["last_complete"] == 4
    last = frames["last_frame"]
    assert last["index"] == 4
    assert last["offset"] == 0x1000 + 8 * 132
    assert last["address"] == 0xC0_0000 + 0x1000 + 8 * 132
    assert (last["closest_mm"], last["valid"], last["min_mm"], last["max_mm"]) == (
        1950,
        60,
        1950,
        2540,
    )
    assert last["poisoned"] is False
    assert frames["exposing"]["index"] == 5 and frames["exposing"]["poisoned"] is True
    az = data["hctl_azimuth"]
    assert az["actual_position"] == {"counts": 1024, "deg": 90.0}
    assert az["command_position"] == {"counts": 1000, "deg": pytest.approx(87.890625)}
    assert az["final_position"] == {"counts": -2048, "deg": -180.0}
    assert az["acceleration"] == {"value": 0x3322}
    assert az["filter"] == {"A": 0x7F, "B": 0xEF, "K": 0x3F}
    assert az["max_velocity"]["counts_per_sample"] == 2
    assert az["mode"] == "trapezoid"
    assert az["flags"] == {"F0": True, "F1": False}
    assert az["stop_limit"] == {"stop": False, "limit": False}
    assert az["registers"]["ACT_POS_LSB"]["offset"] == 0x14
    assert az["registers"]["FLAG"]["raw"] is None
    assert az["registers"]["FLAG"]["decoded"] == "(write-only)"
    el = data["hctl_elevation"]
    assert el["actual_position"] == {"counts": -1, "deg": pytest.approx(-360 / 4096)}
    assert el["mode"] == "init/idle"
    assert el["registers"]["ACT_POS_LSB"]["offset"] == 0x54
    assert data["board"]["registers"]["IRQ_VECTOR"]["raw"] == 0x70
    assert data["board"]["registers"]["CHIP_RESET"]["raw"] is None
    assert data["coupler"]["errors"] == ["PARITY_ERROR"]
    assert data["coupler"]["connected"] is True
    assert data["changed"] == [] and data["dump"] == 1


def test_param_that_is_not_text_is_shown_in_hex(tmp_path: Path) -> None:
    img = build_image()
    at = IMAGE.biris_offset + MM.biexec_offset + BiexecCom.PARAM.offset
    img[at : at + 64] = b"\xff" * 64  # no NUL, not ASCII
    dump = regdump.snapshot(MemoryWindow(len(img), buffer=img), IMAGE)
    row = dump.section("biexec").row("PARAM")
    assert row.value == {"text": None, "hex": "ff" * 64}
    assert row.decoded.startswith("not NUL-terminated ASCII: FF FF")


@pytest.mark.parametrize(
    ("acq_line", "current", "expected"),
    [(5, 9, 4), (1, 9, 0), (0, 9, None), (-1, 9, None), (-128, 9, 9), (-128, -1, None)],
)
def test_last_complete_frame(acq_line: int, current: int, expected: int | None) -> None:
    assert regdump.last_complete_frame(acq_line, current) == expected


def test_sequence_end_uses_current_frame() -> None:
    img = build_image()
    com = BiexecCom.from_buffer(img, IMAGE.biris_offset + MM.biexec_offset)
    com.ACQ_LINE = -128
    com.CURRENT_FRAME = 3
    del com
    frames = regdump.to_json(regdump.snapshot(MemoryWindow(len(img), buffer=img)))["frames"]
    assert frames["last_complete"] == 3
    assert frames["last_frame"]["closest_mm"] == 1850
    assert frames["exposing"] is None


def test_summarize_frame_of_empty_frame() -> None:
    summary = regdump.summarize_frame(bytes(2 * 65))
    assert summary.valid == 0 and summary.min_mm is None and summary.max_mm is None
    assert not summary.poisoned
    assert summary.text() == "closest 0 mm; 0/64 valid, none valid"


# -- watching -------------------------------------------------------------------------------------


def test_changed_rows_marks_only_what_changed() -> None:
    img = build_image()
    first = regdump.snapshot(MemoryWindow(len(img), buffer=bytearray(img)))
    img[IMAGE.motion_offset + Reg.ACT_POS_LSB] = 0x10  # azimuth 1024 -> 1040
    second = regdump.snapshot(MemoryWindow(len(img), buffer=img))
    changed = regdump.changed_rows(first, second)
    assert changed == {("hctl_azimuth", "ACT_POS_LSB"), ("hctl_azimuth", "actual_position")}
    assert regdump.changed_rows(None, second) == frozenset()
    table = regdump.format_table(second, changed)
    marked = [line.split()[1] for line in table.splitlines() if line.startswith("* ")]
    assert marked == ["ACT_POS_LSB", "actual_position"]


def test_watch_marks_a_change_between_dumps(
    image_file: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    pauses: list[float] = []

    def rewrite_file(seconds: float) -> None:
        pauses.append(seconds)
        img = bytearray(image_file.read_bytes())
        img[IMAGE.motion_offset + Reg.STATUS] = 0xE0  # azimuth back to init/idle
        image_file.write_bytes(img)

    monkeypatch.setattr(regdump, "_sleep", rewrite_file)
    assert main(["regdump", "--file", str(image_file), "--watch", "1", "--count", "2"]) == 0
    out = capsys.readouterr().out
    first, second = out.split("=== dump 2: ")
    assert first.startswith("=== dump 1: 0 changed ===")
    assert "* " not in first
    assert second.startswith("3 changed ===")
    marked = {line.split()[1] for line in second.splitlines() if line.startswith("* ")}
    assert marked == {"STATUS", "flags", "mode"}
    assert pauses == [0.001]


def test_watch_json_is_one_object_per_line(
    image_file: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(regdump, "_sleep", lambda s: None)
    args = ["regdump", "--file", str(image_file), "--json", "--watch", "5", "--count", "3"]
    assert main(args) == 0
    lines = capsys.readouterr().out.splitlines()
    assert [json.loads(line)["dump"] for line in lines] == [1, 2, 3]


def test_ctrl_c_ends_quietly(
    image_file: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    def interrupt(seconds: float) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(regdump, "_sleep", interrupt)
    assert main(["regdump", "--file", str(image_file), "--watch", "10"]) == 0
    captured = capsys.readouterr()
    assert captured.out.count("=== dump") == 1
    assert captured.err == ""


# -- layout options -------------------------------------------------------------------------------


def test_region_offsets_can_be_moved(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    moved = TargetImage(coupler_offset=0x200, motion_offset=0x0, biris_offset=0x2000)
    src = build_image()
    img = bytearray(moved.size)
    for old, new in zip(IMAGE.regions(), moved.regions(), strict=True):
        img[new.offset : new.end] = src[old.offset : old.end]
    path = tmp_path / "moved.img"
    path.write_bytes(img)
    args = ["--coupler-at", "0x200", "--motion-at", "0", "--biris-at", "0x2000", "--json"]
    assert main(["regdump", "--file", str(path), *args]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["layout"]["biris"] == 0x2000
    assert data["hctl_azimuth"]["actual_position"]["counts"] == 1024
    assert data["frames"]["last_complete"] == 4
    assert data["coupler"]["errors"] == ["PARITY_ERROR"]


def test_frame_size_and_range_base_override(
    image_file: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # a frame size of 66 bytes puts range(4) at base + 8*66: a different, empty place
    args = ["--frame-size", "132", "--range-base", "0x1000", "--json"]
    assert main(["regdump", "--file", str(image_file), *args]) == 0
    assert json.loads(capsys.readouterr().out)["frames"]["last_frame"]["closest_mm"] == 1950
    args = ["--frame-size", "264", "--json"]  # range(2) of 264-byte frames is range(4) of 132
    assert main(["regdump", "--file", str(image_file), *args]) == 0
    last = json.loads(capsys.readouterr().out)["frames"]["last_frame"]
    assert last["offset"] == 0x1000 + 8 * 264


def test_samples_128_reads_longer_frames(
    image_file: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["regdump", "--file", str(image_file), "--samples", "128", "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["layout"]["frame_size"] == 260
    assert data["frames"]["last_frame"]["samples"] == 128


# -- errors ---------------------------------------------------------------------------------------


def _error(capsys: pytest.CaptureFixture[str], *argv: str) -> str:
    assert main(list(argv)) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    lines = captured.err.splitlines()
    assert len(lines) == 1, captured.err
    assert lines[0].startswith("biris regdump: ")
    return lines[0]


def test_missing_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    line = _error(capsys, "regdump", "--file", str(tmp_path / "nope.img"))
    assert "no such file" in line


def test_short_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "short.img"
    path.write_bytes(build_image()[:0x2000])
    line = _error(capsys, "regdump", "--file", str(path))
    assert "too short" in line and "0x85000" in line


@pytest.mark.parametrize(
    ("args", "words"),
    [
        (["--offset", "zz"], "not an offset"),
        (["--offset", "-4"], "negative"),
        (["--offset", "0x10"], "too short"),
        (["--biexec-offset", "0x101"], "biexec_offset"),
        (["--biexec-offset", "0x1000"], "overlaps"),
        (["--motion-at", "0x10"], "overlaps"),
        (["--biris-at", "0x1002"], "multiple of 4"),
        (["--frame-size", "100"], "frame size"),
        (["--samples", "96"], "invalid choice"),
        (["--count", "2"], "--count needs --watch"),
    ],
)
def test_bad_options(
    image_file: Path, capsys: pytest.CaptureFixture[str], args: list[str], words: str
) -> None:
    assert words in _error(capsys, "regdump", "--file", str(image_file), *args)


def test_debug_shows_the_traceback(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--debug", "regdump", "--file", str(tmp_path / "nope.img")]) == 2
    err = capsys.readouterr().err
    assert "Traceback" in err and err.rstrip().splitlines()[-1].startswith("biris regdump: ")
    assert main(["regdump", "--debug", "--file", str(tmp_path / "nope.img")]) == 2
    assert "Traceback" in capsys.readouterr().err


def test_window_too_small_for_the_image() -> None:
    with pytest.raises(regdump.DumpError, match="needs 0x85000"):
        regdump.snapshot(MemoryWindow(0x1000))


def test_region_refuses_reads_outside_it() -> None:
    region = regdump.Region(MemoryWindow(0x100), 0x40, 0x10)
    with pytest.raises(BusError):
        region.read8(0x10)
    with pytest.raises(BusError):
        region.read16(-2)


def test_frame_outside_the_window_is_reported_not_raised() -> None:
    img = build_image()
    com = BiexecCom.from_buffer(img, IMAGE.biris_offset + MM.biexec_offset)
    com.ACQ_LINE = 30000
    del com
    frames = regdump.snapshot(MemoryWindow(len(img), buffer=img)).section("frames")
    assert frames.row("last_frame").decoded == "range(29999) is outside the BIRIS window"


# -- other sources --------------------------------------------------------------------------------


def test_snapshot_hardware_reads_three_windows() -> None:
    img = build_image()
    parts = [open_window("memory", size=r.size) for r in IMAGE.regions()]
    for window, region in zip(parts, IMAGE.regions(), strict=True):
        window.write(0, img[region.offset : region.end])
    coupler, motion, biris = parts
    hw = BirisHardware(
        biris=biris,
        motion=motion,
        coupler=coupler,
        level2=EventFdLine(),
        level3=EventFdLine(),
        biexec_offset=MM.biexec_offset,
        biris_base=MM.biris_base,
        clock=lambda: 0.0,
    )
    try:
        dump = regdump.snapshot_hardware(hw)
    finally:
        hw.close()
    data = regdump.to_json(dump)
    assert data["source"] == "hardware bundle"
    assert data["layout"]["biris"] == 0 and data["biexec"]["base"] == MM.biexec_offset
    assert data["frames"]["last_complete"] == 4
    assert data["hctl_azimuth"]["actual_position"]["counts"] == 1024
    assert data["coupler"]["registers"]["LEVEL2_VECTOR"]["raw"] == 0x40


def test_mmap_source_at_an_offset(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    offset = 0x3000 + 0x24  # not page aligned: the window handles alignment
    path = tmp_path / "big.img"
    path.write_bytes(b"\xee" * offset + build_image() + b"\xee" * 0x1000)
    assert main(["regdump", "--mmap", str(path), "--offset", hex(offset), "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["source"] == f"mmap {path} at 0x{offset:X}"
    assert data["frames"]["last_complete"] == 4
    assert data["hctl_azimuth"]["actual_position"] == {"counts": 1024, "deg": 90.0}


def test_mmap_short_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "img"
    path.write_bytes(build_image())
    assert "too short" in _error(capsys, "regdump", "--mmap", str(path), "--offset", "0x1000")


def test_shm_source(capsys: pytest.CaptureFixture[str]) -> None:
    img = build_image()
    # The owner is a window too, as in the simulator: the shm window keeps the tracker straight.
    with SharedMemoryWindow(size=len(img), create=True) as owner:
        owner.write(0, img)
        name = owner.name
        assert main(["regdump", "--shm", name, "--json"]) == 0
        data = json.loads(capsys.readouterr().out)
        assert data["source"] == f"shm {name}"
        assert data["frames"]["last_complete"] == 4
        assert data["hctl_elevation"]["actual_position"]["counts"] == -1
        owner.write(IMAGE.motion_offset + Reg.ACT_POS_LSB, b"\x10")
        assert main(["regdump", "--shm", name, "--json"]) == 0
        data = json.loads(capsys.readouterr().out)
        assert data["hctl_azimuth"]["actual_position"]["counts"] == 1040


def test_missing_shm_segment(capsys: pytest.CaptureFixture[str]) -> None:
    line = _error(capsys, "regdump", "--shm", "biris-regdump-test-no-such-segment")
    assert line == "biris regdump: no shared memory segment 'biris-regdump-test-no-such-segment'"


def test_default_map_matches_image() -> None:
    assert IMAGE.biris == BirisMemoryMap()

"""Issue 21's scan invariants (biris_hw.scancheck), and the two Scan fields that say what a scan
covers (partial_reason, span), carried losslessly by the wire codec and scan files, old payloads
and old files included."""

from __future__ import annotations

import pickle
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from biris_hw.data import Direction, Scan
from biris_hw.io import codec
from biris_hw.io.scanfile import FORMAT_VERSION, load_scans, save_scans
from biris_hw.scancheck import ScanChecker, check_scan, coverage_shortfall

SAMPLES = 8


def _scan(
    azimuth: list[int] | None = None,
    direction: Direction = Direction.CCW,
    seq: int = 1,
    *,
    seed: int = 0,
    **fields: Any,
) -> Scan:
    """A plausible sweep: azimuths as given (default 0..400 by 40s), t 1/30 s apart, ranges with
    noise (so that no two rows of two scans agree by chance, as on the simulator)."""
    az = np.array(list(range(0, 401, 40)) if azimuth is None else azimuth, dtype=np.int32)
    n = az.size
    rng = np.random.default_rng(seed)
    ranges = rng.integers(1500, 2500, (n, SAMPLES)).astype(np.int16)
    values: dict[str, Any] = {
        "direction": direction,
        "seq": seq,
        "azimuth": az,
        "range_mm": ranges,
        "closest_mm": ranges.min(axis=1) if n else np.zeros(0, np.int16),
        "intensity": (ranges // 2).astype(np.int16),
        "t": 10.0 + np.arange(n) / 30.0,
    }
    values.update(fields)
    return Scan(**values)


# -- the Scan fields ---------------------------------------------------------------------------


def test_scan_fields_default_to_unknown_and_are_checked() -> None:
    scan = _scan()
    assert scan.partial_reason == "" and scan.span is None  # old constructors keep working
    given = _scan(partial=True, partial_reason="ended short", span=(np.int64(0), np.int32(400)))
    assert given.span == (0, 400) and all(type(end) is int for end in given.span)
    assert _scan(span=[0, 400]).span == (0, 400)
    for bad in (
        {"partial_reason": "ended short"},  # a reason on a whole scan contradicts it
        {"partial": True, "partial_reason": None},
        {"partial": True, "partial_reason": b"bytes"},
        {"span": (0,)},
        {"span": (0, 1, 2)},
        {"span": (0.0, 400)},
        {"span": (True, 400)},
        {"span": "0,400"},
        {"span": 400},
    ):
        with pytest.raises(ValueError):
            _scan(**bad)
    copy = pickle.loads(pickle.dumps(given))
    assert (copy.partial, copy.partial_reason, copy.span) == (True, "ended short", (0, 400))


# -- coverage_shortfall --------------------------------------------------------------------------


def _az(*values: int) -> np.ndarray:
    return np.array(values, dtype=np.int32)


def test_coverage_allows_one_acquisitions_travel_and_settling_at_each_end() -> None:
    # steps of 40: the first may lie 40 + 2 past the start, the last 42 short of the end
    assert coverage_shortfall(_az(42, 80, 120, 160, 198), 0, 240) is None
    assert coverage_shortfall(_az(43, 80, 120, 160), 0, 202) == (
        "began 43 counts (3.8 deg) after its start 0"
    )
    assert coverage_shortfall(_az(0, 40, 80, 120), 0, 163) == (
        "ended 43 counts (3.8 deg) short of its destination 163"
    )
    # the largest step sets the travel: one long step makes both ends more forgiving
    assert coverage_shortfall(_az(60, 80, 200), 0, 300) is None


def test_coverage_names_what_is_missing() -> None:
    assert coverage_shortfall(_az(), 0, 2048) == "no acquisition"
    assert coverage_shortfall(_az(5), 0, 2048) == "only one acquisition (at 5)"
    short = coverage_shortfall(_az(*range(8, 1737, 24)), 0, 2048)
    assert short == "ended 312 counts (27.4 deg) short of its destination 2048"
    late_and_short = coverage_shortfall(_az(150, 160, 170), 0, 400)
    assert late_and_short == (
        "began 150 counts (13.2 deg) after its start 0; "
        "ended 230 counts (20.2 deg) short of its destination 400"
    )
    # clockwise: "after" and "short" along the way the sweep goes
    assert coverage_shortfall(_az(-100, -140, -180), 0, -400) == (
        "began 100 counts (8.8 deg) after its start 0; "
        "ended 220 counts (19.3 deg) short of its destination -400"
    )
    # rows from the wrong side of either end
    assert coverage_shortfall(_az(*range(-300, 101, 20)), 0, 100) == (
        "began 300 counts (26.4 deg) before its start 0"
    )
    assert coverage_shortfall(_az(*range(0, 401, 20)), 0, 100) == (
        "ended 300 counts (26.4 deg) beyond its destination 100"
    )
    # a move to where it stands: both ends there
    assert coverage_shortfall(_az(10, 11), 10, 10) is None
    assert coverage_shortfall(_az(*range(10, 41, 2)), 10, 10) == (
        "ended 30 counts (2.6 deg) away from its destination 10"
    )


# -- check_scan ----------------------------------------------------------------------------------


def test_a_good_scan_breaks_no_rule() -> None:
    assert check_scan(_scan()) == []
    assert check_scan(_scan(span=(0, 400))) == []
    cw = _scan(list(range(400, -1, -40)), Direction.CW, span=(400, 0))
    assert check_scan(cw, expect_returns=True) == []
    # the first sweep of a continuous scan: partial, its reason given, whole within its span
    first = _scan(span=(0, 400), partial=True, partial_reason="first sweep, from 0")
    assert check_scan(first) == []
    # standing at the end: a count or two of jitter back is not a wrong direction
    assert check_scan(_scan([0, 40, 80, 82, 80, 81])) == []


def test_time_must_increase() -> None:
    t = 10.0 + np.arange(11) / 30.0
    t[6] = t[5]
    (violation,) = check_scan(_scan(t=t))
    assert violation.startswith("CCW #1: row 6: t 10.166667 s is not after row 5's 10.166667 s")
    t[8] = np.nan
    (violation,) = check_scan(_scan(t=t, seq=4))
    assert violation.startswith("CCW #4: row 6:") and violation.endswith("(and 2 more rows)")


def test_azimuths_must_go_the_scans_way() -> None:
    (violation,) = check_scan(_scan([0, 40, 80, 77, 120]))
    assert violation == (
        "CCW #1: row 3: azimuth 77 is 3 counts back from 80, against the scan's direction (CCW)"
    )
    # a clockwise scan whose azimuths climb
    (violation,) = check_scan(_scan([0, 40, 80], Direction.CW, seq=2))
    assert violation.startswith("CW #2: row 1: azimuth 40 is 40 counts back from 0")
    assert violation.endswith("(CW) (and 1 more row)")
    # small steps back that add up are caught against the furthest reached, not the last row
    assert check_scan(_scan([0, 40, 80, 78, 76, 74]))[0].startswith("CCW #1: row 4:")


def test_a_whole_scan_covers_its_span() -> None:
    short = _scan(list(range(8, 1737, 24)), span=(0, 2048))
    (violation,) = check_scan(short)
    assert violation == (
        "CCW #1: not marked partial, yet it ended 312 counts (27.4 deg) short of its "
        "destination 2048 (span 0 -> 2048)"
    )
    # the same data marked partial with its reason is what the server must deliver
    said = _scan(
        list(range(8, 1737, 24)),
        span=(0, 2048),
        partial=True,
        partial_reason="ended 312 counts (27.4 deg) short of its destination 2048",
    )
    assert check_scan(said) == []
    # coverage is judged only where the span is known (data from before the field)
    assert check_scan(_scan(list(range(8, 1737, 24)))) == []


def test_partial_scans_say_why_and_empty_ones_are_partial() -> None:
    (violation,) = check_scan(_scan(span=(0, 400), partial=True))
    assert violation == "CCW #1: partial without a reason (partial_reason is empty)"
    assert check_scan(_scan(partial=True)) == []  # old data: no span, no reason to ask for
    empty = _scan([], seq=3, dropped=12)
    assert check_scan(empty) == ["CCW #3: holds no acquisition, yet is not marked partial"]
    assert check_scan(_scan([], partial=True, partial_reason="no acquisition")) == []
    (violation,) = check_scan(_scan([], span=(0, 400), partial=True))
    assert "partial without a reason" in violation


def test_a_span_runs_the_scans_way() -> None:
    (violation,) = check_scan(_scan(span=(400, 0), partial=True, partial_reason="cut"))
    assert violation == "CCW #1: its span 400 -> 0 runs CW, the scan CCW"


def test_all_zero_rows_only_where_returns_are_expected() -> None:
    scan = _scan()
    ranges, intensity, closest = scan.range_mm.copy(), scan.intensity.copy(), scan.closest_mm.copy()
    for array in (ranges, intensity, closest):
        array[4] = 0
    silent = _scan(range_mm=ranges, intensity=intensity, closest_mm=closest)
    assert check_scan(silent) == []  # a real acquisition that saw nothing looks like this
    (violation,) = check_scan(silent, expect_returns=True)
    assert violation.startswith("CCW #1: row 4 (azimuth 160) is all zero")
    intensity[4] = 7  # anything written there: not a frame BIRIS never wrote
    assert (
        check_scan(
            _scan(range_mm=ranges, intensity=intensity, closest_mm=closest), expect_returns=True
        )
        == []
    )


def test_made_up_rows_are_judged_on_bookkeeping_only() -> None:
    """A test's fake BIRIS feeds the server made-up rows: physical=False judges only what the
    server decides about them (empty means partial, partial says why, the span's way)."""
    fake = _scan([0, 40, 80], Direction.CW, t=np.zeros(3), span=(0, -400))
    assert len(check_scan(fake)) == 3  # time, direction, coverage
    assert check_scan(fake, physical=False) == []
    assert ScanChecker(physical=False).extend([fake, fake]) == []  # made-up rows repeat
    assert check_scan(_scan([], seq=2), physical=False) == [
        "CCW #2: holds no acquisition, yet is not marked partial"
    ]
    wrong_way = _scan(span=(400, 0), partial=True)
    assert len(check_scan(wrong_way, physical=False)) == 2  # the span's way, no reason


# -- ScanChecker ---------------------------------------------------------------------------------


def test_a_row_in_two_scans_is_caught_and_named() -> None:
    checker = ScanChecker()
    first = _scan(seed=1)
    assert checker.add(first) == [] and checker.add(_scan(seed=2, seq=2)) == []
    # a CW sweep whose row 3 is CCW #1's row 7, read again (stamped afresh: t differs)
    back = _scan(list(range(400, -1, -40)), Direction.CW, seq=1, seed=3)
    ranges, intensity = back.range_mm.copy(), back.intensity.copy()
    azimuth = back.azimuth.copy()
    ranges[3], intensity[3], azimuth[3] = first.range_mm[7], first.intensity[7], 280
    mixed = _scan(list(azimuth), Direction.CW, seq=1, range_mm=ranges, intensity=intensity)
    (violation,) = checker.add(mixed)
    assert violation == (
        "CW #1: row 3 (azimuth 280) repeats CCW #1 row 7 (scan 1 of the stream): one "
        "acquisition delivered twice"
    )
    assert checker.violations == [violation] and (checker.scans, checker.bad_scans) == (3, 1)
    assert checker.summary() == "1 violation in 1 scan (of 3 checked)"


def test_a_row_twice_in_one_scan_is_caught() -> None:
    scan = _scan(seed=4)
    ranges, intensity = scan.range_mm.copy(), scan.intensity.copy()
    ranges[5], intensity[5] = ranges[2], intensity[2]
    twice = _scan(
        [0, 40, 80, 120, 160, 80, 240],
        range_mm=ranges[:7],
        intensity=intensity[:7],
        closest_mm=scan.closest_mm[:7],
        t=scan.t[:7],
    )
    found = ScanChecker().add(twice)
    assert any("row 5 (azimuth 80) repeats row 2 of the same scan" in v for v in found), found


def test_repeats_need_the_same_azimuth_and_data_and_skip_rows_without_return() -> None:
    checker = ScanChecker()
    first = _scan(seed=5)
    checker.add(first)
    # the same line of data at another azimuth is another acquisition (a flat, noiseless wall)
    moved = _scan(
        [a + 1 for a in first.azimuth], seq=2, range_mm=first.range_mm, intensity=first.intensity
    )
    assert checker.add(moved) == []
    # rows with no return at all look alike whatever made them: never keyed
    nothing = np.zeros_like(first.range_mm)
    blind = [
        _scan(
            seq=3 + k,
            range_mm=nothing,
            intensity=nothing,
            closest_mm=np.zeros(first.n_acq, np.int16),
        )
        for k in range(2)
    ]
    assert checker.extend(blind) == [] and checker.ok
    assert checker.summary() == "checked 4 scans: OK"
    # without noise, two sweeps over one azimuth agree: the rule can be turned off
    quiet = ScanChecker(repeats=False)
    assert quiet.extend([first, _scan(seed=5, seq=2)]) == []
    assert ScanChecker().extend([first, _scan(seed=5, seq=2)]) != []


# -- the wire: lossless, and old payloads still read ---------------------------------------------

OLD_SCAN_DEFINITION = """\
std_msgs/Header header
uint8 DIRECTION_CW=0
uint8 DIRECTION_CCW=1
uint8 direction
uint64 seq
uint32 n_acq
uint32 samples
int32[] azimuth
int16[] range_mm
int16[] closest_mm
int16[] intensity
float64[] t
uint64 dropped
int32 elevation
bool has_t_delivered
float64 t_delivered
bool has_mount
biris_msgs/Mount mount
string acquisition
bool partial
"""
"""biris_msgs/msg/Scan as the first release defined it (before partial_reason and span), written
out here rather than derived from biris_hw.io.codec, so that the test holds the module to it."""


def _old_payload(scan: Scan) -> bytes:
    """``scan`` serialised with :data:`OLD_SCAN_DEFINITION`: what recordings made before the
    new fields hold."""
    store = get_typestore(Stores.ROS2_HUMBLE)
    types: dict[str, Any] = {}
    types.update(get_types_from_msg(codec.MSG_DEFINITIONS[codec.MOUNT], codec.MOUNT))
    types.update(get_types_from_msg(OLD_SCAN_DEFINITION, codec.SCAN))
    store.register(types)
    cls = store.types
    stamp = cls["builtin_interfaces/msg/Time"](sec=10, nanosec=0)
    msg = cls[codec.SCAN](
        header=cls["std_msgs/msg/Header"](stamp=stamp, frame_id="biris"),
        direction=int(scan.direction),
        seq=scan.seq,
        n_acq=scan.n_acq,
        samples=scan.samples,
        azimuth=scan.azimuth.copy(),
        range_mm=scan.range_mm.reshape(-1).copy(),
        closest_mm=scan.closest_mm.copy(),
        intensity=scan.intensity.reshape(-1).copy(),
        t=scan.t.copy(),
        dropped=scan.dropped,
        elevation=scan.elevation,
        has_t_delivered=False,
        t_delivered=0.0,
        has_mount=False,
        mount=cls[codec.MOUNT](offset_m=np.zeros(3), head_height_m=0.0, head_offset_m=0.0),
        acquisition=scan.acquisition,
        partial=scan.partial,
    )
    return bytes(store.serialize_cdr(msg, codec.SCAN))


def test_the_wire_keeps_the_new_fields() -> None:
    for scan in (
        _scan(partial=True, partial_reason="ended 40 counts (3.5 deg) short", span=(-5, 2048)),
        _scan(span=(-(2**31), 2**31 - 1)),  # the int32 range, whole
        _scan([], partial=True, partial_reason="no acquisition", span=(0, 400)),
        _scan(),  # unknown span stays unknown, not (0, 0)
    ):
        back = codec.decode_scan(codec.encode_scan(scan))
        assert (back.partial, back.partial_reason, back.span) == (
            scan.partial,
            scan.partial_reason,
            scan.span,
        )
        assert np.array_equal(back.azimuth, scan.azimuth) and back.seq == scan.seq
    with pytest.raises(codec.WireError):
        codec.encode_scan(_scan(span=(0, 2**31)))  # beyond int32: refused, not wrapped


def test_a_payload_of_the_old_definition_still_decodes() -> None:
    scan = _scan(partial=True, acquisition="continuous", seq=9, dropped=2)
    old = _old_payload(scan)
    assert old != codec.encode_scan(scan)  # truly the old layout
    back = codec.decode_scan(old)
    assert (back.partial, back.partial_reason, back.span) == (True, "", None)
    assert (back.seq, back.dropped, back.acquisition) == (9, 2, "continuous")
    for key in ("azimuth", "range_mm", "closest_mm", "intensity", "t"):
        assert np.array_equal(getattr(back, key), getattr(scan, key)), key
    # neither layout: the error is the current type's, and cut payloads of either are errors
    new = codec.encode_scan(_scan(span=(0, 400)))
    for bad in (old[:-3], new[:-3], new + b"\0" * 16, b"\0\1\0\0garbage"):
        with pytest.raises(codec.WireError, match="biris_msgs/msg/Scan"):
            codec.decode_scan(bad)


def test_the_documented_definition_is_the_codecs() -> None:
    """docs/wire-format.md shows biris_msgs/msg/Scan field for field as the codec defines it."""
    doc = (Path(__file__).resolve().parent.parent / "docs" / "wire-format.md").read_text()
    block = doc.split("# biris_msgs/msg/Scan --", 1)[1].split("```", 1)[0]
    documented = [line.split("#")[0].strip() for line in block.splitlines()[1:]]
    defined = [
        line.strip()
        for line in codec.MSG_DEFINITIONS[codec.SCAN].splitlines()
        if line.strip() and not line.startswith("#")
    ]
    assert [line for line in documented if line] == defined


# -- scan files ----------------------------------------------------------------------------------


def test_scan_files_keep_the_new_fields(tmp_path: Path) -> None:
    saved = [
        _scan(partial=True, partial_reason="first sweep, from 12", span=(12, 400)),
        _scan(list(range(400, -1, -40)), Direction.CW, span=(400, 0)),
        _scan(),
        _scan([], partial=True, partial_reason="no acquisition: BIRIS's start seen late"),
    ]
    loaded = load_scans(save_scans(tmp_path / "run", saved))
    assert [(s.partial, s.partial_reason, s.span) for s in loaded] == [
        (s.partial, s.partial_reason, s.span) for s in saved
    ]
    assert all(type(s.partial_reason) is str for s in loaded)
    assert FORMAT_VERSION == 4
    # a version-3 file has neither: no reason, span unknown
    with np.load(tmp_path / "run.npz", allow_pickle=False) as data:
        arrays = {
            key: data[key]
            for key in data.files
            if key not in ("partial_reason", "has_span", "span")
        }
    arrays["format_version"] = np.array(3, dtype=np.int64)
    np.savez(tmp_path / "v3.npz", **arrays)
    back = load_scans(tmp_path / "v3.npz")
    assert [(s.partial, s.partial_reason, s.span) for s in back] == [
        (s.partial, "", None) for s in saved
    ]

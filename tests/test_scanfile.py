"""Scan files: every field of every scan comes back from a .npz exactly, old files still load, and
the .csv export says what it says."""

from __future__ import annotations

import csv
import dataclasses
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from biris_hw.data import Direction, Scan
from biris_hw.geometry import Mount
from biris_hw.io.scanfile import FORMAT_VERSION, SAVED_FIELDS, export_csv, load_scans, save_scans

INT64 = st.integers(-(2**63), 2**63 - 1)
COUNT = st.integers(0, 2**63 - 1)
FINITE = st.floats(allow_nan=False, allow_infinity=False)


@st.composite
def scans(draw: st.DrawFn) -> Scan:
    """Any scan the Scan class accepts: any sizes (empty too), any values, NaN times included."""
    n = draw(st.integers(0, 5))
    samples = draw(st.integers(0, 4))
    mount = draw(
        st.none()
        | st.builds(
            Mount,
            offset_m=st.tuples(FINITE, FINITE, FINITE),
            head_height_m=FINITE,
            head_offset_m=FINITE,
        )
    )
    return Scan(
        direction=draw(st.sampled_from(Direction)),
        seq=draw(COUNT),
        azimuth=draw(arrays(np.int32, n)),
        range_mm=draw(arrays(np.int16, (n, samples))),
        closest_mm=draw(arrays(np.int16, n)),
        intensity=draw(arrays(np.int16, (n, samples))),
        t=draw(arrays(np.float64, n)),
        dropped=draw(COUNT),
        elevation=draw(INT64),
        t_delivered=draw(st.none() | st.floats()),
        mount=mount,
    )


def _same_value(a: Any, b: Any) -> bool:
    if isinstance(a, np.ndarray):
        return (
            isinstance(b, np.ndarray)
            and a.dtype == b.dtype
            and a.shape == b.shape
            and a.tobytes() == b.tobytes()  # bit for bit: NaNs and -0.0 included
        )
    if isinstance(a, float):
        return isinstance(b, float) and np.float64(a).tobytes() == np.float64(b).tobytes()
    return type(a) is type(b) and bool(a == b)


def assert_same_scans(saved: list[Scan], loaded: list[Scan]) -> None:
    assert len(loaded) == len(saved)
    for i, (a, b) in enumerate(zip(saved, loaded, strict=True)):
        for f in dataclasses.fields(Scan):
            x, y = getattr(a, f.name), getattr(b, f.name)
            assert _same_value(x, y), (i, f.name, x, y)


def test_every_field_of_scan_is_saved() -> None:
    """A field added to Scan must be added to the file format (and this test tells)."""
    assert {f.name for f in dataclasses.fields(Scan)} == SAVED_FIELDS


@pytest.mark.slow  # fast-tier budget (issue 13 added the transports); make test-slow
@settings(max_examples=80, deadline=None)
@given(st.lists(scans(), max_size=4))
def test_save_then_load_gives_equal_scans(saved: list[Scan]) -> None:
    with tempfile.TemporaryDirectory() as folder:
        path = save_scans(Path(folder) / "run.npz", saved)
        assert path == Path(folder) / "run.npz"
        assert_same_scans(saved, load_scans(path))


def _scan(seq: int, samples: int = 3, n: int = 2, **extra: Any) -> Scan:
    rng = np.random.default_rng(seq)
    return Scan(
        direction=Direction(seq % 2),
        seq=seq,
        azimuth=np.arange(n, dtype=np.int32) * 7 - 3,
        range_mm=rng.integers(0, 3000, (n, samples), dtype=np.int16),
        closest_mm=rng.integers(0, 3000, n, dtype=np.int16),
        intensity=rng.integers(0, 255, (n, samples), dtype=np.int16),
        t=np.linspace(1.0, 2.0, n),
        **extra,
    )


def test_the_suffix_is_added_as_numpy_would(tmp_path: Path) -> None:
    saved = [_scan(1, elevation=114, mount=Mount(offset_m=(0.1, 0.0, 0.3)))]
    path = save_scans(tmp_path / "run", saved)
    assert path == tmp_path / "run.npz" and path.is_file()
    assert_same_scans(saved, load_scans(tmp_path / "run"))
    assert_same_scans(saved, load_scans(str(path)))


def test_the_file_is_plain_arrays_for_other_programs(tmp_path: Path) -> None:
    saved = [_scan(1, samples=3, n=2), _scan(2, samples=5, n=1, t_delivered=2.5)]
    path = save_scans(tmp_path / "mixed.npz", saved)
    with np.load(path, allow_pickle=False) as data:
        assert int(data["format_version"]) == FORMAT_VERSION
        assert data["range_mm"].shape == (3, 5)  # as wide as the widest, padded with 0
        assert data["range_mm"][:2, 3:].tolist() == [[0, 0], [0, 0]]
        assert data["scan_index"].tolist() == [0, 0, 1]
        assert data["samples"].tolist() == [3, 5]
        assert data["has_t_delivered"].tolist() == [False, True]
        np.testing.assert_allclose(data["azimuth_deg"], data["azimuth"] * 360.0 / 4096)
    assert_same_scans(saved, load_scans(path))


def _save_like_release_1(path: Path, scans: list[Scan]) -> None:
    """What ``biris_hw.commands.scan.save_scans`` wrote before format version 2."""
    index = np.concatenate([np.full(s.n_acq, i, dtype=np.int32) for i, s in enumerate(scans)])
    with open(path, "wb") as f:
        np.savez_compressed(
            f,
            scan_index=index,
            direction=np.array([int(s.direction) for s in scans], dtype=np.int8),
            seq=np.array([s.seq for s in scans], dtype=np.int32),
            dropped=np.array([s.dropped for s in scans], dtype=np.int32),
            azimuth=np.concatenate([s.azimuth for s in scans]),
            azimuth_deg=np.concatenate([s.azimuth_deg for s in scans]),
            t=np.concatenate([s.t for s in scans]),
            closest_mm=np.concatenate([s.closest_mm for s in scans]),
            range_mm=np.concatenate([s.range_mm for s in scans]),
            intensity=np.concatenate([s.intensity for s in scans]),
        )


def test_files_of_the_first_release_still_load(tmp_path: Path) -> None:
    saved = [_scan(1, dropped=2), _scan(2, n=4), _scan(3, n=0)]
    path = tmp_path / "old.npz"
    _save_like_release_1(path, saved)
    assert_same_scans(saved, load_scans(path))  # they kept no elevation, mount or delivery


def test_not_a_scan_file(tmp_path: Path) -> None:
    path = tmp_path / "other.npz"
    np.savez(path, something=np.zeros(3))
    with pytest.raises(ValueError, match="not a file of BIRIS scans"):
        load_scans(path)
    np.savez(path, format_version=np.array(99))
    with pytest.raises(ValueError, match="format version 99"):
        load_scans(path)


def test_the_csv_export(tmp_path: Path) -> None:
    saved = [_scan(1, samples=2, n=2), _scan(2, samples=3, n=1)]
    path = export_csv(tmp_path / "run", saved)
    assert path == tmp_path / "run.csv"
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    assert rows[0] == [
        "scan", "direction", "seq", "acq", "t_s", "azimuth_counts", "azimuth_deg", "closest_mm",
        "range_1_mm", "range_2_mm", "range_3_mm",
    ]  # fmt: skip
    first_columns = [row[:4] for row in rows[1:]]
    assert first_columns == [["0", "CCW", "1", "0"], ["0", "CCW", "1", "1"], ["1", "CW", "2", "0"]]
    assert rows[1][8:] == [*map(str, saved[0].range_mm[0].tolist()), ""]  # narrower: padded
    assert rows[3][8:] == [str(v) for v in saved[1].range_mm[0].tolist()]
    assert float(rows[1][4]) == pytest.approx(saved[0].t[0], abs=1e-6)

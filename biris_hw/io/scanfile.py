"""Scans on disk: a lossless ``.npz`` for programs, a ``.csv`` table for people and spreadsheets.

:func:`save_scans` writes a list of :class:`~biris_hw.Scan` to ``.npz`` and :func:`load_scans`
gives back scans equal to them field by field: every array with its dtype and shape, and
``direction``, ``seq``, ``dropped``, ``elevation``, ``t_delivered`` (None kept as None),
``mount`` (None kept as None), ``acquisition``, ``partial``, ``partial_reason`` and ``span``
(None kept as None). Scans of different sample counts may share a file.

The ``.npz`` (format version 4) is plain numpy arrays, no pickles, readable without this
module. Per scan, in saving order: ``direction`` (0 CW, 1 CCW), ``seq``, ``dropped``,
``elevation`` (counts), ``n_acq``, ``samples``, ``t_delivered`` (NaN where
``has_t_delivered`` is false), ``has_mount``, ``mount_offset_m`` (n, 3), ``mount_head_height_m``,
``mount_head_offset_m``, ``acquisition`` (text: ``single`` or ``continuous``), ``partial``
(bool), ``partial_reason`` (text, empty for a whole scan), ``has_span`` (bool) and ``span``
(n, 2: start and destination in counts, 0 where ``has_span`` is false). Per acquisition,
every scan's rows one after the other:
``scan_index`` (which scan the row belongs to), ``azimuth`` (counts, int32), ``azimuth_deg``
(for convenience; not read back), ``t``, ``closest_mm``, and ``range_mm`` and ``intensity``
(int16, as wide as the widest scan; a narrower scan's rows are padded with 0, "no return", and
its ``samples`` says where they end). ``format_version`` is 4.

Files of earlier format versions load too. Version 3 did not keep ``partial_reason`` or
``span``: they come back as ``""`` and None (not known), and a partial scan of such a file says
no more than that it is partial. Version 2 did not keep ``acquisition`` or
``partial``: every scan of its day was a single-acquisition one or a whole continuous-acquisition
sweep, and they come back as ``"single"`` and False (the mode is not recorded anywhere else, so a
version-2 file of Appendix D sweeps reads as single). Files written before version 2 (by
``biris scan --save`` and ``biris demo`` of earlier releases) did not keep ``elevation``,
``t_delivered`` or ``mount`` either, which come back as 0, None and None.

The ``.csv`` (:func:`export_csv`) is an export, not a second format: one row per acquisition
with ``scan`` (index in the list), ``direction`` (CW/CCW), ``seq``, ``acq``, ``t_s`` (to the
microsecond), ``azimuth_counts``, ``azimuth_deg``, ``closest_mm`` and ``range_1_mm`` ...
``range_N_mm`` (the profile, top row first). It leaves out intensities, ``dropped``,
``elevation``, ``t_delivered``, ``mount``, ``acquisition``, ``partial``, ``partial_reason`` and
``span``; it is never read back.
"""

from __future__ import annotations

import csv
import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from biris_hw.data import Direction, Scan
from biris_hw.geometry import Mount

__all__ = ["FORMAT_VERSION", "SAVED_FIELDS", "export_csv", "load_scans", "save_scans"]

FORMAT_VERSION = 4
"""Version 1 (no ``format_version`` key) kept the arrays, direction, seq and dropped only;
version 2 added elevation, t_delivered and mount; version 3 added acquisition and partial;
version 4 added partial_reason and span."""

SAVED_FIELDS = frozenset(
    {
        "direction",
        "seq",
        "azimuth",
        "range_mm",
        "closest_mm",
        "intensity",
        "t",
        "dropped",
        "elevation",
        "t_delivered",
        "mount",
        "acquisition",
        "partial",
        "partial_reason",
        "span",
    }
)
"""The :class:`~biris_hw.Scan` fields a ``.npz`` keeps: all of them (tests/test_scanfile.py
holds this to ``dataclasses.fields(Scan)``, so a new field cannot be forgotten here)."""


_MODE_DTYPE = np.dtype("<U10")
"""``acquisition`` as fixed-width text: readable by any numpy program, no pickle needed."""


def _with_suffix(path: str | os.PathLike[str], suffix: str) -> Path:
    """``path`` as given if it ends in ``suffix``, else with ``suffix`` appended (as numpy does)."""
    p = Path(path)
    return p if p.suffix == suffix else p.with_name(p.name + suffix)


def _mount_fields(mount: Mount | None) -> tuple[tuple[float, float, float], float, float]:
    m = mount if mount is not None else Mount()
    return m.offset_m, m.head_height_m, m.head_offset_m


def save_scans(path: str | os.PathLike[str], scans: Sequence[Scan]) -> Path:
    """Write ``scans`` to ``path`` (``.npz`` appended unless it ends so); returns the path.

    Lossless: :func:`load_scans` gives back equal scans in the same order. An empty list is
    saved as an empty file of scans. Raises OverflowError for a ``seq``, ``dropped`` or
    ``elevation`` beyond 64 bits rather than store it wrong.
    """
    target = _with_suffix(path, ".npz")
    scans = list(scans)
    width = max((s.samples for s in scans), default=0)
    total = sum(s.n_acq for s in scans)

    def rows(key: str, dtype: type[np.generic]) -> NDArray[Any]:
        out = np.zeros((total, width), dtype=dtype)
        start = 0
        for s in scans:
            out[start : start + s.n_acq, : s.samples] = getattr(s, key)
            start += s.n_acq
        return out

    def column(key: str, dtype: type[np.generic]) -> NDArray[Any]:
        parts = [getattr(s, key) for s in scans]
        return np.concatenate(parts).astype(dtype) if parts else np.zeros(0, dtype=dtype)

    mounts = [_mount_fields(s.mount) for s in scans]
    arrays: dict[str, NDArray[Any]] = {
        "format_version": np.array(FORMAT_VERSION, dtype=np.int64),
        # per scan
        "direction": np.array([int(s.direction) for s in scans], dtype=np.int8),
        "seq": np.array([s.seq for s in scans], dtype=np.int64),
        "dropped": np.array([s.dropped for s in scans], dtype=np.int64),
        "elevation": np.array([s.elevation for s in scans], dtype=np.int64),
        "n_acq": np.array([s.n_acq for s in scans], dtype=np.int64),
        "samples": np.array([s.samples for s in scans], dtype=np.int64),
        "t_delivered": np.array(
            [math.nan if s.t_delivered is None else s.t_delivered for s in scans],
            dtype=np.float64,
        ),
        "has_t_delivered": np.array([s.t_delivered is not None for s in scans], dtype=np.bool_),
        "has_mount": np.array([s.mount is not None for s in scans], dtype=np.bool_),
        "mount_offset_m": np.array([m[0] for m in mounts], dtype=np.float64).reshape(-1, 3),
        "mount_head_height_m": np.array([m[1] for m in mounts], dtype=np.float64),
        "mount_head_offset_m": np.array([m[2] for m in mounts], dtype=np.float64),
        "acquisition": np.array([s.acquisition for s in scans], dtype=_MODE_DTYPE),
        "partial": np.array([s.partial for s in scans], dtype=np.bool_),
        # text of the longest reason's width (numpy's str dtype), never an object array
        "partial_reason": np.array([s.partial_reason for s in scans], dtype=np.str_),
        "has_span": np.array([s.span is not None for s in scans], dtype=np.bool_),
        "span": np.array(
            [s.span if s.span is not None else (0, 0) for s in scans], dtype=np.int64
        ).reshape(-1, 2),
        # per acquisition
        "scan_index": np.repeat(
            np.arange(len(scans), dtype=np.int32), [s.n_acq for s in scans]
        ).astype(np.int32),
        "azimuth": column("azimuth", np.int32),
        "azimuth_deg": column("azimuth_deg", np.float64),
        "t": column("t", np.float64),
        "closest_mm": column("closest_mm", np.int16),
        "range_mm": rows("range_mm", np.int16),
        "intensity": rows("intensity", np.int16),
    }
    with open(target, "wb") as f:  # a file object: numpy appends nothing to the name
        np.savez_compressed(f, **arrays)  # type: ignore[arg-type]  # (stubs: allow_pickle)
    return target


def load_scans(path: str | os.PathLike[str]) -> list[Scan]:
    """The scans a :func:`save_scans` ``.npz`` holds, in the order they were saved.

    ``.npz`` is appended unless the path ends so. Reads format version 4 and the files of
    earlier releases (see the module's notes). ValueError if the file is not a scan file.
    """
    source = _with_suffix(path, ".npz")
    with np.load(source, allow_pickle=False) as data:
        arrays = {key: data[key] for key in data.files}
    try:
        if "format_version" not in arrays:
            return _load_v1(arrays)
        version = int(arrays["format_version"])
        if version not in (2, 3, FORMAT_VERSION):
            raise ValueError(f"format version {version}; this release reads 1 to 4")
        return _load_v2(arrays, with_mode=version >= 3, with_span=version >= 4)
    except KeyError as exc:
        raise ValueError(f"{source} is not a file of BIRIS scans: no {exc.args[0]!r}") from None
    except ValueError as exc:
        raise ValueError(f"{source}: {exc}") from None


def _load_v2(a: dict[str, NDArray[Any]], *, with_mode: bool, with_span: bool) -> list[Scan]:
    """Versions 2 to 4 (``with_mode``: the file keeps ``acquisition`` and ``partial``;
    ``with_span``: ``partial_reason`` and ``span`` too)."""
    n_acq = a["n_acq"]
    total = int(n_acq.sum()) if n_acq.size else 0
    if a["azimuth"].shape[0] != total:
        raise ValueError(f"{a['azimuth'].shape[0]} acquisitions stored, the scans count {total}")
    ends = np.cumsum(n_acq)
    scans = []
    for i in range(n_acq.shape[0]):
        stop = int(ends[i])
        start = stop - int(n_acq[i])
        width = int(a["samples"][i])
        mount = None
        if bool(a["has_mount"][i]):
            x, y, z = (float(v) for v in a["mount_offset_m"][i])
            mount = Mount(
                offset_m=(x, y, z),
                head_height_m=float(a["mount_head_height_m"][i]),
                head_offset_m=float(a["mount_head_offset_m"][i]),
            )
        scans.append(
            Scan(
                direction=Direction(int(a["direction"][i])),
                seq=int(a["seq"][i]),
                azimuth=a["azimuth"][start:stop],
                range_mm=a["range_mm"][start:stop, :width],
                closest_mm=a["closest_mm"][start:stop],
                intensity=a["intensity"][start:stop, :width],
                t=a["t"][start:stop],
                dropped=int(a["dropped"][i]),
                elevation=int(a["elevation"][i]),
                t_delivered=float(a["t_delivered"][i]) if bool(a["has_t_delivered"][i]) else None,
                mount=mount,
                acquisition=str(a["acquisition"][i]) if with_mode else "single",
                partial=bool(a["partial"][i]) if with_mode else False,
                partial_reason=str(a["partial_reason"][i]) if with_span else "",
                span=_span(a, i) if with_span else None,
            )
        )
    return scans


def _span(a: dict[str, NDArray[Any]], i: int) -> tuple[int, int] | None:
    """Scan ``i``'s span as a version-4 file keeps it (None where ``has_span`` is false)."""
    if not bool(a["has_span"][i]):
        return None
    start, destination = (int(v) for v in a["span"][i])
    return start, destination


def _load_v1(a: dict[str, NDArray[Any]]) -> list[Scan]:
    index = a["scan_index"]
    scans = []
    for i, (direction, seq, dropped) in enumerate(
        zip(a["direction"], a["seq"], a["dropped"], strict=True)
    ):
        rows = index == i
        scans.append(
            Scan(
                direction=Direction(int(direction)),
                seq=int(seq),
                azimuth=a["azimuth"][rows],
                range_mm=a["range_mm"][rows],
                closest_mm=a["closest_mm"][rows],
                intensity=a["intensity"][rows],
                t=a["t"][rows],
                dropped=int(dropped),
            )
        )
    return scans


def export_csv(path: str | os.PathLike[str], scans: Sequence[Scan]) -> Path:
    """Write the readable table (``.csv`` appended unless the path ends so); returns the path.

    One row per acquisition; see the module's notes for the columns and what is left out.
    Scans narrower than the widest leave their last range cells empty.
    """
    target = _with_suffix(path, ".csv")
    width = max((s.samples for s in scans), default=0)
    with open(target, "w", newline="", encoding="ascii") as f:
        writer = csv.writer(f)
        writer.writerow(
            ["scan", "direction", "seq", "acq", "t_s", "azimuth_counts", "azimuth_deg"]
            + ["closest_mm"]
            + [f"range_{k + 1}_mm" for k in range(width)]
        )
        for i, scan in enumerate(scans):
            az_deg = scan.azimuth_deg
            pad = [""] * (width - scan.samples)
            for k in range(scan.n_acq):
                writer.writerow(
                    [
                        i,
                        scan.direction.name,
                        scan.seq,
                        k,
                        f"{scan.t[k]:.6f}",
                        int(scan.azimuth[k]),
                        f"{az_deg[k]:.4f}",
                        int(scan.closest_mm[k]),
                        *scan.range_mm[k].tolist(),
                        *pad,
                    ]
                )
    return target

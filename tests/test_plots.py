"""The pictures do not mislead: no line across a gap, a 3-D view with a colour bar that fills its
frame, and every sweep drawn.

No simulator here: the scans are built by hand from a known scene (a wall at 2 m with a hole in
it and a box in front), so the test knows where every gap is and each picture is a fraction of
a second. The figures are inspected before they are saved (their lines, gids and colour bars),
not their pixels.
"""

from __future__ import annotations

import itertools
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from numpy.typing import NDArray

from biris_hw.data import Direction, Scan
from biris_hw.io import plots
from biris_hw.io.plots import (
    GAP_RATIO,
    polar_figure,
    save_3d_view,
    save_polar,
    save_top_view,
    segments,
    top_view_figure,
    view_3d_figure,
)
from regs.hctl1000 import COUNTS_PER_REV

PNG = b"\x89PNG\r\n\x1a\n"
SAMPLES = 8
WALL_X_M = 2.0
HOLE_DEG = (8.0, 16.0)
"""A doorway in the wall: no return (the sensor sees nothing within its range through it)."""
BOX_DEG = (-22.0, -12.0)
BOX_X_M = 1.0
"""A box standing 1 m in front of the wall: its returns are half the wall's range."""


# -- hand-made scans -------------------------------------------------------------------------------


def scene_range_m(az_deg: NDArray[np.float64]) -> NDArray[np.float64]:
    """Closest range of the scene at each azimuth: wall, hole (0) and box."""
    x = np.where((az_deg >= BOX_DEG[0]) & (az_deg <= BOX_DEG[1]), BOX_X_M, WALL_X_M)
    r = x / np.cos(np.radians(az_deg))
    return np.where((az_deg >= HOLE_DEG[0]) & (az_deg <= HOLE_DEG[1]), 0.0, r)


def make_scan(
    direction: Direction = Direction.CCW, seq: int = 1, span_deg: float = 45.0, n: int = 46
) -> Scan:
    """A sweep across the scene from -span to +span (CCW) or back (CW), every sample at the
    closest range (a flat profile is enough for pictures)."""
    az_deg = np.linspace(-span_deg, span_deg, n)
    if direction is Direction.CW:
        az_deg = az_deg[::-1]
    closest = np.round(scene_range_m(az_deg) * 1000.0)
    return Scan(
        direction=direction,
        seq=seq,
        azimuth=np.round(az_deg * COUNTS_PER_REV / 360.0).astype(np.int32),
        range_mm=np.repeat(closest[:, np.newaxis], SAMPLES, axis=1).astype(np.int16),
        closest_mm=closest.astype(np.int16),
        intensity=np.full((n, SAMPLES), 100, dtype=np.int16),
        t=np.arange(n, dtype=np.float64) * 0.0334,
    )


def sweeps(count: int) -> list[Scan]:
    """``count`` sweeps back and forth, CCW first, as a continuous scan makes them."""
    return [
        make_scan(Direction.CCW if i % 2 == 0 else Direction.CW, seq=i // 2 + 1)
        for i in range(count)
    ]


def drawn_pieces(line: Any) -> list[NDArray[np.float64]]:
    """The polylines one Line2D draws: its vertices split where matplotlib breaks it (NaN)."""
    xy = np.column_stack((line.get_xdata(), line.get_ydata())).astype(np.float64)
    broken = np.isnan(xy).any(axis=1)
    pieces, start = [], 0
    for i in [*np.flatnonzero(broken), len(xy)]:
        if i > start:
            pieces.append(xy[start:i])
        start = i + 1
    return pieces


def lines_by_gid(fig: Any) -> dict[str, Any]:
    return {line.get_gid(): line for ax in fig.axes for line in ax.get_lines() if line.get_gid()}


# -- the gap rule ----------------------------------------------------------------------------------


def test_a_hole_in_a_wall_breaks_the_run() -> None:
    wall = [2.00, 2.01, 2.03, 0.0, 0.0, 0.0, 2.05, 2.04]
    assert segments(wall) == [(0, 3), (6, 8)]


def test_a_jump_from_one_metre_to_four_breaks_the_run() -> None:
    assert segments([1.0, 1.02, 1.01, 4.0, 4.05, 4.1]) == [(0, 3), (3, 6)]
    assert segments([4.0, 4.05, 1.0, 1.02]) == [(0, 2), (2, 4)]  # and coming back


def test_missing_returns_are_never_drawn() -> None:
    assert segments([0, 0, 0]) == []
    assert segments([]) == []
    assert segments([0, 1500, 0]) == [(1, 2)]  # a return alone: a marker, no line
    assert segments([1500, -1, 1500, math.nan, 1500, math.inf, 1500]) == [
        (0, 1), (2, 3), (4, 5), (6, 7)
    ]  # fmt: skip


def test_the_threshold_is_relative_to_the_nearer_range() -> None:
    assert segments([1.0, 1.0 + GAP_RATIO]) == [(0, 2)]
    assert segments([1.0, 1.0 + GAP_RATIO * 1.05]) == [(0, 1), (1, 2)]
    # the same 0.3 m is a gap at 1 m and a slope at 3 m; the unit does not matter
    assert segments([1000, 1300]) == [(0, 1), (1, 2)]
    assert segments([3000, 3300]) == [(0, 2)]
    assert segments([1.0, 1.5], gap_ratio=0.6) == [(0, 2)]


def test_a_slanted_wall_stays_one_run() -> None:
    """A flat wall 2 m away seen over +-65 degrees with a 90-degree sweep's spacing."""
    az = np.radians(np.arange(-65.0, 65.1, 90.0 / 25))
    assert segments(2.0 / np.cos(az)) == [(0, az.size)]


def test_the_rule_refuses_what_it_cannot_judge() -> None:
    with pytest.raises(ValueError, match="gap_ratio"):
        segments([1.0, 2.0], gap_ratio=0.0)
    with pytest.raises(ValueError, match="one range per acquisition"):
        segments(np.ones((2, 3)))


# -- the polar picture -----------------------------------------------------------------------------


def test_polar_lines_do_not_bridge_the_hole_or_join_the_box_to_the_wall() -> None:
    scan = make_scan()
    fig = polar_figure(scan)
    line = lines_by_gid(fig)["sweep 1 line"]
    pieces = drawn_pieces(line)
    # the wall left of the box, the box, the wall between box and hole, the wall past the hole
    assert len(pieces) == 4
    r = scan.closest_mm / 1000.0
    az = scan.azimuth * 2 * math.pi / COUNTS_PER_REV
    expected = [
        np.column_stack((r[a:b] * np.cos(az[a:b]), r[a:b] * np.sin(az[a:b])))
        for a, b in segments(r)
        if b - a > 1
    ]
    assert len(expected) == len(pieces)
    for got, want in zip(pieces, expected, strict=True):
        np.testing.assert_allclose(got, want)
    for piece in pieces:
        ranges = np.hypot(piece[:, 0], piece[:, 1])
        bearing = np.degrees(np.arctan2(piece[:, 1], piece[:, 0]))
        # each piece lies on one surface: the box or the wall, never both
        on_box = np.abs(piece[:, 0] - BOX_X_M) < 0.01
        assert on_box.all() or not on_box.any()
        # and no segment crosses the hole
        for a, b in itertools.pairwise(bearing):
            lo, hi = sorted((a, b))
            assert hi <= HOLE_DEG[0] or lo >= HOLE_DEG[1], (a, b)
        assert np.all(np.abs(np.diff(ranges)) <= GAP_RATIO * np.minimum(ranges[:-1], ranges[1:]))
    # every return is still shown as a marker, the hole's none
    returns = lines_by_gid(fig)["sweep 1 returns"]
    assert returns.get_linestyle() == "None"
    assert len(returns.get_xdata()) == int(np.count_nonzero(scan.closest_mm))


def test_polar_draws_every_sweep_with_a_legend() -> None:
    fig = polar_figure(sweeps(3))
    gids = lines_by_gid(fig)
    for n in (1, 2, 3):
        assert f"sweep {n} line" in gids and f"sweep {n} returns" in gids
    colours = {tuple(gids[f"sweep {n} returns"].get_color()) for n in (1, 2, 3)}
    assert len(colours) == 3
    labels = [t.get_text() for legend in fig.legends for t in legend.get_texts()]
    assert [label.split(":")[0] for label in labels if label.startswith("sweep")] == [
        "sweep 1 CCW", "sweep 2 CW", "sweep 3 CCW"
    ]  # fmt: skip


def test_polar_with_many_sweeps_colours_them_by_order_on_a_bar() -> None:
    fig = polar_figure(sweeps(plots._LEGEND_SWEEPS + 2))
    assert f"sweep {plots._LEGEND_SWEEPS + 2} returns" in lines_by_gid(fig)
    labels = [t.get_text() for legend in fig.legends for t in legend.get_texts()]
    assert not [label for label in labels if label.startswith("sweep")]
    assert any("sweep" in ax.get_ylabel() for ax in fig.axes)


def test_polar_of_one_scan_equals_polar_of_a_list_of_it() -> None:
    scan = make_scan()
    one, listed = lines_by_gid(polar_figure(scan)), lines_by_gid(polar_figure([scan]))
    assert one.keys() == listed.keys()
    for gid, line in one.items():
        np.testing.assert_array_equal(line.get_xydata(), listed[gid].get_xydata())


# -- the 3-D picture -------------------------------------------------------------------------------


def test_the_3d_view_has_a_colour_bar_for_height() -> None:
    fig = view_3d_figure(sweeps(2))
    ax = fig.axes[0]
    dots = ax.collections[0]
    assert dots.colorbar is not None
    label = dots.colorbar.ax.get_ylabel()
    assert "height" in label and "(m)" in label
    cloud = np.vstack([plots.profile_points(s) for s in sweeps(2)])
    lo, hi = dots.get_clim()
    assert lo == pytest.approx(cloud[:, 2].min()) and hi == pytest.approx(cloud[:, 2].max())


def test_the_3d_view_fits_the_points_with_equal_aspect() -> None:
    scans = sweeps(2)
    fig = view_3d_figure(scans)
    ax: Any = fig.axes[0]
    cloud = np.vstack([plots.profile_points(s) for s in scans])
    centre = np.array((0.0, 0.0, 0.5))  # the simulator's head, drawn too
    every = np.vstack((cloud, centre))
    lo, hi = every.min(axis=0), every.max(axis=0)
    limits = np.array([ax.get_xlim(), ax.get_ylim(), ax.get_zlim()])
    assert np.all(limits[:, 0] <= lo) and np.all(limits[:, 1] >= hi)
    spans = limits[:, 1] - limits[:, 0]
    assert np.all(spans - (hi - lo) <= 0.1 * spans.max())  # a thin margin
    box = np.asarray(ax.get_box_aspect(), dtype=np.float64)
    np.testing.assert_allclose(box / box.max(), spans / spans.max(), rtol=1e-6)  # 1 m is 1 m


def test_the_3d_view_fills_its_frame() -> None:
    fig = view_3d_figure(sweeps(2))
    fig.draw_without_rendering()
    ink = plots._extent_3d(fig.axes[0])
    frame = fig.bbox  # pixels
    bar = fig.axes[1].get_tightbbox()
    assert bar is not None
    assert ink.x0 >= frame.x0 - 2 and ink.x1 <= bar.x0 + 2  # nothing cut, the bar clear
    assert ink.y0 >= frame.y0 - 2 and ink.y1 <= frame.y1 - 2
    assert ink.width >= 0.85 * (bar.x0 - frame.x0)
    assert ink.height >= 0.8 * frame.height


# -- files -----------------------------------------------------------------------------------------


@pytest.mark.parametrize("many", [False, True], ids=["one scan", "several"])
def test_every_picture_is_written(tmp_path: Path, many: bool) -> None:
    scans: Scan | list[Scan] = sweeps(3) if many else make_scan()
    outline = [np.array([[WALL_X_M, -3.0], [WALL_X_M, 3.0]])]
    written = [
        save_polar(tmp_path / "polar.png", scans, outline, title="polar"),
        save_top_view(tmp_path / "top.png", scans, outline),
        save_3d_view(tmp_path / "3d.png", scans),
    ]
    assert written == [tmp_path / name for name in ("polar.png", "top.png", "3d.png")]
    for path in written:
        assert path.read_bytes()[:8] == PNG


def test_the_older_calls_still_work(tmp_path: Path) -> None:
    """Points already computed for the top and 3-D views; an empty list for the polar one."""
    scans = sweeps(2)
    points = np.vstack([plots.profile_points(s) for s in scans])
    save_top_view(tmp_path / "top.png", points, None, title="top")
    save_3d_view(tmp_path / "3d.png", points, title="3d")
    save_polar(tmp_path / "polar.png", [])
    for name in ("top.png", "3d.png", "polar.png"):
        assert (tmp_path / name).read_bytes()[:8] == PNG
    title = top_view_figure(points).get_suptitle()
    assert title == f"BIRIS profiles from above: {points.shape[0]} points"


def test_something_that_is_not_a_scan_is_refused() -> None:
    with pytest.raises(TypeError, match="not a Scan"):
        polar_figure([make_scan(), "scan"])  # type: ignore[list-item]
    with pytest.raises(TypeError, match="a Scan or a sequence"):
        polar_figure(3)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"\(m, 3\)"):
        view_3d_figure(np.zeros((4, 2)))

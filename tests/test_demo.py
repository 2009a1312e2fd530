"""``biris demo`` end to end, short and fast: it sweeps, reports, and its pictures show the truth.

One run at a high time scale in a temporary folder serves every check: the summary, the three
pictures (real PNGs with something drawn on them) and the points they show, held against the
scene's true walls. A round wall at 2 m keeps the check sharp: the closest of 64 noisy samples
reads short by about 2.4 sigma, 5 cm there (12 cm at the far walls of the default room).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from biris_hw.cli import main
from biris_hw.data import Direction
from biris_hw.io.plots import closest_points_xy, profile_points
from biris_hw.io.scanfile import load_scans
from sim import Scene

RADIUS_M = 2.0
PICTURES = ("demo-polar.png", "demo-top.png", "demo-3d.png")


@pytest.fixture(scope="module")
def demo(tmp_path_factory: pytest.TempPathFactory) -> tuple[int, str, Path]:
    """(exit status, stdout, output folder) of one short demo run."""
    out = tmp_path_factory.mktemp("demo")
    import contextlib
    import io

    stdout = io.StringIO()
    with contextlib.redirect_stdout(stdout):
        code = main(
            [
                "demo", "--duration", "2", "--time-scale", "20", "--scene", f"circle:{RADIUS_M}",
                "--cw", "-60", "--ccw", "60", "--seed", "5", "--out", str(out),
            ]
        )  # fmt: skip
    return code, stdout.getvalue(), out


@pytest.mark.slow  # fast-tier budget (issue 13 added the transports); make test-slow
def test_the_demo_sweeps_and_sums_up(demo: tuple[int, str, Path]) -> None:
    code, text, out = demo
    assert code == 0, text
    lines = text.splitlines()
    assert lines[0].startswith("biris demo: simulated circle:2.0, 64 samples, x20")
    summary = next(line for line in lines if line.startswith("biris demo: ") and "sweeps (" in line)
    sweeps = int(summary.split()[2])
    assert sweeps >= 4
    assert ", 0 dropped, 0 faults, 0 audit violations in " in summary
    for name in PICTURES:
        assert f"  picture: {out / name}" in lines


def test_the_pictures_are_not_blank(demo: tuple[int, str, Path]) -> None:
    from matplotlib.image import imread

    _, _, out = demo
    for name in PICTURES:
        path = out / name
        assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        pixels = imread(path)
        assert pixels.shape[0] > 400 and pixels.shape[1] > 400
        ink = np.mean(pixels[..., :3] < 0.9)  # share of pixels that are not (nearly) white
        assert 0.01 < ink < 0.6, (name, ink)


def test_the_plotted_points_lie_on_the_true_walls(demo: tuple[int, str, Path]) -> None:
    _, _, out = demo
    scans = load_scans(out / "latest-scans.npz")
    assert sorted(s.direction for s in scans) == [Direction.CW, Direction.CCW]
    scene = Scene.circle(RADIUS_M)
    flat = np.vstack([closest_points_xy(s) for s in scans])
    assert flat.shape[0] >= 40
    assert np.mean(scene.distance_to_surface_2d(flat) <= 0.10) >= 0.8
    cloud = np.vstack([profile_points(s) for s in scans])
    assert cloud.shape[0] >= 40 * 64 * 0.8
    assert np.mean(scene.distance_to_surface_2d(cloud[:, :2]) <= 0.10) >= 0.8
    assert np.all(np.abs(cloud[:, 2] - 0.5) < RADIUS_M * np.tan(np.radians(11.0)) + 0.3)


@pytest.mark.slow  # the fast tier runs the plain demo; continuous mode has fast tests of its own
def test_the_continuous_demo_sweeps_whole_and_loses_nothing(
    fonts_open: None, no_leaks: None, tmp_path: Path
) -> None:
    import contextlib
    import io

    stdout = io.StringIO()
    with contextlib.redirect_stdout(stdout):
        code = main(
            [
                "demo", "--duration", "1.5", "--time-scale", "20", "--scene", f"circle:{RADIUS_M}",
                "--cw", "-40", "--ccw", "40", "--continuous", "--out", str(tmp_path),
            ]
        )  # fmt: skip
    text = stdout.getvalue()
    assert code == 0, text
    assert text.splitlines()[0].endswith(", continuous acquisition")
    assert ", 0 dropped, 0 faults, 0 audit violations in " in text
    scans = load_scans(tmp_path / "latest-scans.npz")
    assert len(scans) == 2
    for scan in scans:  # a whole sweep: BIRIS did not start 240 ms after the head
        ends = sorted((int(scan.azimuth[0]), int(scan.azimuth[-1])))
        assert ends[0] <= -455 + 3 and ends[1] >= 455 - 3, ends


def test_the_demo_refuses_limits_the_wrong_way_round(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["demo", "--cw", "30", "--ccw", "-30", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.splitlines()
    assert err == ["biris demo: --cw (30) must lie below --ccw (-30)"]


@pytest.fixture(scope="module")
def drive_fonts(tmp_path_factory: pytest.TempPathFactory) -> None:
    """matplotlib keeps open the font files it has used (a cache): draw the drive's pictures
    once before the leak check takes its snapshot (a module fixture is set up before it)."""
    from biris_hw.io.grid import CertaintyGrid, save_grid
    from biris_hw.io.plots import save_3d_view, save_top_view

    where = tmp_path_factory.mktemp("fonts")
    points = np.zeros((1, 3))
    save_grid(where / "grid.png", CertaintyGrid(), title="warm-up")
    save_top_view(where / "top.png", points, [], title="warm-up")
    save_3d_view(where / "3d.png", points, title="warm-up")


@pytest.mark.slow  # a drive of 42 hardware seconds at x20 and its pictures: make test-slow
def test_the_drive_demo_deskews_every_sweep_onto_the_true_walls(
    drive_fonts: None, tmp_path: Path
) -> None:
    """``biris demo --drive``: the vehicle drives its default path through the room while the
    head sweeps; every sweep is placed in odom with the poses at its acquisitions' own times, so
    the returns lie on the room's true walls (and the grid holds them), however far the vehicle
    has moved."""
    import io

    from biris_hw.commands.demo import DemoConfig, run_demo

    config = DemoConfig(duration_s=4.0, cw_deg=-60.0, ccw_deg=60.0, out=tmp_path, time_scale=20.0,
                        seed=3, drive=True)  # fmt: skip
    result = run_demo(config, io.StringIO())
    drive = result.drive
    assert drive is not None and result.ok
    assert drive.sweeps >= 4 and drive.unplaced == 0
    assert [p.name for p in result.pictures] == ["demo-grid.png", "demo-top.png", "demo-3d.png"]
    points = np.vstack(drive.points)
    near = Scene.room().distance_to_surface_2d(points[:, :2])
    assert float(np.median(near)) < 0.05  # standing still, the room's median is about 0.03 m
    occupied = drive.grid.occupied_xy()
    assert float(np.median(Scene.room().distance_to_surface_2d(occupied))) < 0.05

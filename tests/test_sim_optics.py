"""sim.optics: BIRIS frames from a scene: depth along the axis, noise, limits, calibration."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sim.optics import Acquisition, BirisOptics, OpticsParams
from sim.scene import DEFAULT_ROOM_ORIGIN, Box, Cylinder, Plane, Scene

X0, Y0 = DEFAULT_ROOM_ORIGIN
X1, Y1 = X0 + 5.0, Y0 + 6.0


def optics(samples: int = 64, seed: int = 0, noise: bool = False, **params: float) -> BirisOptics:
    return BirisOptics(samples, np.random.default_rng(seed), OpticsParams(**params), noise=noise)


def valid_rows(a: Acquisition) -> np.ndarray:
    return a.range_mm[1:][a.range_mm[1:] > 0]


# --- geometry -------------------------------------------------------------------------------------


@pytest.mark.parametrize("samples", [64, 128])
@pytest.mark.parametrize("radius_mm", [500, 1234, 2000, 3400])
def test_circle_reads_its_radius_on_every_row_at_every_azimuth(
    samples: int, radius_mm: int
) -> None:
    cam = optics(samples)
    scene = Scene.circle(radius_mm / 1000.0)
    for azimuth in (0.0, 0.7, -1.9, math.pi):
        a = cam.acquire(scene, azimuth)
        assert a.range_mm.shape == (samples + 1,) and a.range_mm.dtype == np.int16
        assert a.intensity.shape == (samples + 1,) and a.intensity.dtype == np.int16
        assert (a.range_mm == radius_mm).all()  # element 0 included
        assert (a.intensity == a.intensity[1]).all() and a.intensity[0] > 0


@pytest.mark.parametrize("samples", [64, 128])
def test_elevations_spread_evenly_over_the_fan_top_to_bottom(samples: int) -> None:
    e = optics(samples).elevations
    assert e.shape == (samples,)
    step = np.diff(e)
    np.testing.assert_allclose(step, step[0])
    assert step[0] < 0  # top first
    np.testing.assert_allclose(e[0] - e[-1] - step[0], math.radians(22.0))  # spans the fan
    np.testing.assert_allclose(e, -e[::-1])  # symmetric about the optical axis
    with pytest.raises(ValueError):
        e[0] = 0.0  # read-only: the rows are fixed by the optics


@pytest.mark.parametrize(
    ("azimuth", "wall_m"),
    [(0.0, X1), (math.pi / 2, Y1), (math.pi, -X0), (-math.pi / 2, -Y0)],
)
def test_azimuth_is_counter_clockwise_from_dead_ahead(azimuth: float, wall_m: float) -> None:
    # A wall square to the optical axis has the same depth on every row that sees it.
    a = optics().acquire(Scene.room(obstacles=[]), azimuth)
    rows = valid_rows(a)
    assert len(rows) > 40
    assert (rows == round(wall_m * 1000)).all()


def test_tilt_turns_the_axis_and_depth_stays_along_it() -> None:
    cam = optics()
    tilt = 0.3
    a = cam.acquire(Scene.circle(2.0), 0.0, tilt_rad=tilt)
    e = cam.elevations
    expected = np.rint(2000.0 * np.cos(e) / np.cos(tilt + e))
    np.testing.assert_array_equal(a.range_mm[1:], expected)


def test_head_height_sets_where_the_floor_is_seen() -> None:
    cam = optics()
    floor = Scene([Plane(0.0)])
    tilt = -0.6
    e = cam.elevations
    for height in (0.5, 0.8):
        a = cam.acquire(floor, 0.0, tilt_rad=tilt, head_height_m=height)
        expected = np.rint(1000.0 * height / np.sin(-(tilt + e)) * np.cos(e))
        np.testing.assert_array_equal(a.range_mm[1:], expected)
    assert cam.params.head_height_m == 0.5


def test_pan_offset_moves_the_optical_centre_off_the_axis() -> None:
    a = optics(pan_offset_m=0.1).acquire(Scene.circle(2.0), 1.0)
    assert (a.range_mm == 1900).all()


def test_measured_points_lie_on_the_true_walls() -> None:
    # Tall obstacles only: every return is then on a side, which the plan view can check.
    scene = Scene.room(
        obstacles=[
            Box(center=(1.6, 1.2), size=(0.6, 0.4), height=1.5, yaw=0.3),
            Cylinder(center=(1.4, -1.3), radius=0.25, height=1.5),
        ]
    )
    cam = optics()
    points = []
    for azimuth in np.linspace(-math.pi, math.pi, 90, endpoint=False):
        depth = valid_rows(cam.acquire(scene, azimuth)) / 1000.0
        points.append(np.column_stack((depth * math.cos(azimuth), depth * math.sin(azimuth))))
    xy = np.vstack(points)
    assert len(xy) > 2000
    assert scene.distance_to_surface_2d(xy).max() <= 0.6e-3  # mm rounding only
    # and the obstacles were seen, not just the walls
    assert (np.hypot(xy[:, 0] - 1.4, xy[:, 1] + 1.3) < 0.3).sum() > 10


# --- the frame's element 0 ---------------------------------------------------------------------


def test_element_0_is_the_closest_valid_sample_and_its_intensity() -> None:
    cam = optics(noise=True, seed=5)
    scene = Scene.room()
    seen_zero_rows = False
    for azimuth in np.linspace(-3.0, 3.0, 25):
        a = cam.acquire(scene, azimuth)
        rows = a.range_mm[1:]
        valid = rows > 0
        seen_zero_rows |= bool((~valid).any() and valid.any())
        if not valid.any():
            assert a.range_mm[0] == 0 and a.intensity[0] == 0
            continue
        i = int(np.argmin(np.where(valid, rows, np.iinfo(np.int16).max)))
        assert a.range_mm[0] == rows[i] == rows[valid].min()
        assert a.intensity[0] == a.intensity[1 + i]
    assert seen_zero_rows  # element 0 was chosen past rows without a return


def test_intensity_scale_mid_scale_at_1m_and_inverse_square() -> None:
    cam = optics()
    assert cam.acquire(Scene.circle(1.0, albedo=0.6), 0.0).intensity[0] == 16384
    assert cam.acquire(Scene.circle(2.0, albedo=0.6), 0.0).intensity[0] == 4096
    assert cam.acquire(Scene.circle(1.0, albedo=0.3), 0.0).intensity[0] == 8192
    assert cam.acquire(Scene.circle(0.35, albedo=1.0), 0.0).intensity[0] == 32767  # saturates


# --- limits ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("radius", [4.0, 6.0, 0.25, 0.1])
def test_no_return_outside_the_working_range(radius: float) -> None:
    a = optics(noise=True).acquire(Scene.circle(radius), 0.4)
    assert not a.range_mm.any() and not a.intensity.any()


def test_working_range_limits_are_parameters() -> None:
    a = optics(max_range_m=5.0).acquire(Scene.circle(4.0), 0.0)
    assert (a.range_mm == 4000).all()
    assert not optics(min_range_m=1.0).acquire(Scene.circle(0.8), 0.0).range_mm.any()


def test_dark_surface_fades_out_with_range() -> None:
    cam = optics()
    dark = 0.05  # 0.05 * 16384 / 0.6 / z^2: 1365 counts at 1 m, 152 at 3 m; threshold 200
    assert (cam.acquire(Scene.circle(1.0, albedo=dark), 0.0).range_mm == 1000).all()
    far = cam.acquire(Scene.circle(3.0, albedo=dark), 0.0)
    assert not far.range_mm.any() and not far.intensity.any()
    assert (cam.acquire(Scene.circle(3.0, albedo=0.6), 0.0).range_mm == 3000).all()


# --- noise ----------------------------------------------------------------------------------------


def range_errors(radius: float, acquisitions: int, seed: int) -> np.ndarray:
    cam = optics(noise=True, seed=seed)
    scene = Scene.circle(radius)
    frames = [cam.acquire(scene, 0.1 * k).range_mm[1:] for k in range(acquisitions)]
    return np.concatenate(frames).astype(float) / 1000.0 - radius


def test_noise_grows_with_the_square_of_range() -> None:
    params = OpticsParams()
    near = range_errors(1.0, 150, seed=11)
    far = range_errors(3.0, 150, seed=12)
    assert near.size == far.size == 150 * 64  # no dropped rows at either range
    assert near.std() == pytest.approx(params.sigma_z_m(1.0), rel=0.05)  # 5.7 mm
    assert far.std() == pytest.approx(params.sigma_z_m(3.0), rel=0.05)  # 51 mm
    assert far.std() / near.std() == pytest.approx(9.0, rel=0.08)
    assert abs(near.mean()) < 0.001 and abs(far.mean()) < 0.005  # unbiased to first order


def test_same_seed_same_frames_other_seed_other_frames() -> None:
    scene = Scene.room()

    def run(seed: int) -> list[np.ndarray]:
        cam = optics(noise=True, seed=seed)
        out = []
        for k in range(5):
            a = cam.acquire(scene, 0.3 * k)
            out += [a.range_mm, a.intensity]
        return out

    first, again, other = run(42), run(42), run(43)
    for x, y in zip(first, again, strict=True):
        np.testing.assert_array_equal(x, y)
    assert any(not np.array_equal(x, y) for x, y in zip(first, other, strict=True))


def test_noise_off_ignores_the_generator() -> None:
    rng = np.random.default_rng(1)
    state = rng.bit_generator.state
    BirisOptics(64, rng, noise=False).acquire(Scene.room(), 0.2)
    assert rng.bit_generator.state == state


# --- calibration ----------------------------------------------------------------------------------


def test_matched_calibration_changes_nothing() -> None:
    scene = Scene.room()
    for tilt in (0.0, 0.2):
        plain = optics(noise=True, seed=3).acquire(scene, 0.5, tilt_rad=tilt)
        matched = optics(noise=True, seed=3).acquire(scene, 0.5, tilt_rad=tilt, lut_tilt_rad=tilt)
        np.testing.assert_array_equal(plain.range_mm, matched.range_mm)
        np.testing.assert_array_equal(plain.intensity, matched.intensity)


def test_mismatched_calibration_bends_the_profile_as_documented() -> None:
    cam = optics()
    scene = Scene.circle(2.0)
    lut = 0.2
    a = cam.acquire(scene, 0.0, lut_tilt_rad=lut)
    e = cam.elevations
    offset = cam.params.lut_offset_m_per_rad * (0.0 - lut)
    expected = np.rint(1000.0 * (2.0 * np.cos(e) / np.cos(lut + e) + offset))
    np.testing.assert_array_equal(a.range_mm[1:], expected)
    rows = a.range_mm[1:].astype(int)
    assert rows.max() - rows.min() > 100  # a flat-depth wall no longer reads flat
    assert a.range_mm[0] == rows.min()
    assert (a.intensity[1:] == cam.acquire(scene, 0.0).intensity[1:]).all()  # light unchanged

"""sim.scene: shapes, ready-made scenes, the ray caster (both paths) and the plan views."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sim.scene import DEFAULT_ROOM_ORIGIN, Box, Cylinder, Plane, Scene, Wall, polygon_walls

HEAD = np.array([0.0, 0.0, 0.5])


def fan(azimuth: float, elevations: np.ndarray) -> np.ndarray:
    """Unit rays sharing one heading, as one BIRIS profile's rows are."""
    return np.column_stack(
        (
            np.cos(elevations) * math.cos(azimuth),
            np.cos(elevations) * math.sin(azimuth),
            np.sin(elevations),
        )
    )


def level(azimuth: float) -> np.ndarray:
    return fan(azimuth, np.zeros(1))


EMPTY_ROOM = Scene.room(obstacles=[])
X0, Y0 = DEFAULT_ROOM_ORIGIN
X1, Y1 = X0 + 5.0, Y0 + 6.0  # default depth 5 m along x, width 6 m along y


# --- casting --------------------------------------------------------------------------------------


@pytest.mark.parametrize("radius", [0.4, 1.0, 3.3])
def test_circle_is_at_its_radius_horizontally_for_every_elevation(radius: float) -> None:
    scene = Scene.circle(radius)
    elevations = np.linspace(0.6, -0.6, 9)
    for azimuth in (0.0, 1.0, -2.5, math.pi):
        for cast in (scene.cast, scene.cast_general):
            dist, albedo = cast(HEAD, fan(azimuth, elevations))
            np.testing.assert_allclose(dist * np.cos(elevations), radius, rtol=1e-12)
            np.testing.assert_array_equal(albedo, 0.6)


@pytest.mark.parametrize(
    ("azimuth", "expected"),
    [(0.0, X1), (math.pi, -X0), (math.pi / 2, Y1), (-math.pi / 2, -Y0)],
)
def test_room_walls_are_where_the_room_arguments_put_them(azimuth: float, expected: float) -> None:
    dist, albedo = EMPTY_ROOM.cast(HEAD, level(azimuth))
    assert dist[0] == pytest.approx(expected, abs=1e-12)
    assert albedo[0] == 0.6


def test_room_with_its_own_origin_and_size() -> None:
    scene = Scene.room(width_m=4.0, depth_m=3.0, origin=(-1.0, -0.5), obstacles=[])
    got = [scene.cast(HEAD, level(a))[0][0] for a in (0.0, math.pi / 2, math.pi, -math.pi / 2)]
    np.testing.assert_allclose(got, [2.0, 3.5, 1.0, 0.5], atol=1e-12)


def test_default_room_is_asymmetric_and_has_obstacles_within_range() -> None:
    room = Scene.room()
    assert X1 != -X0 and Y1 != -Y0
    obstacles = [s for s in room.shapes if isinstance(s, (Box, Cylinder))]
    assert len(obstacles) >= 3
    assert any(isinstance(s, Cylinder) for s in obstacles)
    for s in obstacles:
        assert math.hypot(*s.center) < 3.5
        assert X0 < s.center[0] < X1 and Y0 < s.center[1] < Y1


def test_a_box_in_front_shortens_the_range_and_lends_its_albedo() -> None:
    box = Box(center=(1.5, 0.0), size=(0.4, 0.6), height=1.0, albedo=0.3)
    before, _ = EMPTY_ROOM.cast(HEAD, level(0.0))
    after, albedo = EMPTY_ROOM.with_shapes(box).cast(HEAD, level(0.0))
    assert before[0] == pytest.approx(X1)
    assert after[0] == pytest.approx(1.3, abs=1e-12)
    assert albedo[0] == 0.3


def test_a_turned_box_is_hit_on_its_turned_face() -> None:
    # A 45-degree box with a corner pointing at the sensor: the level ray meets the corner.
    half = 0.5
    box = Box(center=(2.0, 0.0), size=(2 * half, 2 * half), height=1.0, yaw=math.pi / 4)
    dist, _ = Scene([box]).cast(HEAD, level(0.0))
    assert dist[0] == pytest.approx(2.0 - half * math.sqrt(2.0), abs=1e-12)


def test_a_low_box_is_seen_on_its_top_by_rays_going_down() -> None:
    box = Box(center=(1.5, 0.0), size=(1.0, 1.0), height=0.2)
    scene = Scene([box])
    down = -math.atan2(0.3, 1.5)  # reaches z = 0.2 at 1.5 m, over the middle of the top
    dist, _ = scene.cast(HEAD, fan(0.0, np.array([0.0, down])))
    assert dist[0] == np.inf  # the level ray passes over it
    assert dist[1] == pytest.approx(math.hypot(1.5, 0.3), abs=1e-12)


def test_a_cylinder_seen_from_outside_and_its_top() -> None:
    post = Cylinder(center=(0.0, 2.0), radius=0.25, height=0.3)
    scene = Scene([post])
    down = -math.atan2(0.2, 2.0)  # reaches z = 0.3 above the post's centre
    dist, _ = scene.cast(HEAD, fan(math.pi / 2, np.array([-0.2, down])))
    assert dist[0] == pytest.approx(1.75 / math.cos(0.2), abs=1e-12)
    assert dist[1] == pytest.approx(math.hypot(2.0, 0.2), abs=1e-12)


def test_floor_and_ceiling_planes() -> None:
    scene = Scene.room(obstacles=[], floor=True, ceiling=True)
    dist, albedo = scene.cast(HEAD, fan(0.3, np.array([-0.4, 1.2])))
    assert dist[0] == pytest.approx(0.5 / math.sin(0.4), abs=1e-12)
    assert dist[1] == pytest.approx(2.0 / math.sin(1.2), abs=1e-12)
    assert albedo[0] != albedo[1]  # floor and ceiling differ, so both were really hit


def test_nothing_hit_is_inf_with_zero_albedo() -> None:
    wall = Wall((2.0, -1.0), (2.0, 1.0), height=1.0)
    dist, albedo = Scene([wall]).cast(HEAD, fan(0.0, np.array([0.0, 0.5])))
    assert dist[0] == pytest.approx(2.0)
    assert dist[1] == np.inf and albedo[1] == 0.0  # over the wall: z = 1.59 at x = 2
    dist, albedo = Scene([]).cast(HEAD, level(0.0))
    assert dist[0] == np.inf and albedo[0] == 0.0


def test_rays_of_mixed_headings_match_one_cast_per_ray() -> None:
    rng = np.random.default_rng(7)
    scene = Scene.room(floor=True, ceiling=True)  # closed: every ray hits something
    d = rng.normal(size=(40, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    dist, albedo = scene.cast(HEAD, d)
    singles = [scene.cast(HEAD, d[i : i + 1]) for i in range(len(d))]
    np.testing.assert_allclose(dist, [s[0][0] for s in singles], rtol=1e-12)
    np.testing.assert_array_equal(albedo, [s[1][0] for s in singles])
    assert np.isfinite(dist).all()


@pytest.mark.parametrize("seed", range(12))
def test_fan_shortcut_agrees_with_the_general_caster(seed: int) -> None:
    rng = np.random.default_rng(seed)
    scene = Scene.room(seed=seed, floor=seed % 2 == 0, ceiling=seed % 3 == 0).with_shapes(
        Wall((rng.uniform(-2, 2), rng.uniform(-2, 2)), (rng.uniform(-2, 2), rng.uniform(-2, 2))),
        Box((rng.uniform(-2, 2), rng.uniform(-2, 2)), (0.5, 0.3), 0.3, yaw=rng.uniform(-3, 3)),
    )
    origin = np.array([rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3), rng.uniform(0.2, 1.2)])
    hits = 0
    for _ in range(20):
        tilt = rng.uniform(-1.2, 1.2)
        d = fan(rng.uniform(-math.pi, math.pi), tilt + np.linspace(0.2, -0.2, 64))
        fast = scene.cast(origin, d)
        slow = scene.cast_general(origin, d)
        np.testing.assert_allclose(fast[0], slow[0], rtol=1e-9, atol=1e-12)
        np.testing.assert_array_equal(fast[1], slow[1])
        hits += int(np.isfinite(fast[0]).sum())
    assert hits > 0


def test_cast_rejects_bad_shapes() -> None:
    with pytest.raises(ValueError, match="origin"):
        EMPTY_ROOM.cast(np.zeros(2), level(0.0))
    with pytest.raises(ValueError, match="directions"):
        EMPTY_ROOM.cast(HEAD, np.zeros(3))


# --- construction ---------------------------------------------------------------------------------


def test_room_is_deterministic_and_seeded_rooms_differ() -> None:
    assert Scene.room().shapes == Scene.room().shapes
    assert Scene.room(seed=3).shapes == Scene.room(seed=3).shapes
    assert Scene.room(seed=3).shapes != Scene.room(seed=4).shapes
    assert Scene.room(seed=3).shapes != Scene.room().shapes
    for seed in range(20):
        obstacles = [s for s in Scene.room(seed=seed).shapes if isinstance(s, (Box, Cylinder))]
        assert len(obstacles) == 3
        assert all(0.8 <= math.hypot(*s.center) <= 3.0 for s in obstacles)


@pytest.mark.parametrize(
    "make",
    [
        lambda: Wall((0.0, 0.0), (0.0, 0.0)),
        lambda: Box((0.0, 0.0), (1.0, 1.0), 1.0, albedo=0.0),
        lambda: Cylinder((0.0, 0.0), -1.0, 1.0),
        lambda: Plane(0.0, albedo=1.5),
        lambda: Scene.room(origin=(0.5, -1.0)),
        lambda: Scene.room(obstacles=[], seed=1),
        lambda: Scene.circle(0.0),
    ],
)
def test_bad_shapes_and_rooms_are_refused(make: object) -> None:
    with pytest.raises(ValueError):
        make()  # type: ignore[operator]


# --- scenes named on a command line ---------------------------------------------------------------


@pytest.mark.parametrize(
    ("spec", "radius"),
    [("circle:2", 2.0), ("circle:0.25", 0.25), ("circle:1e2", 100.0), ("circle:2.50", 2.5)],
)
def test_a_circle_spec_is_that_circle(spec: str, radius: float) -> None:
    """One rule for R: any finite R > 0, beyond BIRIS's 32.767 m reach too (no returns then)."""
    scene = Scene.from_spec(spec)
    (cylinder,) = scene.shapes
    assert isinstance(cylinder, Cylinder) and cylinder.radius == radius
    dist, _ = scene.cast(HEAD, level(0.7))
    assert dist[0] == pytest.approx(radius, rel=1e-12)


def test_the_room_spec_is_the_furnished_room() -> None:
    assert Scene.from_spec("room").shapes == Scene.room().shapes


@pytest.mark.parametrize(
    ("spec", "words"),
    [
        ("cube", "a scene is 'room' or 'circle:R'"),
        ("", "a scene is 'room' or 'circle:R'"),
        ("Room", "a scene is 'room' or 'circle:R'"),
        ("room:3", "a scene is 'room' or 'circle:R'"),
        ("circle", "a scene is 'room' or 'circle:R'"),
        ("circle:", "circle:R needs a radius in metres, a finite R > 0, not ''"),
        ("circle:two", "not 'two'"),
        ("circle:0", "not '0'"),
        ("circle:-1", "not '-1'"),
        ("circle:nan", "not 'nan'"),
        ("circle:inf", "not 'inf'"),
    ],
)
def test_a_bad_spec_is_one_line_saying_why(spec: str, words: str) -> None:
    with pytest.raises(ValueError) as caught:
        Scene.from_spec(spec)
    message = str(caught.value)
    assert words in message and "\n" not in message


# --- plan views -----------------------------------------------------------------------------------


def test_outline_polylines_are_closed() -> None:
    outlines = Scene.room().outline_2d()
    assert len(outlines) == 4  # the room (walls joined) and three obstacles
    for line in outlines:
        assert line.ndim == 2 and line.shape[1] == 2 and len(line) >= 5
        np.testing.assert_array_equal(line[0], line[-1])
    room = outlines[0]
    np.testing.assert_allclose(room[:4], [(X0, Y0), (X1, Y0), (X1, Y1), (X0, Y1)])


def test_cylinder_outline_is_on_its_circle_and_lone_walls_stay_open() -> None:
    scene = Scene([Cylinder((1.0, 2.0), 0.5, 1.0), Wall((0.0, 0.0), (1.0, 0.0))])
    wall, circle = scene.outline_2d()
    np.testing.assert_allclose(np.hypot(circle[:, 0] - 1.0, circle[:, 1] - 2.0), 0.5)
    np.testing.assert_array_equal(wall, [(0.0, 0.0), (1.0, 0.0)])
    square = Scene(polygon_walls([(0, 0), (1, 0), (1, 1), (0, 1)])).outline_2d()
    assert len(square) == 1 and len(square[0]) == 5


def test_distance_to_surface_is_zero_on_every_outline() -> None:
    room = Scene.room()
    for line in room.outline_2d():
        # points along each segment, not just the corners
        t = np.linspace(0.0, 1.0, 7)[:, None]
        points = (line[:-1, None, :] * (1 - t) + line[1:, None, :] * t).reshape(-1, 2)
        # cylinders are drawn as polygons: their chords are within 1 mm of the true circle
        assert room.distance_to_surface_2d(points).max() < 2e-3


def test_distance_to_surface_at_known_points() -> None:
    scene = EMPTY_ROOM.with_shapes(Cylinder((2.0, 2.0), 0.25, 1.0))
    points = np.array([(0.0, 0.0), (2.0, -2.5), (2.0, 2.0), (2.0, 2.6), (10.0, 0.0)])
    expected = [-X0, -Y0 - 2.5, 0.25, 0.35, 10.0 - X1]
    np.testing.assert_allclose(scene.distance_to_surface_2d(points), expected, atol=1e-12)
    assert Scene([Plane()]).distance_to_surface_2d(points)[0] == np.inf

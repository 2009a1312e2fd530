"""The service on a moving robot: ``serve(..., poses=, grid=, proximity=)`` publishes the
vehicle's odometry, its ``odom -> vehicle`` transforms, the deskewed clouds, the certainty grid
and the proximity alarm's answers on keys of their own; without them it publishes nothing new.

The simulated vehicle drives the room while the head sweeps (scaled real time: the service's
Zenoh threads call into the server, which the virtual time base cannot see); a raw Zenoh
subscriber on loopback sees every key the service publishes, with its encoding and counter,
and a remote client subscribes to the grid and the odometry through ``RemoteSensor.subscribe``.
"""

from __future__ import annotations

import contextlib
import struct
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np
import pytest
import zenoh

from biris_hw.io import codec
from biris_hw.io.grid import GridParams
from biris_hw.io.net import connect, serve
from biris_hw.io.net.keys import Keys
from biris_hw.io.net.zconfig import make_config
from biris_hw.io.proximity import DEFAULT_ZONE, RATE_HZ
from biris_hw.opening import open_poses, open_sensor
from sim import Scene
from sim.drives import default_drive
from tests.conftest import RigFactory, until
from tests.net_helpers import endpoint, free_port, warm_up_zenoh

# the Zenoh service's own threads call into the server: scaled real time
pytestmark = pytest.mark.realtime

WAIT = 20.0
MOVING_KEYS = ("odom", "tf", "cloud", "grid", "proximity")


@pytest.fixture(scope="module", autouse=True)
def _zenoh_runtime() -> None:
    warm_up_zenoh()


@dataclass
class Heard:
    """Every publication under one service's prefix: (key suffix, encoding, counter, bytes)."""

    prefix: str
    samples: list[tuple[str, str, int, bytes]] = field(default_factory=list)
    changed: threading.Condition = field(default_factory=threading.Condition)

    def on_sample(self, sample: zenoh.Sample) -> None:
        attachment = sample.attachment
        counter = -1 if attachment is None else struct.unpack("<Q", attachment.to_bytes())[0]
        suffix = str(sample.key_expr)[len(self.prefix) + 1 :]
        with self.changed:
            self.samples.append((suffix, str(sample.encoding), counter, sample.payload.to_bytes()))
            self.changed.notify_all()

    def on(self, suffix: str) -> list[tuple[str, int, bytes]]:
        with self.changed:
            return [(e, n, b) for k, e, n, b in self.samples if k == suffix]


@contextlib.contextmanager
def listening(where: str, name: str) -> Iterator[Heard]:
    """A plain Zenoh session on loopback subscribed to everything service ``name`` publishes."""
    heard = Heard(Keys(name).prefix)
    session = zenoh.open(make_config(connect=[where], multicast=False))
    try:
        session.declare_subscriber(f"{heard.prefix}/**", heard.on_sample)
        yield heard
    finally:
        session.close()  # type: ignore[no-untyped-call]


def _sweep(sensor: object, *targets: float) -> None:
    conn = sensor.open()  # type: ignore[attr-defined]
    conn.wait_idle()
    for to in targets:
        conn.single_scan(to)
        conn.wait_idle()
    conn.close()


def test_a_served_drive_publishes_odometry_transforms_clouds_the_grid_and_the_alarm(
    make_rig: RigFactory,
) -> None:
    scene = Scene.room()
    where = endpoint(free_port())
    grids: list[codec.OccupancyGridMessage] = []
    odoms: list[codec.PoseMessage] = []
    alarms: list[codec.ProximityMessage] = []
    got = threading.Condition()

    def keep(into: list[object]) -> object:
        def on(value: object) -> None:
            with got:
                into.append(value)
                got.notify_all()

        return on

    rig = make_rig(scene=scene, seed=1, trajectory=default_drive(scene))
    with (
        open_sensor(sim=rig) as sensor,
        open_poses(sim=rig) as poses,
        serve(
            sensor,
            name="mv",
            listen=[where],
            multicast=False,
            poses=poses,
            grid=GridParams(),
            proximity=DEFAULT_ZONE,
        ) as svc,
    ):
        assert svc.moving is not None
        with (
            listening(where, "mv") as heard,
            connect("mv", [where], multicast=False) as remote,
        ):
            remote.subscribe("grid", keep(grids))  # type: ignore[arg-type]
            remote.subscribe("odom", keep(odoms))  # type: ignore[arg-type]
            remote.subscribe("proximity", keep(alarms))  # type: ignore[arg-type]
            _sweep(sensor, 90.0, -90.0)
            until(
                lambda: all(heard.on(k) for k in MOVING_KEYS) and grids and odoms and alarms,
                WAIT,
                "odom, tf, cloud, grid and proximity published, and grid, odom and proximity "
                "decoded by a subscriber",
            )
            published = dict(svc.published)
            heard_now = {k: heard.on(k) for k in MOVING_KEYS}
    assert not rig.audit.violations, rig.audit.violations

    # each key carries its type in the encoding, and the service's counter, from 1 upwards
    types = {
        "odom": codec.ODOMETRY,
        "tf": codec.TF_MESSAGE,
        "cloud": codec.POINT_CLOUD2,
        "grid": codec.OCCUPANCY_GRID,
        "proximity": codec.PROXIMITY,
    }
    for key, msgtype in types.items():
        samples = heard_now[key]
        assert all(e.endswith(msgtype) and "cdr" in e for e, _, _ in samples), samples[0][0]
        counters = [n for _, n, _ in samples]
        assert counters == sorted(counters) and counters[0] >= 1
        assert published[key] >= counters[-1]
    # the grid: in odom, cells unknown (-1) or 0..100, some of them known and some occupied
    grid = codec.decode_occupancy_grid(heard_now["grid"][-1][2])
    assert grid.frame_id == "odom"
    assert set(np.unique(grid.data)) <= {-1, *range(101)}
    assert np.any(grid.data >= 0) and np.any(grid.data > 50)
    assert all(g.frame_id == "odom" for g in grids)
    # the proximity alarm: its answers in the vehicle frame, at most RATE_HZ of hardware time
    answers = [codec.decode_proximity(data) for _, _, data in heard_now["proximity"]]
    assert all(a.frame_id == "vehicle" and a.zone_width_m == 0.6 for a in answers)
    proximity_stamps = np.array([a.t for a in answers])
    assert np.all(np.diff(proximity_stamps) >= 1 / RATE_HZ - 1e-9)
    assert all(isinstance(a, codec.ProximityMessage) and a.frame_id == "vehicle" for a in alarms)
    # odometry: odom -> vehicle at the simulator's 50 Hz, each sample once, in order
    assert all((o.frame_id, o.child_frame_id) == ("odom", "vehicle") for o in odoms)
    stamps = np.array([o.sample.t for o in odoms])
    assert np.all(np.diff(stamps) > 0)
    assert np.median(np.diff(stamps)) == pytest.approx(0.02, abs=1e-6)
    # /tf: one odom -> vehicle transform per message, the same samples
    transforms = [codec.decode_tf_poses(data) for _, _, data in heard_now["tf"]]
    assert all(len(t) == 1 for t in transforms)
    tf_stamps = np.array([t[0].t for t in transforms])
    assert np.all(np.diff(tf_stamps) > 0)
    assert np.median(np.diff(tf_stamps)) == pytest.approx(0.02, abs=1e-6)


def test_without_poses_the_service_publishes_nothing_new(make_rig: RigFactory) -> None:
    where = endpoint(free_port())
    rig = make_rig(scene=Scene.room(), seed=2)
    with (
        open_sensor(sim=rig) as sensor,
        serve(sensor, name="still", listen=[where], multicast=False) as svc,
    ):
        assert svc.moving is None
        assert set(svc.published) == {"point", "scan/cw", "scan/ccw", "status", "fault"}
        with listening(where, "still") as heard:
            _sweep(sensor, 30.0)
            until(lambda: heard.on("scan/ccw"), WAIT, "the scan published")
            keys = {k for k, _, _, _ in heard.samples}
    assert keys <= {"point", "scan/cw", "scan/ccw", "status", "fault"}
    assert "point" in keys


def test_a_grid_or_an_alarm_without_poses_or_of_no_kind_is_refused(
    make_rig: RigFactory,
) -> None:
    rig = make_rig(scene=Scene.room(), seed=3)
    with open_sensor(sim=rig) as sensor, open_poses(sim=rig) as poses:
        with pytest.raises(ValueError, match="grid= needs poses="):
            serve(sensor, name="bad", multicast=False, grid=GridParams()).__enter__()
        with pytest.raises(TypeError, match="grid= takes"):
            serve(sensor, name="bad", multicast=False, poses=poses, grid=5).__enter__()
        with pytest.raises(ValueError, match="proximity= needs poses="):
            serve(sensor, name="bad", multicast=False, proximity=DEFAULT_ZONE).__enter__()
        with pytest.raises(TypeError, match="proximity= takes"):
            serve(sensor, name="bad", multicast=False, poses=poses, proximity=5).__enter__()
        # poses alone: the vehicle's keys, neither the grid's nor the alarm's
        with serve(sensor, name="poses", multicast=False, poses=poses) as svc:
            assert set(svc.published) == {
                "point", "scan/cw", "scan/ccw", "status", "fault", "odom", "tf", "cloud"
            }  # fmt: skip

"""Scans that stay sharp on a moving robot: how far wall points land from the true walls.

BIRIS rides on a vehicle (issue 27). A sweep from -90 to +90 degrees lasts about 1.4 s; at 0.5 m/s
on an arc of 3 m the vehicle moves 70 cm and turns 14 degrees meanwhile, so a scan put together
in one frame smears every wall. :func:`biris_hw.io.deskew.deskewed` places each acquisition with
the vehicle's pose at its own time, from the simulator's odometry (50 Hz, without drift: ``odom``
is then the scene's frame) through a :class:`biris_hw.io.pose.PoseBuffer`.

The figure: on virtual time (the run is the same on any host), a simulated BIRIS in
``Scene.room()`` sweeps between -90 and +90 degrees :data:`SWEEPS` times, once with the vehicle
standing at the origin, once with it driving ``Trajectory.arc(speed_mps=0.5, radius_m=3.0)``
(from :data:`DRIVE_FROM_S`, once the server is up: the path then stays inside the room for the
sweeps). For every return the horizontal distance to the nearest true surface
(``Scene.distance_to_surface_2d``: walls, furniture sides) is taken and the median reported:
deskewed, and without deskewing (the whole scan placed with one pose: its middle acquisition's,
the best single choice, and its first's, what a client holding the pose of the scan's start
would do). Standing still all three are one figure. The target is the issue's: deskewed within
1.5 x of standing still.

Twice: with the simulator's range noise (the sensor as simulated: its noise, centimetres at 3 m,
dominates every figure) and without it (the placement alone: what is left is the encoder's
whole counts and its lag behind the head, sub-millimetre). A shorter run of the same
measurement is a test (``tests/test_deskew.py``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from benchmarks.harness import BenchContext, Figure, Target, benchmark, summarise
from biris_hw import BirisServer
from biris_hw.data import Direction, Scan
from biris_hw.io.deskew import deskewed
from biris_hw.opening import open_poses
from sim import Scene, SimulatedBiris, Trajectory

__all__ = ["DRIVE_FROM_S", "RADIUS_M", "SPEED_MPS", "SWEEPS", "Distances", "measure", "moving"]

SPEED_MPS = 0.5
RADIUS_M = 3.0
DRIVE_FROM_S = 8.0
"""Hardware time the vehicle starts driving: just after the server is ready and the head has
gone to -90 degrees (7.8 s with seed 1), so every sweep measured is taken while driving and
the arc stays inside the default room (3.4 m of it by the fourth sweep's end)."""

SWEEPS = 4
"""Sweeps measured: -90 to +90 and back, twice (about 7 s of driving)."""

ENDS_DEG = (90.0, -90.0)


@dataclass(frozen=True)
class Distances:
    """Horizontal distances (m) from every return to the nearest true surface, by placing."""

    deskewed: NDArray[np.float64]
    one_pose_middle: NDArray[np.float64]
    one_pose_first: NDArray[np.float64]
    scans: list[Scan]
    unplaced: int
    """Acquisitions that had no pose (none expected: the buffer is waited for)."""
    deskew_us: list[float]
    """Wall time of each timed :func:`deskewed` call (``timed`` calls per scan)."""

    def medians_mm(self) -> dict[str, float]:
        return {
            "deskewed_mm": 1000.0 * float(np.median(self.deskewed)),
            "one_pose_middle_mm": 1000.0 * float(np.median(self.one_pose_middle)),
            "one_pose_first_mm": 1000.0 * float(np.median(self.one_pose_first)),
        }


def measure(
    trajectory: Trajectory | None,
    *,
    sweeps: int = SWEEPS,
    noise: bool = True,
    seed: int = 1,
    timed: int = 0,
) -> Distances:
    """The distances of :class:`Distances` over ``sweeps`` sweeps between +-90 degrees, in
    ``Scene.room()`` on virtual time, the vehicle following ``trajectory`` (None: standing);
    each scan's :func:`deskewed` timed ``timed`` more times."""
    scene = Scene.room()
    found: dict[str, list[NDArray[np.float64]]] = {"deskewed": [], "middle": [], "first": []}
    scans: list[Scan] = []
    unplaced = 0
    costs: list[float] = []
    with (
        SimulatedBiris(
            scene=scene, seed=seed, noise=noise, clock="virtual", trajectory=trajectory
        ) as rig,
        BirisServer(rig.hardware) as server,
        open_poses(sim=rig) as poses,
    ):
        conn = server.open()
        conn.wait_idle()
        conn.single_scan(ENDS_DEG[1])  # to the start of the first sweep measured
        conn.wait_idle()
        for i in range(sweeps):
            to = ENDS_DEG[i % 2]
            conn.single_scan(to)
            conn.wait_idle()
            scan = conn.request_scan_data(Direction.CCW if to > 0 else Direction.CW)
            if scan is None or scan.n_acq == 0:
                raise RuntimeError(f"sweep {i} to {to:g} deg delivered no scan")
            if not poses.wait_for(float(scan.t[-1]), timeout_hw=1.0):
                raise RuntimeError("the odometry did not reach the scan's last acquisition")
            placed = deskewed(scan, poses)
            for _ in range(timed):
                begun = time.perf_counter_ns()
                deskewed(scan, poses)
                costs.append((time.perf_counter_ns() - begun) / 1000.0)
            unplaced += int(placed.unplaced.size)
            found["deskewed"].append(scene.distance_to_surface_2d(placed.points()[:, :2]))
            in_vehicle = scan.points("vehicle")
            for name, at in (("middle", scan.t[scan.n_acq // 2]), ("first", scan.t[0])):
                one = poses.poses_at(np.full(in_vehicle.shape[0], at)).to_odom(in_vehicle)
                found[name].append(scene.distance_to_surface_2d(one[:, :2]))
            scans.append(scan)
    return Distances(
        np.concatenate(found["deskewed"]),
        np.concatenate(found["middle"]),
        np.concatenate(found["first"]),
        scans,
        unplaced,
        costs,
    )


def _arc() -> Trajectory:
    return Trajectory.arc(speed_mps=SPEED_MPS, radius_m=RADIUS_M, start_s=DRIVE_FROM_S)


def _figures(noise: bool, sweeps: int, timed: int) -> list[Figure]:
    standing = measure(None, sweeps=sweeps, noise=noise)
    driving = measure(_arc(), sweeps=sweeps, noise=noise, timed=timed)
    still = standing.medians_mm()["deskewed_mm"]
    moving_mm = driving.medians_mm()
    key = "moving.wall_distance" + ("" if noise else "_noiseless")
    what = "with the simulator's range noise" if noise else "without range noise (noise=False)"
    figures = [
        Figure(
            key=key,
            values={
                "standing_mm": still,
                **moving_mm,
                "ratio": moving_mm["deskewed_mm"] / still,
                "smear_ratio": moving_mm["one_pose_middle_mm"] / moving_mm["deskewed_mm"],
                "returns": float(driving.deskewed.size),
                "unplaced_acquisitions": float(driving.unplaced),
            },
            unit="mm",
            target=Target("<=", 1.5, on="ratio"),
            method=(
                f"Median horizontal distance from each return to the nearest true surface, "
                f"{what}: Scene.room(), seed 1, 64 samples, virtual time, {sweeps} sweeps between "
                f"-90 and +90 deg; standing_mm with the vehicle standing at the origin; the others "
                f"with it on Trajectory.arc(speed_mps={SPEED_MPS:g}, radius_m={RADIUS_M:g}) from "
                f"t={DRIVE_FROM_S:g} s, placed in odom by deskewed() (each acquisition with the "
                "odometry's pose at its time: 50 Hz, no drift) or with one pose for the whole scan "
                "(its middle or its first acquisition's). ratio = deskewed / standing (target: at "
                "most 1.5), smear_ratio = one_pose_middle / deskewed."
            ),
            note=(
                "Deskewed, a scan taken at 0.5 m/s on an arc lies on the walls as a scan taken "
                "standing still does; placed with one pose it misses them by centimetres."
                if noise
                else ""
            ),
        )
    ]
    if timed:
        scan = driving.scans[-1]
        figures.append(
            Figure(
                key="moving.deskew_cost_us",
                values=summarise(driving.deskew_us),
                unit="us",
                target=Target("<=", 3300.0, on="p50"),
                method=(
                    f"Wall time of deskewed(scan, poses) for each scan of the driving run "
                    f"({scan.n_acq} acquisitions of {scan.samples} samples), {timed} times "
                    "each against the run's pose buffer: the pose lookup of every acquisition "
                    "and the placing of every sample, one thread. Target: a tenth of an "
                    "acquisition period (33 ms at 30 Hz) per scan, so a client places every "
                    "scan as it arrives and hardly notices."
                ),
            )
        )
    return figures


@benchmark("moving")
def moving(ctx: BenchContext) -> list[Figure]:
    """Wall points' distance to the true walls, deskewed or not, driving at 0.5 m/s."""
    sweeps = ctx.pick(full=SWEEPS, quick=2)
    timed = ctx.pick(full=500, quick=50)
    return [*_figures(True, sweeps, timed), *_figures(False, sweeps, 0)]

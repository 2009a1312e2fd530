"""Scans that stay sharp while the vehicle drives: each acquisition placed with its own pose.

A sweep lasts most of a second (90 degrees in about 0.8 s); at 0.5 m/s the vehicle carrying the
head moves 40 cm meanwhile, and turns too on a curve. Each acquisition's profile is exact in the
``vehicle`` frame *of its own moment*; put together in one frame, as if the vehicle had stood
still, they smear every wall by the distance driven. :func:`deskewed` places acquisition k with
the vehicle's pose at ``scan.t[k]`` (the middle of its exposure), looked up in a
:class:`~biris_hw.io.pose.PoseBuffer`, so the scan lies in ``odom`` as sharp as one taken
standing still: one array operation for the whole scan (the grid of
:func:`biris_hw.geometry.project_profiles`, rotated and shifted row by row).

An acquisition for which the buffer has no pose within its bounds is not placed: its row is
NaN, and :attr:`DeskewedScan.placed` says which. ``scan.points("odom", poses=buffer)`` is the
strict form, which refuses a scan with any acquisition unplaced.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from biris_hw.data import PoseLookup, Scan, VehiclePoses
from biris_hw.geometry import project_profiles

__all__ = ["DeskewedScan", "deskewed"]


@dataclass(frozen=True, eq=False)
class DeskewedScan:
    """A scan placed in ``odom``, acquisition by acquisition (made by :func:`deskewed`)."""

    scan: Scan
    poses: VehiclePoses
    """The vehicle's pose at each acquisition's time (``valid`` False: none known)."""
    grid: NDArray[np.float64]
    """``(n_acq, samples, 3)``, metres in ``odom``: sample j of acquisition k at ``[k, j]``;
    NaN for no return, and for every sample of an acquisition without a pose."""

    @property
    def placed(self) -> NDArray[np.bool_]:
        """Per acquisition: True if it has a pose and is placed."""
        return self.poses.valid

    @property
    def unplaced(self) -> NDArray[np.intp]:
        """The indices of the acquisitions without a pose (empty when all are placed)."""
        return np.flatnonzero(~self.poses.valid)

    @property
    def complete(self) -> bool:
        """True when every acquisition is placed."""
        return bool(self.poses.valid.all())

    def points(self) -> NDArray[np.float64]:
        """The placed returns as an ``(m, 3)`` array in ``odom``: those of ``scan.points()``, in
        its order, less the acquisitions without a pose."""
        keep = (self.scan.range_mm > 0) & self.poses.valid[:, np.newaxis]
        return np.ascontiguousarray(self.grid[keep])


def deskewed(scan: Scan, poses: PoseLookup) -> DeskewedScan:
    """``scan`` in ``odom``, each acquisition placed with the vehicle's pose at its own time
    (``poses.poses_at(scan.t)``: a :class:`~biris_hw.io.pose.PoseBuffer`, on the same
    hardware clock as the scan). The mount is the scan's (``scan.mount``)."""
    at = poses.poses_at(scan.t)
    if at.t.shape != scan.t.shape:
        raise ValueError(f"poses gave {at.t.shape[0]} poses for {scan.n_acq} acquisitions")
    vehicle = project_profiles(scan.range_mm, scan.azimuth, scan.elevation, "vehicle", scan.mount)
    return DeskewedScan(scan, at, at.to_odom(vehicle))

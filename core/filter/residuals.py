"""Scan residuals: each point's distance to the map for the scan placed at a pose, read from the
lookup table the particle filter reads (so the distances are the filter's: capped at d_max,
within δ·√3/2 + half a code step of the true nearest-point distance, see
:mod:`lidarloc.core.maps.lookup`).

A snapshot's ``scan_world`` is the prepared scan placed at the estimate; the same scan at any other
pose T (a particle, the truth) is T · inv(T_est) · p (:func:`move_scan`). The share of points at
d_max or beyond is the complement of the localizer's inlier share
(:func:`~lidarloc.core.filter.likelihood.residual_stats`): points the map does not explain at that pose.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import LidarlocError
from ..geometry import as_points, inv_pose, pose_matrix
from ..maps.lookup import LookupTable


def as_pose(pose) -> np.ndarray:
    """A 4×4 pose from a 4×4 matrix or a state (x, y, z, yaw, pitch, roll, …)."""
    p = np.asarray(pose, dtype=np.float64)
    if p.shape == (4, 4):
        return p
    p = p.reshape(-1)
    if p.shape[0] < 6:
        raise LidarlocError(f"a pose is a 4×4 matrix or (x, y, z, yaw, pitch, roll); got {p.shape[0]} values")
    return pose_matrix(*p[:6])


def move_scan(points_world: np.ndarray, from_pose, to_pose) -> np.ndarray:
    """(M, 3) float32: points placed at ``from_pose`` (world frame) moved to ``to_pose``:
    to · inv(from) · p."""
    pts = as_points(points_world)
    T = as_pose(to_pose) @ inv_pose(as_pose(from_pose))
    return (pts[:, :3].astype(np.float64) @ T[:3, :3].T + T[:3, 3]).astype(np.float32)


@dataclass(frozen=True)
class Residuals:
    """One scan's residuals at one pose."""

    points: np.ndarray  # (M, 3) float32 world points of the scan at the pose
    distance: np.ndarray  # (M,) float32 lookup distance to the map (m), capped at d_max
    d_max: float  # m, the cap used

    @property
    def share_beyond(self) -> float:
        """Share of points at d_max or beyond (0.0 for an empty scan)."""
        # distances are float32, capped at float32(d_max): compare in the same precision
        return float(np.mean(self.distance >= np.float32(self.d_max))) if len(self.distance) else 0.0


def scan_residuals(points_world: np.ndarray, lookup: LookupTable, d_max: float) -> Residuals:
    """The lookup-table distance of every (M, ≥3) world point to the map, capped at ``d_max``
    (and at the table's built d_max)."""
    pts = as_points(points_world)
    d_max = float(d_max)
    if not d_max > 0:
        raise LidarlocError(f"d_max must be > 0, got {d_max}")
    cap = lookup.capped(d_max)
    dist = lookup.query(pts, cap)
    return Residuals(points=np.ascontiguousarray(pts[:, :3], dtype=np.float32), distance=dist, d_max=cap)

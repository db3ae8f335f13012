"""Motion skew of a spinning LiDAR, and de-skewing a scan with the sensor's motion.

Sweep convention (the same for the generated town's simulated skew and for de-skewing, so that
de-skewing a skewed scan with the true motion gives back the unskewed scan):

- a scan is reported in the sensor frame at **mid-sweep**; the sequence's pose of the scan is
  the pose at mid-sweep;
- the head turns clockwise seen from above (azimuth decreasing), starting and ending behind the
  car (azimuth π);
- a point at azimuth ``az = atan2(y, x)`` (sensor frame) was measured at the time offset
  ``(f − 0.5) · period`` from mid-sweep, ``f = ((π − az) mod 2π) / 2π``: the first points of a
  sweep (just right of straight behind) at −period/2, the points straight ahead at 0, the last
  ones (just left of straight behind) at +period/2.

A raw (skewed) point is where the sensor saw it *from where the sensor was at its firing time*:
its coordinates are in the sensor frame at that time, not at mid-sweep.

Motion model of :func:`deskew`: over one sweep the sensor moves with a constant linear velocity
``v`` and a constant angular velocity ``ω``, both expressed in the mid-sweep sensor frame. The
sensor's pose at offset τ relative to its mid-sweep pose is ``(R(τ), τ·v)`` with
``R(τ) = exp(τ·[ω]×)`` (rotation and translation are interpolated independently, as scipy's
Slerp plus a linear translation do, rather than along a screw); a point p measured at τ is, in
the mid-sweep frame, ``R(τ)·p + τ·v``. At 10 Hz a sweep lasts 0.1 s, over which a car's
acceleration and the screw/straight-line difference move a point by millimetres.
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import LidarlocError


def sweep_period(timestamps, fallback: float) -> float:
    """One sweep's duration, s: a spinning sensor reports a scan per turn, so one sweep lasts one
    scan interval (the median of the positive gaps between ``timestamps``); ``fallback`` without any."""
    gaps = np.diff(np.asarray(timestamps, dtype=np.float64))
    gaps = gaps[gaps > 0]
    return float(np.median(gaps)) if gaps.size else float(fallback)


def sweep_fraction(azimuth: np.ndarray) -> np.ndarray:
    """Share of the sweep done when the head pointed at ``azimuth`` (rad, atan2(y, x)): 0 just
    after straight behind, 0.5 straight ahead, → 1 at straight behind again."""
    return np.mod(math.pi - np.asarray(azimuth, np.float64), 2.0 * math.pi) / (2.0 * math.pi)


def sweep_offsets(points: np.ndarray, period: float) -> np.ndarray:
    """(n,) float64 seconds from mid-sweep at which each point of a scan was measured, from its
    azimuth in the sensor frame (see the module's sweep convention). ``period`` is one sweep, s."""
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] < 2:
        raise LidarlocError(f"sweep_offsets: points must be (n, ≥2), got shape {points.shape}")
    if not period > 0:
        raise LidarlocError(f"sweep_offsets: period must be > 0 s, got {period}")
    azimuth = np.arctan2(points[:, 1].astype(np.float64), points[:, 0].astype(np.float64))
    return (sweep_fraction(azimuth) - 0.5) * float(period)


def _rotate(points: np.ndarray, rotvec: np.ndarray) -> np.ndarray:
    """Rodrigues' rotation of each point (n, 3) by its own rotation vector (n, 3)."""
    theta = np.linalg.norm(rotvec, axis=1)
    axis = rotvec / np.maximum(theta, 1e-300)[:, None]
    cos, sin = np.cos(theta)[:, None], np.sin(theta)[:, None]
    along = np.einsum("ij,ij->i", axis, points)[:, None]
    return points * cos + np.cross(axis, points) * sin + axis * along * (1.0 - cos)


def deskew(points: np.ndarray, offsets: np.ndarray, velocity, angular_velocity) -> np.ndarray:
    """Move every point of a scan into the mid-sweep sensor frame.

    ``points`` (n, ≥3), x, y, z first (further columns, e.g. intensity, are kept); ``offsets``
    (n,) s from mid-sweep (:func:`sweep_offsets`); ``velocity`` (3,) m/s and
    ``angular_velocity`` (3,) rad/s of the sensor, constant over the sweep, in the mid-sweep
    sensor frame (see the module docstring for the model). Returns an array of the same shape
    and dtype."""
    points = np.asarray(points)
    offsets = np.asarray(offsets, np.float64)
    v = np.asarray(velocity, np.float64).reshape(3)
    w = np.asarray(angular_velocity, np.float64).reshape(3)
    if points.ndim != 2 or points.shape[1] < 3 or offsets.shape != (len(points),):
        raise LidarlocError(f"deskew: points (n, ≥3) and offsets (n,) expected, got {points.shape} and {offsets.shape}")
    xyz = points[:, :3].astype(np.float64)
    moved = _rotate(xyz, offsets[:, None] * w[None]) + offsets[:, None] * v[None]
    out = points.copy()
    out[:, :3] = moved
    return out


def twist_from_relative_pose(T_rel: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """(velocity (3,) m/s, angular velocity (3,) rad/s) in the later frame, for a sensor that
    moved by ``T_rel`` (the later sensor pose in the earlier one's frame, 4×4) in ``dt`` seconds
    at constant velocity: the form :func:`deskew` takes, e.g. from one odometry step."""
    from scipy.spatial.transform import Rotation

    if not dt > 0:
        raise LidarlocError(f"twist_from_relative_pose: dt must be > 0 s, got {dt}")
    T_rel = np.asarray(T_rel, np.float64)
    R = T_rel[:3, :3]
    rotvec = Rotation.from_matrix(R).as_rotvec()
    return R.T @ T_rel[:3, 3] / dt, rotvec / dt

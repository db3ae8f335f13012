"""Poses and angles. Z-Y-X Euler angles (yaw about z, then pitch about y, then roll about x),
body x forward, z up, as in the paper's dynamic model. Everything in radians and metres."""

from __future__ import annotations

import numpy as np

from .errors import LidarlocError


def wrap_angle(a):
    """Wrap angles to [-π, π)."""
    return (np.asarray(a) + np.pi) % (2.0 * np.pi) - np.pi


def rotation_zyx(yaw, pitch, roll) -> np.ndarray:
    """R = Rz(yaw) · Ry(pitch) · Rx(roll). Vectorised: inputs of shape (N,) give (N, 3, 3)."""
    yaw, pitch, roll = np.broadcast_arrays(np.asarray(yaw, float), np.asarray(pitch, float), np.asarray(roll, float))
    cy, sy = np.cos(yaw), np.sin(yaw)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cr, sr = np.cos(roll), np.sin(roll)
    R = np.empty(yaw.shape + (3, 3))
    R[..., 0, 0] = cy * cp
    R[..., 0, 1] = cy * sp * sr - sy * cr
    R[..., 0, 2] = cy * sp * cr + sy * sr
    R[..., 1, 0] = sy * cp
    R[..., 1, 1] = sy * sp * sr + cy * cr
    R[..., 1, 2] = sy * sp * cr - cy * sr
    R[..., 2, 0] = -sp
    R[..., 2, 1] = cp * sr
    R[..., 2, 2] = cp * cr
    return R


def euler_zyx(R: np.ndarray) -> np.ndarray:
    """Inverse of :func:`rotation_zyx`: (..., 3, 3) → (..., 3) as [yaw, pitch, roll]."""
    R = np.asarray(R, float)
    yaw = np.arctan2(R[..., 1, 0], R[..., 0, 0])
    pitch = np.arcsin(np.clip(-R[..., 2, 0], -1.0, 1.0))
    roll = np.arctan2(R[..., 2, 1], R[..., 2, 2])
    return np.stack([yaw, pitch, roll], axis=-1)


def pose_matrix(x, y, z, yaw, pitch, roll) -> np.ndarray:
    """4×4 homogeneous transform (vectorised like :func:`rotation_zyx`)."""
    R = rotation_zyx(yaw, pitch, roll)
    T = np.zeros(R.shape[:-2] + (4, 4))
    T[..., :3, :3] = R
    T[..., 0, 3] = x
    T[..., 1, 3] = y
    T[..., 2, 3] = z
    T[..., 3, 3] = 1.0
    return T


def pose_to_xyz_ypr(T: np.ndarray) -> np.ndarray:
    """4×4 (or (..., 4, 4)) → [x, y, z, yaw, pitch, roll]."""
    T = np.asarray(T, float)
    return np.concatenate([T[..., :3, 3], euler_zyx(T[..., :3, :3])], axis=-1)


def inv_pose(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4×4 transform without a general matrix inverse."""
    T = np.asarray(T, float)
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    out = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    out[..., 3, 3] = 1.0
    return out


def levelled(points: np.ndarray, pitch: float, roll: float) -> np.ndarray:
    """(N, 3): ``points`` turned by ``pitch`` and ``roll`` (yaw 0), as a scan is levelled for the
    bird's-eye view. With both 0 (every whole-map match without a start) the points themselves:
    the product with the identity is exact, and numpy's threaded product of a scan by a 3 × 3
    costs 5–100 ms on two busy cores (measured beside other jobs), for nothing."""
    pts = np.asarray(points)[:, :3]
    if pitch == 0.0 and roll == 0.0:
        return pts
    return pts @ rotation_zyx(0.0, pitch, roll).T


def transform_points(T: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Apply a 4×4 transform to (N, ≥3) points; returns (N, 3)."""
    pts = np.asarray(pts)
    return pts[:, :3] @ T[:3, :3].T + T[:3, 3]


def as_points(points) -> np.ndarray:
    """``points`` as an (M, ≥3) array (not copied), or a one-line error naming the shape it has."""
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] < 3:
        raise LidarlocError(f"scan must be (M, ≥3); got shape {pts.shape}")
    return pts

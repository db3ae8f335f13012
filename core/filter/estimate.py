"""The particle filter's summary after an update: what the localizer, its rules and the viewer read."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..geometry import pose_matrix


@dataclass(frozen=True)
class Estimate:
    """The filter's summary after an update (weights as they were when it was computed)."""

    state: np.ndarray  # (11,) weighted mean; circular mean for yaw, pitch, roll
    pose: np.ndarray  # 4×4 of the mean state (world ← LiDAR)
    cov_xyz: np.ndarray  # (3, 3) weighted covariance of x, y, z
    std_xyz: np.ndarray  # (3,) per-axis position std (√diag cov_xyz)
    ellipse_xy: tuple  # 2σ x-y ellipse: (semi-major, semi-minor, angle of major axis, rad)
    state_std: np.ndarray  # (11,) per-entry weighted std (circular std for the angles)
    n_eff: float  # 1 / Σ w²
    best_index: int  # particle with the highest weight
    resampled: bool = False  # set by step(): whether this step resampled afterwards


def weighted_estimate(states: np.ndarray, weights: np.ndarray, log_weights: np.ndarray) -> Estimate:
    """The filter's estimate from its particles: the weighted mean state (circular means for the
    angles), the x-y-z covariance and its 2σ x-y ellipse, per-entry stds, N_eff and the best particle
    (by log-weight, whose order survives when the weights underflow to 0)."""
    w = weights
    s = states
    mean = w @ s
    angles = s[:, 3:6]
    c, si = w @ np.cos(angles), w @ np.sin(angles)
    mean[3:6] = np.arctan2(si, c)
    resultant = np.clip(np.hypot(c, si), 1e-300, 1.0)
    d = s - mean
    var = w @ (d * d)
    state_std = np.sqrt(np.maximum(var, 0.0))
    state_std[3:6] = np.sqrt(-2.0 * np.log(resultant))  # circular std
    dp = d[:, :3]
    cov = (dp * w[:, None]).T @ dp
    cov = 0.5 * (cov + cov.T)
    evals, evecs = np.linalg.eigh(cov[:2, :2])
    evals = np.maximum(evals, 0.0)
    major = evecs[:, 1]
    ellipse = (2.0 * math.sqrt(evals[1]), 2.0 * math.sqrt(evals[0]), float(math.atan2(major[1], major[0])))
    pose = pose_matrix(*mean[:6])
    return Estimate(
        state=mean,
        pose=pose,
        cov_xyz=cov,
        std_xyz=np.sqrt(np.maximum(np.diag(cov), 0.0)),
        ellipse_xy=ellipse,
        state_std=state_std,
        n_eff=float(1.0 / np.dot(w, w)),
        best_index=int(np.argmax(log_weights)),
    )

"""Carrying a match forward (paper, eq. of "Particle state correction"): a match computed for scan
k lands at a later scan k' and is propagated as H(ξ_k') = H_(k',k) · H(ξ_k). The paper composes on
the left, so its H are sensor ← world transforms (H_k = H_(k,k−1) ⋯ H_(1,0) H_0 maps world into
sensor k). With this project's world ← LiDAR matrices T = H⁻¹ and odometry poses O_k = T_odom←k,
the paper's H_(k',k) = T_k'←k = inv(O_k')·O_k, so T_w←k' = H(ξ_k')⁻¹ = H(ξ_k)⁻¹ · H_(k',k)⁻¹
= T_w←k · inv(O_k) · O_k'. :func:`carry_forward` implements exactly that."""

from __future__ import annotations

import numpy as np

from ..geometry import inv_pose


def carry_forward_poses(T_w_k: np.ndarray, odom_k: np.ndarray, odom_k_prime: np.ndarray) -> np.ndarray:
    """Propagate a world ← LiDAR pose of scan k to scan k' with the odometry poses of both scans
    (T_odom←k, T_odom←k'): T_w←k' = T_w←k · inv(O_k) · O_k' (the paper's H(ξ_k') = H_(k',k)·H(ξ_k)
    for sensor ← world H; see the module docstring)."""
    return np.asarray(T_w_k, float) @ inv_pose(np.asarray(odom_k, float)) @ np.asarray(odom_k_prime, float)


def carry_forward(T_match_k: np.ndarray, rpe, k: int, k_prime: int) -> np.ndarray:
    """:func:`carry_forward_poses` with the odometry of a
    :class:`~lidarloc.core.odometry.rpe.RelativePoseEstimator` (``rpe.relative(k, k')`` = inv(O_k)·O_k')."""
    return np.asarray(T_match_k, float) @ rpe.relative(k, k_prime)

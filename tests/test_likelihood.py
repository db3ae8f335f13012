"""The particle weights (core/filter/likelihood.py): the paper's truncated sum of squared lookup
distances, misses for poses off the grid, the floored variant's identical weights, and on the
real drive the true pose scoring higher than perturbed ones."""

import math

import numpy as np
from helpers import assert_floor_keeps_the_weights
from lidarloc.core.filter.likelihood import log_likelihood, log_likelihood_floored
from lidarloc.core.filter.scanprep import voxel_downsample_random
from lidarloc.core.geometry import pose_matrix, pose_to_xyz_ypr, transform_points

DEG = math.pi / 180


def test_log_likelihood_is_the_papers_sum(toy_world):
    pts, table = toy_world
    rng = np.random.default_rng(0)
    scan = pts[rng.integers(0, len(pts), 3000)] - [12, 10, 1.7]
    states = np.zeros((40, 11))
    states[:, :3] = [12, 10, 1.7] + rng.normal(0, 1.5, (40, 3))
    states[:, 3:6] = rng.normal(0, 0.1, (40, 3))
    for d_max, sigma in [(5.0, 0.5), (2.0, 0.5), (5.0, 1.3)]:
        ll = log_likelihood(states, scan, table, d_max, sigma)
        expected = []
        for s in states:
            world_pts = transform_points(pose_matrix(*s[:6]), scan)
            d = table.query(world_pts, d_max=d_max).astype(np.float64)
            expected.append(-np.sum(np.minimum(d * d, d_max * d_max)) / sigma**2)
        np.testing.assert_allclose(ll, expected, rtol=1e-4)
    # the parallel kernel (> 64 particles) and its serial twin give the same sums bit for bit:
    # PF.reweight() (one particle) must agree exactly with PF.update() (all of them)
    many = np.repeat(states, 3, axis=0)
    np.testing.assert_array_equal(
        log_likelihood(many, scan, table, 5.0, 0.5)[::3], log_likelihood(states, scan, table, 5.0, 0.5)
    )
    # a lower d_max changes the values (no rebuild: the same table)
    assert not np.allclose(log_likelihood(states, scan, table, 2.0, 0.5), log_likelihood(states, scan, table, 5.0, 0.5))


def test_likelihood_reads_far_or_non_finite_poses_as_misses(toy_world):
    """Particles off the grid — far away, beyond int32 cells, ±inf or NaN — read d_max for
    every point (a miss), never memory outside the table."""
    pts, table = toy_world
    scan = pts[:500] - [12, 10, 1.7]
    states = np.zeros((6, 11))
    states[:, :3] = [[-1e3, 0, 0], [1e12, 1e12, 1e12], [np.inf, 0, 0], [-np.inf, 0, 0], [np.nan, 0, 0], [0, 0, 1e9]]
    for n_copies in (1, 20):  # serial twin and parallel kernel
        ll = log_likelihood(np.repeat(states, n_copies, axis=0), scan, table, 5.0, 0.5)
        np.testing.assert_array_equal(ll, -len(scan) * 5.0**2 / 0.5**2)


def test_floored_likelihood_gives_the_same_weights(toy_world):
    pts, table = toy_world
    rng = np.random.default_rng(1)
    scan = pts[rng.integers(0, len(pts), 4000)] - [15, 12, 1.7]
    states = np.zeros((500, 11))
    states[:, :3] = [15, 12, 1.7] + rng.normal(0, [3, 3, 0.3], (500, 3))
    states[:, 3] = rng.normal(0, 0.3, 500)
    prior = np.log(rng.dirichlet(np.ones(500)))
    exact = prior + log_likelihood(states, scan, table, 5.0, 0.5)
    floored = prior + log_likelihood_floored(states, scan, table, 5.0, 0.5, prior)
    assert_floor_keeps_the_weights(exact, floored, min_floored=100)


def test_true_pose_scores_higher_than_perturbed_poses(kitti_raw_map):
    """On the real drive (its own map), the true pose beats ±1 m and ±2° perturbations."""
    seq, _, table = kitti_raw_map
    offsets = []
    for axis in range(3):  # ±1 m along x, y, z
        for sign in (-1, 1):
            d = np.zeros(6)
            d[axis] = sign * 1.0
            offsets.append(d)
    for axis in range(3, 6):  # ±2° in yaw, pitch, roll
        for sign in (-1, 1):
            d = np.zeros(6)
            d[axis] = sign * 2.0 * DEG
            offsets.append(d)
    offsets = np.array(offsets)
    scans = list(range(2, 100, 5))  # 20 scans spread over the drive
    wins = 0
    for k in scans:
        scan = voxel_downsample_random(seq.scan(k), 0.5, k)
        states = np.zeros((1 + len(offsets), 11))
        states[:, :6] = pose_to_xyz_ypr(seq.pose(k))
        states[1:, :6] += offsets
        ll = log_likelihood(states, scan, table, 5.0, 0.5)
        wins += bool(ll[0] > ll[1:].max())
    assert wins >= math.ceil(0.95 * len(scans)), f"truth best in {wins}/{len(scans)} scans"

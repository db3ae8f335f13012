"""The particle-filter core on real KITTI raw scans (drive 0013) against that drive's map.
Skipped, with the reason, where the licensed data is absent."""

import math

import numpy as np
import pytest

from lidarloc.core.config import MapConfig, PFConfig
from lidarloc.core.geometry import pose_to_xyz_ypr
from lidarloc.core.likelihood import log_likelihood
from lidarloc.core.lookup import LookupTable
from lidarloc.core.mapping import PriorMap, VoxelAccumulator, range_filter
from lidarloc.core.pf import ParticleFilter
from lidarloc.core.scanprep import voxel_downsample_random

DEG = math.pi / 180


@pytest.fixture(scope="module")
def real(kitti_raw_seq):
    """The drive's prior map (all 100 scans fused with their poses, the paper's protocol) and its
    lookup table, built once. Only the 3D points are needed here, so the map is fused with the
    same voxel accumulator as mapping.build_prior_map but without its road-removed BEV copy
    (normal estimation: half of the build time)."""
    cfg = MapConfig()
    acc = VoxelAccumulator(cfg.voxel_size)
    for i in range(len(kitti_raw_seq)):
        T = kitti_raw_seq.pose(i)
        pts = range_filter(kitti_raw_seq.scan(i), cfg)[:, :3].astype(np.float64)
        acc.add(pts @ T[:3, :3].T + T[:3, 3])
    prior = PriorMap(points=acc.points(), points_bev=np.zeros((0, 3), np.float32), voxel_size=cfg.voxel_size)
    return kitti_raw_seq, prior, LookupTable.build(prior.points, 0.25, 5.0)


def test_lookup_matches_kdtree_on_the_real_map(real):
    from scipy.spatial import cKDTree

    _, prior, table = real
    rng = np.random.default_rng(0)
    pts = prior.points
    q = np.concatenate([pts[rng.integers(0, len(pts), 15_000)] + rng.normal(0, 1.0, (15_000, 3)),
                        rng.uniform(pts.min(axis=0), pts.max(axis=0), (15_000, 3))])
    truth = np.minimum(cKDTree(pts).query(q, distance_upper_bound=6.0)[0], 5.0)
    err = np.abs(table.query(q) - truth)
    assert err.max() <= 0.25 * math.sqrt(3) / 2 + table.step / 2 + 1e-6


def test_true_pose_scores_higher_than_perturbed_poses(real):
    seq, _, table = real
    offsets = []
    for axis in range(3):                     # ±1 m along x, y, z
        for sign in (-1, 1):
            d = np.zeros(6)
            d[axis] = sign * 1.0
            offsets.append(d)
    for axis in range(3, 6):                  # ±2° in yaw, pitch, roll
        for sign in (-1, 1):
            d = np.zeros(6)
            d[axis] = sign * 2.0 * DEG
            offsets.append(d)
    offsets = np.array(offsets)
    scans = list(range(2, 100, 5))            # 20 scans spread over the drive
    wins = 0
    for k in scans:
        scan = voxel_downsample_random(seq.scan(k), 0.5, k)
        states = np.zeros((1 + len(offsets), 11))
        states[:, :6] = pose_to_xyz_ypr(seq.pose(k))
        states[1:, :6] += offsets
        ll = log_likelihood(states, scan, table, 5.0, 0.5)
        wins += bool(ll[0] > ll[1:].max())
    assert wins >= math.ceil(0.95 * len(scans)), f"truth best in {wins}/{len(scans)} scans"


def test_filter_step_on_real_scans_tracks_from_near_the_truth(real):
    seq, prior, table = real
    lo, hi = prior.bounds
    pf = ParticleFilter(PFConfig(n_particles=500), table, lo, hi, seed=0, map_points=prior.points)
    pf.initialize(pose=seq.pose(10), pose_std=(1.0, 1.0, 0.2, 3 * DEG, 1 * DEG, 1 * DEG),
                  speed=float(np.linalg.norm(seq.pose(11)[:3, 3] - seq.pose(10)[:3, 3]) / 0.1))
    errors = []
    for k in range(11, 31):
        scan = voxel_downsample_random(seq.scan(k), 0.5, k)
        est = pf.step(scan, seq.timestamp(k) - seq.timestamp(k - 1))
        errors.append(np.linalg.norm(est.state[:3] - seq.pose(k)[:3, 3]))
    assert np.median(errors) < 1.0 and max(errors[5:]) < 2.0, np.round(errors, 2)

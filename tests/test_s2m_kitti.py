"""S2M on real KITTI scans: a real scan, rotated and shifted away from its true pose, is brought
back by M3RSM + GICP to within 0.2 m and 0.5°, in local and in global mode."""

import math

import numpy as np
import pytest

from lidarloc.core.bev import BEVPyramid
from lidarloc.core.config import MapConfig, S2MConfig
from lidarloc.core.geometry import inv_pose, pose_matrix, pose_to_xyz_ypr
from lidarloc.core.mapping import build_prior_map
from lidarloc.core.s2m import ScanToMapMatcher

DEG = math.pi / 180


def pose_error(T, G):
    D = inv_pose(G) @ T
    return float(np.linalg.norm(D[:3, 3])), math.degrees(math.acos(np.clip((np.trace(D[:3, :3]) - 1) / 2, -1, 1)))


@pytest.fixture(scope="module")
def kitti_matcher(kitti_raw_seq):
    prior = build_prior_map(kitti_raw_seq, MapConfig())
    cfg = S2MConfig()
    return ScanToMapMatcher(prior, BEVPyramid.build(prior.points_bev, cfg.match_resolution), cfg)


@pytest.mark.parametrize("k, dx, dy, dyaw", [(50, 7.3, -4.1, 35.0), (63, -11.8, 6.6, -140.0)])
def test_rotated_and_shifted_real_scan_is_recovered_locally(kitti_raw_seq, kitti_matcher, k, dx, dy, dyaw):
    truth = kitti_raw_seq.pose(k)
    x, y, z, yaw, pitch, roll = pose_to_xyz_ypr(truth)
    start = pose_matrix(x + dx, y + dy, z, yaw + dyaw * DEG, pitch, roll)
    out = kitti_matcher.match_local(kitti_raw_seq.scan(k), start)
    assert out.accepted, out.reason
    assert out.score > out.start_score
    dt, dr = pose_error(out.pose, truth)
    assert dt < 0.2 and dr < 0.5, (dt, dr)


def test_real_scan_is_recovered_globally(kitti_raw_seq, kitti_matcher):
    k = 88
    truth = kitti_raw_seq.pose(k)
    out = kitti_matcher.match_global(kitti_raw_seq.scan(k))
    assert out.accepted, out.reason
    dt, dr = pose_error(out.pose, truth)
    assert dt < 0.2 and dr < 0.5, (dt, dr)

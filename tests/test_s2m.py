"""The scan-to-map matcher (core/s2m.py). On a synthetic 3D street scene (walls on a flat
ground): acceptance rule, GICP refinement of the 2D match, global mode's z guess, carry-forward
composition. On real KITTI scans: a scan rotated and shifted away from its true pose is brought
back by M3RSM + GICP to within 0.2 m and 0.5°, in local and in global mode."""

import math

import numpy as np
import pytest

from lidarloc.core.bev import BEVPyramid
from lidarloc.core.config import MapConfig, S2MConfig
from lidarloc.core.geometry import inv_pose, pose_matrix, pose_to_xyz_ypr, transform_points
from lidarloc.core.mapping import PriorMap, build_prior_map
from lidarloc.core.s2m import ScanToMapMatcher, carry_forward, carry_forward_poses

DEG = math.pi / 180
SENSOR_HEIGHT = 1.7


def pose_error(T, G):
    D = inv_pose(G) @ T
    return float(np.linalg.norm(D[:3, 3])), math.degrees(math.acos(np.clip((np.trace(D[:3, :3]) - 1) / 2, -1, 1)))


@pytest.fixture(scope="module")
def scene():
    """Ground at z = 0 (0.4 m grid) and 45 random vertical walls 3–8 m high (0.2 m spacing)."""
    rng = np.random.default_rng(42)
    g = np.arange(0, 140, 0.4)
    gx, gy = np.meshgrid(g, g, indexing="ij")
    ground = np.c_[gx.ravel(), gy.ravel(), np.zeros(gx.size)]
    walls = []
    for _ in range(45):
        a = rng.uniform(5, 135, 2)
        b = a + rng.uniform(-25, 25, 2)
        n = max(int(np.linalg.norm(b - a) / 0.2), 2)
        t = np.linspace(0, 1, n)
        xy = a + (b - a) * t[:, None]
        h = rng.uniform(3, 8)
        for z in np.arange(0.2, h, 0.2):
            walls.append(np.c_[xy, np.full(n, z)])
    walls = np.concatenate(walls)
    walls = walls[(walls[:, :2] >= 0).all(1) & (walls[:, :2] <= 140).all(1)]
    prior = PriorMap(points=np.concatenate([ground, walls]).astype(np.float32),
                     points_bev=walls.astype(np.float32), voxel_size=0.2, source="synthetic")
    return prior


def cut_scan(prior, T, radius=40.0, points=None):
    pts = prior.points if points is None else points
    near = pts[np.hypot(pts[:, 0] - T[0, 3], pts[:, 1] - T[1, 3]) < radius]
    return transform_points(inv_pose(T), near).astype(np.float32)


@pytest.fixture(scope="module")
def matcher(scene):
    cfg = S2MConfig()
    return ScanToMapMatcher(scene, BEVPyramid.build(scene.points_bev, cfg.match_resolution), cfg)


def test_perturbed_start_is_corrected_in_6dof(scene, matcher):
    truth = pose_matrix(70.3, 64.6, SENSOR_HEIGHT, 0.9, 0.0, 0.0)
    scan = cut_scan(scene, truth)
    x, y, z, yaw, pitch, roll = pose_to_xyz_ypr(truth)
    start = pose_matrix(x + 6.2, y - 4.7, z + 0.3, yaw + 25 * DEG, pitch + 1 * DEG, roll - 1 * DEG)
    out = matcher.match_local(scan, start)
    assert out.accepted, out.reason
    assert out.score > out.start_score
    dt, dr = pose_error(out.pose, truth)
    assert dt < 0.1 and dr < 0.3, (dt, dr)
    x0, y0, x1, y1 = out.region
    assert x0 == pytest.approx(start[0, 3] - 25) and y1 == pytest.approx(start[1, 3] + 25)
    assert out.scan_world.shape[1] == 3 and out.ms > 0 and set(out.timings) == {"prepare", "m3rsm", "gicp"}


@pytest.mark.parametrize("level", [True, False])
def test_level_ignores_a_random_attitude_and_height_of_the_start(scene, matcher, level):
    """A particle before localization: position, yaw, z, pitch and roll all wrong (pitch 12°,
    roll −6°, 3 m too high). ``level`` takes pitch = roll = 0 and the map's ground height instead
    and the match is accepted and right; trusting the particle, GICP has to turn the match by more
    than 3 angle steps and it is refused."""
    truth = pose_matrix(70.3, 64.6, SENSOR_HEIGHT, 0.9, 0.0, 0.0)
    scan = cut_scan(scene, truth)
    start = pose_matrix(70.3 + 6.2, 64.6 - 4.7, SENSOR_HEIGHT + 3.0, 0.9 + 25 * DEG, 12 * DEG, -6 * DEG)
    out = matcher.match_local(scan, start, level=level)
    if level:
        assert out.accepted, out.reason
        dt, dr = pose_error(out.pose, truth)
        assert dt < 0.1 and dr < 0.3, (dt, dr)
    else:
        assert not out.accepted and "GICP" in out.reason


def test_match_that_does_not_beat_the_start_is_rejected(scene):
    """Binary cells, and the start is the true pose of a scan made of the map's own wall points: every
    scan cell hits an occupied cell, the highest score any pose can reach, so nothing beats it."""
    cfg = S2MConfig(binary_cells=True)
    matcher = ScanToMapMatcher(scene, BEVPyramid.build(scene.points_bev, 1.0, binary=True), cfg)
    truth = pose_matrix(70.3, 64.6, SENSOR_HEIGHT, 0.9, 0.0, 0.0)
    walls = cut_scan(scene, truth, points=scene.points_bev)
    out = matcher.match_local(walls, truth, road_removed=True)
    assert not out.accepted
    # nothing on the lattice beats it, and GICP from the start (already right) cannot either
    assert "scores higher than the start pose, nor does the start refined by GICP" in out.reason
    assert out.score == out.start_score
    assert np.array_equal(out.pose, truth)


@pytest.mark.parametrize("refine_unbeaten", [True, False])
def test_unbeaten_start_is_refined_by_gicp_only_if_enabled(scene, refine_unbeaten):
    """The search space is cut down to the start pose itself (region below one cell, zero yaw
    window, start yaw on the lattice), so no lattice pose can beat it. With refine_unbeaten the
    start is refined by GICP and accepted because the refined pose scores higher; without, the
    paper's rule rejects it."""
    cfg = S2MConfig(binary_cells=True, region_x=0.4, region_y=0.4, yaw_window=0.0)
    pyr = BEVPyramid.build(scene.points_bev, 1.0, binary=True)
    matcher = ScanToMapMatcher(scene, pyr, cfg, refine_unbeaten=refine_unbeaten)
    yaw = -math.pi + 100 * cfg.angle_step
    truth = pose_matrix(70.3, 64.6, SENSOR_HEIGHT, yaw, 0.0, 0.0)
    start = pose_matrix(70.3 + 0.35, 64.6 - 0.3, SENSOR_HEIGHT + 0.1, yaw, 0.0, 0.0)
    out = matcher.match_local(cut_scan(scene, truth), start)
    if refine_unbeaten:
        assert out.accepted and out.stage == "refined_start", out.reason
        assert out.score > out.start_score
        dt, dr = pose_error(out.pose, truth)
        assert dt < 0.1 and dr < 0.3, (dt, dr)
    else:
        assert not out.accepted and "scores higher than the start" in out.reason
        assert np.array_equal(out.pose, start)


def test_global_match_guesses_z_from_the_map_and_the_scan_ground(scene, matcher):
    truth = pose_matrix(52.8, 81.1, SENSOR_HEIGHT, -2.2, 0.0, 0.0)
    out = matcher.match_global(cut_scan(scene, truth))
    assert out.accepted, out.reason
    assert abs(out.match_pose[2, 3] - SENSOR_HEIGHT) < 0.3     # initial z: ground 0 − scan ground −1.7
    dt, dr = pose_error(out.pose, truth)
    assert dt < 0.1 and dr < 0.3, (dt, dr)


# ----------------------------------------------------------------------------- carry forward
def drive(kind, n=30):
    """True world ← LiDAR poses of a drive: straight, or turning with climbing and banking."""
    poses = []
    x = y = yaw = 0.0
    for k in range(n):
        if kind == "straight":
            poses.append(pose_matrix(2.0 + 1.2 * k, -3.0, 1.7, 0.4, 0.0, 0.0))
            continue
        yaw += 4 * DEG
        x += 1.1 * math.cos(yaw)
        y += 1.1 * math.sin(yaw)
        poses.append(pose_matrix(x, y, 1.7 + 0.05 * k, yaw, 2 * DEG * math.sin(0.2 * k), 1 * DEG * math.cos(0.3 * k)))
    return np.array(poses)


class FakeOdometry:
    """Odometry poses in their own frame (the first scan's), as KISS-ICP reports them."""

    def __init__(self, truth):
        self.O = inv_pose(truth[0])[None] @ truth

    def relative(self, a, b):
        return inv_pose(self.O[a]) @ self.O[b]


@pytest.mark.parametrize("kind", ["straight", "turning"])
def test_carry_forward_propagates_the_match_to_the_landing_scan(kind):
    truth = drive(kind)
    odo = FakeOdometry(truth)
    for k, kp in [(3, 5), (10, 17), (0, 29)]:
        assert np.allclose(carry_forward(truth[k], odo, k, kp), truth[kp], atol=1e-9)
        assert np.allclose(carry_forward_poses(truth[k], odo.O[k], odo.O[kp]), truth[kp], atol=1e-9)
    if kind == "turning":
        # composing on the wrong side is wrong as soon as the vehicle turns
        k, kp = 10, 17
        wrong = odo.relative(k, kp) @ truth[k]
        assert np.linalg.norm(wrong[:3, 3] - truth[kp][:3, 3]) > 0.5


def test_scan_without_vertical_structure_is_rejected(scene, matcher):
    """Only road in view: nothing survives road removal, so there is nothing to match."""
    truth = pose_matrix(70.3, 64.6, SENSOR_HEIGHT, 0.9, 0.0, 0.0)
    ground = scene.points[scene.points[:, 2] == 0.0]
    scan = cut_scan(scene, truth, radius=30.0, points=ground)
    for out in (matcher.match_local(scan, truth), matcher.match_global(scan)):
        assert not out.accepted and "too few" in out.reason


# ----------------------------------------------------------------------------- real KITTI scans
@pytest.fixture(scope="module")
def kitti_matcher(kitti_raw_seq):
    prior = build_prior_map(kitti_raw_seq, MapConfig())
    cfg = S2MConfig()
    return ScanToMapMatcher(prior, BEVPyramid.build(prior.points_bev, cfg.match_resolution), cfg)


@pytest.mark.slow
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


@pytest.mark.slow
def test_real_scan_is_recovered_globally(kitti_raw_seq, kitti_matcher):
    k = 88
    truth = kitti_raw_seq.pose(k)
    out = kitti_matcher.match_global(kitti_raw_seq.scan(k))
    assert out.accepted, out.reason
    dt, dr = pose_error(out.pose, truth)
    assert dt < 0.2 and dr < 0.5, (dt, dr)

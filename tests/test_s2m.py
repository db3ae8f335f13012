"""The scan-to-map matcher (core/matching/s2m.py, carry-forward in carry.py). On a synthetic 3D street scene (walls on a flat
ground): acceptance rule, GICP refinement of the 2D match, global mode's z guess, carry-forward
composition, what an outcome keeps for the inspection. On the town, through the localizer: what
each landed match's view says, also when the match is refused at its landing. On real KITTI
scans: a scan rotated and shifted away from its true pose is brought back by M3RSM + GICP to
within 0.2 m and 0.5°, in local and in global mode."""

import math
import pickle

import numpy as np
import pytest
from helpers import short_town
from lidarloc.core.config import MapConfig, S2MConfig
from lidarloc.core.geometry import inv_pose, pose_matrix, pose_to_xyz_ypr, transform_points
from lidarloc.core.maps.bev import BEVPyramid
from lidarloc.core.maps.mapping import PriorMap, build_prior_map
from lidarloc.core.matching.carry import carry_forward, carry_forward_poses
from lidarloc.core.matching.s2m import ScanToMapMatcher

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
    prior = PriorMap(
        points=np.concatenate([ground, walls]).astype(np.float32),
        points_bev=walls.astype(np.float32),
        voxel_size=0.2,
        source="synthetic",
    )
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


def test_a_start_tilted_beyond_a_vehicles_attitude_is_levelled(scene, matcher):
    """A particle that tumbled (pitch −70°, roll 120°) is not trusted even without ``level``: the
    search levels it and the match is accepted and right, as from a level start."""
    from lidarloc.core.matching.s2m import MAX_TRUSTED_TILT

    truth = pose_matrix(70.3, 64.6, SENSOR_HEIGHT, 0.9, 0.0, 0.0)
    scan = cut_scan(scene, truth)
    start = pose_matrix(70.3 + 6.2, 64.6 - 4.7, SENSOR_HEIGHT + 3.0, 0.9 + 25 * DEG, -70 * DEG, 120 * DEG)
    assert 70 * DEG > MAX_TRUSTED_TILT
    out = matcher.match_local(scan, start)
    assert out.accepted, out.reason
    dt, dr = pose_error(out.pose, truth)
    assert dt < 0.1 and dr < 0.3, (dt, dr)


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
    # what GICP made of the start stays with the rejection, for the inspection
    assert out.stage == "refined_start" and np.array_equal(out.match_pose, truth) and out.gicp is not None
    assert np.all(out.match.candidates[:, 3] <= out.start_score)


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
    assert abs(out.match_pose[2, 3] - SENSOR_HEIGHT) < 0.3  # initial z: ground 0 − scan ground −1.7
    dt, dr = pose_error(out.pose, truth)
    assert dt < 0.1 and dr < 0.3, (dt, dr)


def test_outcome_keeps_what_the_search_and_gicp_did(scene, matcher):
    """The 2D match is the search's best candidate, GICP's correction is the move from it to the
    refined pose, and the whole outcome survives the trip to and from the S2M process."""
    truth = pose_matrix(70.3, 64.6, SENSOR_HEIGHT, 0.9, 0.0, 0.0)
    x, y, z, yaw, _, _ = pose_to_xyz_ypr(truth)
    out = matcher.match_local(cut_scan(scene, truth), pose_matrix(x + 6.2, y - 4.7, z, yaw + 25 * DEG, 0.0, 0.0))
    assert out.accepted and out.stage == "m3rsm", out.reason
    best = out.match.candidates[0]
    assert (best[0], best[1]) == (out.match_pose[0, 3], out.match_pose[1, 3])
    assert best[2] == pytest.approx(pose_to_xyz_ypr(out.match_pose)[3], abs=1e-9) and best[3] == out.score
    assert sum(out.match.nodes_per_level) == out.match.nodes_expanded > 0
    moved, turned = pose_error(out.gicp.pose, out.match_pose)
    assert out.gicp.correction_m == pytest.approx(moved, abs=1e-6)
    assert math.degrees(out.gicp.correction_rad) == pytest.approx(turned, abs=1e-4)
    back = pickle.loads(pickle.dumps(out))
    assert np.array_equal(back.match.candidates, out.match.candidates)
    assert back.match.nodes_per_level == out.match.nodes_per_level
    # small: beside the scan it carries, the inspection adds a few hundred bytes
    assert len(pickle.dumps(out)) < out.scan_world.nbytes + 8_000


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_localizer_views_say_what_each_match_did(cache_root):
    """A real run on the town, matches in the S2M process: every landed match's view says whether it
    searched the whole map, where it started, what the search scored and expanded, what GICP did,
    and why it was refused if it was."""
    from lidarloc.core.config import Config
    from lidarloc.core.localizer import Localizer

    town = short_town(16)
    views, localized = {}, {}
    cfg = Config()
    cfg.pf.n_particles = 300
    cfg.s2m.global_search = "candidates"  # the town is small enough for "auto" to search it whole
    with Localizer(town, cfg, cache_root) as loc:
        assert loc.cfg.localize.s2m_process
        loc.reset(pose=town.poses[0])  # near the truth: the first matches land and are accepted
        for _ in range(len(town)):
            snap = loc.step()
            localized[snap.scan_index] = snap.localized
            if snap.s2m is not None:
                views[snap.s2m.started_at] = snap.s2m
    assert len(views) >= 3
    assert any(v.accepted for v in views.values())
    for v in views.values():
        assert v.mode == ("local" if localized[v.started_at] else "global")
        assert v.start_pose.shape == (4, 4) and np.isfinite(v.start_pose).all()
        c = v.candidates
        assert c.ndim == 2 and c.shape[1] == 4 and 1 <= len(c) <= 10
        assert np.all(np.diff(c[:, 3]) <= 0)
        # a whole-map match goes through the place index's candidates; their windows may all be
        # bounded below a start already at the truth (nothing expanded: the places' own scores shown)
        assert v.search == ("" if v.mode == "local" else "candidates")
        assert v.search == "candidates" or (len(v.nodes_per_level) >= 1 and sum(v.nodes_per_level) > 0)
        x0, y0, x1, y1 = v.region
        assert np.all((c[:, 0] >= x0 - 1e-6) & (c[:, 0] <= x1 + 1e-6) & (c[:, 1] >= y0 - 1e-6) & (c[:, 1] <= y1 + 1e-6))
        if v.accepted:
            assert v.reason == "" and v.stage in ("m3rsm", "refined_start")
            assert v.gicp_pose.shape == (4, 4) and v.match_pose.shape == (4, 4)
            assert 0.0 <= v.gicp_fitness <= 1.0 and len(v.gicp_correction) == 2
            moved = np.linalg.norm(v.gicp_pose[:3, 3] - v.match_pose[:3, 3])
            assert v.gicp_correction[0] == pytest.approx(moved, abs=1e-6)
            if v.stage == "m3rsm":  # the 2D match is the search's best candidate
                assert (c[0, 0], c[0, 1]) == (v.match_pose[0, 3], v.match_pose[1, 3]) and c[0, 3] == v.score
            else:  # GICP refined the start itself
                assert np.array_equal(v.match_pose, v.start_pose)
        else:
            assert v.reason


@pytest.mark.slow
def test_a_match_refused_at_its_landing_says_why_in_its_view(cache_root):
    """With the paper's acceptance, a match that S2M accepted but that lowers its particle's weight
    is refused when it lands: the view says so, and keeps the pose it would have written."""
    from lidarloc.app.viewer.s2m_detail import carried_pose, s2m_detail_markdown
    from lidarloc.core.config import Config, apply_preset
    from lidarloc.core.localizer import Localizer
    from lidarloc.core.matching.outcome import S2MOutcome

    town = short_town(6)
    cfg = apply_preset(Config(), "paper")
    cfg.pf.n_particles = 200
    cfg.localize.s2m_process = False

    def across_the_street(scan, pose, level=False):  # "accepted", 15 m off and turned 90°
        wrong = np.asarray(pose, float) @ pose_matrix(0.0, 0.0, 0.0, math.pi / 2, 0.0, 0.0)
        wrong[1, 3] += 15.0
        return S2MOutcome(accepted=True, pose=wrong, score=2.0, start_score=1.0, region=(0, 0, 1, 1), ms=1.0)

    with Localizer(town, cfg, cache_root) as loc:
        loc.s2m.matcher.match_local = across_the_street
        loc.reset(pose=town.poses[0])
        for _ in range(cfg.s2m.n_s2m + 1):
            snap = loc.step()
    view = snap.s2m
    assert view is not None and not view.accepted
    assert view.reason.startswith("lowers the particle's weight")
    assert carried_pose(view) is not None  # carried forward, then not written
    assert "**rejected**: lowers the particle's weight" in s2m_detail_markdown(view)
    assert "(not written)" in s2m_detail_markdown(view)


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

"""The paper's S2M acceptance, as the ``paper`` preset sets it (core/matching/schedule.py, core/matching/s2m.py):
a landed match that lowers its particle's weight is rejected and the particle keeps its state
(``s2m.reject_if_weight_drops``), and a start that branch and bound did not beat is rejected
without a GICP refinement (``s2m.refine_unbeaten_start = false``). The defaults keep accepting
both."""

import math
from dataclasses import replace

import numpy as np
import pytest
from helpers import short_town
from lidarloc.core.config import Config, apply_preset
from lidarloc.core.geometry import inv_pose, pose_matrix, pose_to_xyz_ypr, transform_points
from lidarloc.core.localizer import Localizer
from lidarloc.core.maps.bev import BEVPyramid
from lidarloc.core.maps.mapping import PriorMap
from lidarloc.core.matching.outcome import S2MOutcome
from lidarloc.core.matching.s2m import ScanToMapMatcher

SHIFT_M = 15.0  # how far the stub's "match" is from the pose it started at


@pytest.fixture(scope="module")
def town():
    return short_town(12)


def wrong_matcher(loc):
    """The in-process matcher replaced by one that answers at once with an "accepted" match
    SHIFT_M metres across the street from its start and turned by 90°: a failed match that the
    BEV score let through."""

    def match(scan, pose, level=False):
        wrong = np.asarray(pose, float) @ pose_matrix(0.0, 0.0, 0.0, math.pi / 2, 0.0, 0.0)
        wrong[1, 3] += SHIFT_M
        return S2MOutcome(accepted=True, pose=wrong, score=2.0, start_score=1.0, region=(0, 0, 1, 1), ms=1.0)

    loc.s2m.matcher.match_local = match


def make(town, cache_root, preset) -> Localizer:
    """A localizer whose particles follow a pose exactly (no process noise): the S2M particle
    stays where it is put."""
    cfg = apply_preset(Config(), preset)
    cfg.pf.n_particles = 300
    cfg.pf.q_std = (0.0,) * 11
    cfg.localize.s2m_process = False
    return Localizer(town, cfg, cache_root)


def place_particles(loc, town, pose):
    """Every particle at ``pose`` (4×4), driving at the drive's speed with no turn rates."""
    loc.reset(pose=pose)
    loc.pf.states[:, :6] = pose_to_xyz_ypr(pose)
    loc.pf.states[:, 6] = np.linalg.norm(town.poses[1][:3, 3] - town.poses[0][:3, 3]) / (
        town.timestamps[1] - town.timestamps[0]
    )
    loc.pf.states[:, 7:] = 0.0


def land_wrong_match(town, cache_root, preset):
    """Particles at the truth; the match started at scan 0 lands at scan n_s2m. Returns the
    landing event, and the S2M particle's state and the log-weights right after the weight update
    of the landing scan and right after the landing (where resampling would start)."""
    loc = make(town, cache_root, preset)
    cfg = loc.cfg
    try:
        wrong_matcher(loc)
        place_particles(loc, town, town.poses[0])
        loc.step()
        job = loc.s2m.job
        assert job is not None and job.started_at == 0
        j, landing = job.particle, cfg.s2m.n_s2m
        seen = {}
        real_update, real_resample = loc.pf.update, loc.pf.resample_if_needed

        def update(scan):
            real_update(scan)
            if loc.k == landing:
                seen["updated"] = (loc.pf.states[j].copy(), loc.pf.log_weights.copy())

        def resample_if_needed(protect=None):
            if loc.k == landing:
                seen["landed"] = (loc.pf.states[j].copy(), loc.pf.log_weights.copy())
            return real_resample(protect=protect)

        loc.pf.update, loc.pf.resample_if_needed = update, resample_if_needed
        loc.run(landing)
        event = next(e for e in loc.events if e.kind in ("s2m_accepted", "s2m_rejected"))
        assert event.scan == landing
        return event, seen, loc.snapshot().s2m
    finally:
        loc.close()


def test_paper_preset_rejects_a_match_that_lowers_the_weight(town, cache_root):
    event, seen, view = land_wrong_match(town, cache_root, "paper")
    assert event.kind == "s2m_rejected"
    assert "lowers the particle's weight" in event.detail
    assert not view.accepted and view.reason.startswith("lowers the particle's weight")
    state_before, weights_before = seen["updated"]
    state_after, weights_after = seen["landed"]
    np.testing.assert_array_equal(state_after, state_before)  # the particle keeps its state …
    np.testing.assert_array_equal(weights_after, weights_before)  # … and every weight stays


def test_default_accepts_the_same_match(town, cache_root):
    event, seen, view = land_wrong_match(town, cache_root, "default")
    assert event.kind == "s2m_accepted" and view.accepted
    state_before, _ = seen["updated"]
    state_after, _ = seen["landed"]
    moved = state_after[:2] - state_before[:2]
    # written into the particle: SHIFT_M from where it was (carried forward over two scans)
    assert np.linalg.norm(moved) > SHIFT_M - 5.0
    np.testing.assert_allclose(state_after[:3], view.pose[:3, 3])


def test_a_match_that_raises_the_weight_is_accepted_by_the_paper_preset(town, cache_root):
    """The check rejects only what lowers the weight: a match that puts a particle which is off
    the truth back onto it is accepted."""
    loc = make(town, cache_root, "paper")
    try:

        def to_truth(scan, pose, level=False):
            return S2MOutcome(
                accepted=True, pose=town.poses[0].copy(), score=2.0, start_score=1.0, region=(0, 0, 1, 1), ms=1.0
            )

        loc.s2m.matcher.match_local = to_truth
        start = town.poses[0].copy()
        start[1, 3] += 4.0  # every particle 4 m across the street from the truth
        place_particles(loc, town, start)
        loc.run(1 + loc.cfg.s2m.n_s2m)
        event = next(e for e in loc.events if e.kind in ("s2m_accepted", "s2m_rejected"))
        assert event.kind == "s2m_accepted", event.detail
    finally:
        loc.close()


# ------------------------------------------------------------------------------ unbeaten start
@pytest.fixture(scope="module")
def scene():
    """Flat ground and 40 random vertical walls, 140 m square."""
    rng = np.random.default_rng(7)
    g = np.arange(0, 140, 0.4)
    gx, gy = np.meshgrid(g, g, indexing="ij")
    ground = np.c_[gx.ravel(), gy.ravel(), np.zeros(gx.size)]
    walls = []
    for _ in range(40):
        a = rng.uniform(5, 135, 2)
        b = a + rng.uniform(-25, 25, 2)
        n = max(int(np.linalg.norm(b - a) / 0.2), 2)
        xy = a + (b - a) * np.linspace(0, 1, n)[:, None]
        for z in np.arange(0.2, rng.uniform(3, 8), 0.2):
            walls.append(np.c_[xy, np.full(n, z)])
    walls = np.concatenate(walls)
    walls = walls[(walls[:, :2] >= 0).all(1) & (walls[:, :2] <= 140).all(1)]
    return PriorMap(
        points=np.concatenate([ground, walls]).astype(np.float32),
        points_bev=walls.astype(np.float32),
        voxel_size=0.2,
        source="synthetic",
    )


@pytest.mark.parametrize("preset", ["paper", "default"])
def test_unbeaten_start_is_refined_only_outside_the_paper_preset(scene, preset):
    """The search is cut down to the start itself (region below one cell, no yaw window, the
    start's yaw on the lattice), so no lattice pose can beat it. The paper rejects it outright;
    the default refines the start by GICP and accepts the refined pose, which scores higher."""
    s2m = replace(apply_preset(Config(), preset).s2m, binary_cells=True, region_x=0.4, region_y=0.4, yaw_window=0.0)
    matcher = ScanToMapMatcher(scene, BEVPyramid.build(scene.points_bev, 1.0, binary=True), s2m)
    yaw = -math.pi + 100 * s2m.angle_step
    truth = pose_matrix(70.3, 64.6, 1.7, yaw, 0.0, 0.0)
    start = pose_matrix(70.3 + 0.35, 64.6 - 0.3, 1.8, yaw, 0.0, 0.0)
    near = scene.points[np.hypot(scene.points[:, 0] - 70.3, scene.points[:, 1] - 64.6) < 40]
    out = matcher.match_local(transform_points(inv_pose(truth), near).astype(np.float32), start)
    if preset == "paper":
        assert not out.accepted and out.gicp is None, "no GICP refinement of an unbeaten start"
        assert out.reason == "no pose in the search region scores higher than the start pose"
        np.testing.assert_array_equal(out.pose, start)
    else:
        assert out.accepted and out.stage == "refined_start", out.reason
        assert out.score > out.start_score
        assert np.linalg.norm(out.pose[:3, 3] - truth[:3, 3]) < 0.1

"""The particle filter (core/filter/pf.py) on a toy world: systematic resampling, the paper's and the
map-support initialisation, convergence from a uniform start, determinism per seed, the estimate,
log-space weights, live parameters; and tracking on real scans of the KITTI drive."""

import math

import numpy as np
import pytest
from helpers import paper_pf, toy_scan
from lidarloc.core.errors import LidarlocError
from lidarloc.core.filter.likelihood import log_likelihood
from lidarloc.core.filter.motion import propagate
from lidarloc.core.filter.pf import ParticleFilter, systematic_resample
from lidarloc.core.filter.scanprep import voxel_downsample_random
from lidarloc.core.filter.support import SupportGrid
from lidarloc.core.geometry import pose_matrix, wrap_angle

DEG = math.pi / 180
ZERO_Q = np.zeros(11)


def planar_cfg(**kw):
    """A 2-D problem (x, y, speed): heading and height known, no angular noise."""
    q = np.zeros(11)
    q[0] = q[1] = 0.3
    q[6] = 0.1
    base = dict(
        n_particles=2000, init_yaw=0.0, init_pitch=0.0, init_roll=0.0, init_rate_std=0.0, v_max=2.0, q_std=tuple(q)
    )
    base.update(kw)
    return paper_pf(**base)


def run_toy(world_pts, table, cfg, seed, steps=12):
    rng = np.random.default_rng(100)
    truth = np.zeros(11)
    truth[:6] = [12, 10, 1.7, 0, 0, 0]
    truth[6] = 1.0
    lo, hi = world_pts.min(axis=0).astype(float), world_pts.max(axis=0).astype(float)
    lo[2] = hi[2] = 1.7
    pf = ParticleFilter(cfg, table, lo, hi, seed=seed)
    est = None
    for k in range(steps):
        truth = propagate(truth[None], 0.1, ZERO_Q, None)[0]
        est = pf.step(toy_scan(world_pts, truth, rng, k), 0.1)
    return pf, est, truth


# ------------------------------------------------------------------------------ resampling
def test_systematic_resampling_preserves_the_weighted_mean():
    rng = np.random.default_rng(42)
    n = 20_000
    x = rng.normal(3.0, 2.0, n)
    w = rng.dirichlet(np.full(n, 0.3))
    weighted_mean = float(w @ x)
    weighted_sd = math.sqrt(float(w @ (x - weighted_mean) ** 2))
    means = [x[systematic_resample(w, n, rng)].mean() for _ in range(20)]
    # each resampled mean is within 4 standard errors of multinomial sampling (systematic is tighter)
    assert max(abs(m - weighted_mean) for m in means) < 4 * weighted_sd / math.sqrt(n)
    assert abs(np.mean(means) - weighted_mean) < weighted_sd / math.sqrt(n)


def test_resampling_keeps_the_protected_particle(toy_world):
    _, table = toy_world
    cfg = paper_pf(n_particles=500)
    pf = ParticleFilter(cfg, table, [0, 0, 0], [40, 40, 4], seed=0)
    lw = np.full(500, -50.0)
    lw[:5] = 0.0  # five particles hold all weight
    pf.log_weights = lw - np.log(np.exp(lw).sum())
    protected = 321  # a particle of weight ≈ e^−50
    kept = pf.states[protected].copy()
    heavy = pf.states[:5].copy()
    assert pf.resample_if_needed(protect=protected)
    np.testing.assert_array_equal(pf.states[protected], kept)  # survives, at its own index
    copies_of_heavy = np.all(pf.states[:, None] == heavy[None], axis=2).any(axis=1)
    assert copies_of_heavy.sum() == 499 and not copies_of_heavy[protected]
    assert pf.n_eff() == pytest.approx(500)
    assert not pf.resample_if_needed(protect=protected)  # N_eff = N: nothing to do


def test_set_n_particles_resamples_to_the_new_count(toy_world):
    _, table = toy_world
    pf = ParticleFilter(paper_pf(n_particles=300), table, [0, 0, 0], [40, 40, 4], seed=0)
    pf.set_n_particles(1200)
    assert pf.states.shape == (1200, 11) and pf.log_weights.shape == (1200,) and pf.n == 1200
    assert pf.weights.sum() == pytest.approx(1.0)


# ------------------------------------------------------------------------------ the filter
def test_converges_to_the_truth_from_a_uniform_start(toy_world):
    pts, table = toy_world
    pf, est, truth = run_toy(pts, table, planar_cfg(), seed=3)
    assert np.linalg.norm(est.state[:2] - truth[:2]) < 0.3
    assert est.std_xyz[:2].max() < 0.5
    # the uniform start really was uniform over the 40 × 40 m box
    fresh = ParticleFilter(planar_cfg(), table, [0, 0, 1.7], [40, 40, 1.7], seed=3)
    assert fresh.states[:, 0].std() > 10 and fresh.states[:, 1].std() > 10


def test_same_seed_same_particles_other_seed_differs(toy_world):
    pts, table = toy_world
    a, _, _ = run_toy(pts, table, planar_cfg(n_particles=300), seed=11, steps=4)
    b, _, _ = run_toy(pts, table, planar_cfg(n_particles=300), seed=11, steps=4)
    c, _, _ = run_toy(pts, table, planar_cfg(n_particles=300), seed=12, steps=4)
    np.testing.assert_array_equal(a.states, b.states)
    np.testing.assert_array_equal(a.log_weights, b.log_weights)
    assert not np.array_equal(a.states, c.states)


def test_paper_initialisation_ranges(toy_world):
    _, table = toy_world
    cfg = paper_pf(n_particles=5000)
    pf = ParticleFilter(cfg, table, [0, 0, 0], [40, 30, 4], seed=0)
    s = pf.states
    assert np.all(s[:, :3] >= [0, 0, 0]) and np.all(s[:, :3] <= [40, 30, 4])
    assert s[:, 3].min() < -3.0 and s[:, 3].max() > 3.0
    assert np.abs(s[:, 4]).max() <= cfg.init_pitch and np.abs(s[:, 5]).max() <= cfg.init_roll
    assert np.abs(s[:, 4]).max() > 0.9 * cfg.init_pitch
    assert s[:, 7:10].std(axis=0) == pytest.approx([0.1] * 3, rel=0.05)
    assert s[:, 6].min() >= 0 and s[:, 6].max() <= cfg.v_max and np.all(s[:, 10] == 0)
    np.testing.assert_allclose(pf.weights, 1 / 5000)


def test_map_support_init_stays_on_the_map_at_sensor_height(toy_world):
    pts, table = toy_world
    # a map whose points only cover x < 10: the other 30 m of the box must get no particles
    part = pts[pts[:, 0] < 10]
    cfg = paper_pf(n_particles=4000, init_mode="map_support")
    pf = ParticleFilter(cfg, table, [0, 0, 0], [40, 40, 4], seed=0, map_points=part)
    s = pf.states
    assert s[:, 0].max() <= 10.5
    assert np.all(np.abs(s[:, 2] - cfg.sensor_height) < 0.01)  # ground at z = 0 everywhere
    assert np.abs(s[:, 4]).max() < math.radians(10) and np.abs(s[:, 5]).max() < math.radians(10)
    grid = SupportGrid.from_points(part)
    pf2 = ParticleFilter(cfg, table, [0, 0, 0], [40, 40, 4], seed=0, support=grid)
    np.testing.assert_array_equal(pf2.states, s)
    with pytest.raises(LidarlocError):
        ParticleFilter(cfg, table, [0, 0, 0], [40, 40, 4], seed=0)  # no map for map_support


def test_initialize_in_region_and_around_pose(toy_world):
    _, table = toy_world
    pf = ParticleFilter(paper_pf(n_particles=2000), table, [0, 0, 0], [40, 40, 4], seed=0)
    pf.initialize(region=(5, 6, 9, 8))
    assert pf.states[:, 0].min() >= 5 and pf.states[:, 0].max() <= 9
    assert pf.states[:, 1].min() >= 6 and pf.states[:, 1].max() <= 8
    T = pose_matrix(20, 15, 1.7, 1.0, 0.0, 0.0)
    pf.initialize(pose=T, pose_std=(0.5, 0.5, 0.1, 0.05, 0.01, 0.01))
    np.testing.assert_allclose(pf.states[:, :4].mean(axis=0), [20, 15, 1.7, 1.0], atol=0.05)
    np.testing.assert_allclose(pf.states[:, :2].std(axis=0), [0.5, 0.5], rtol=0.1)
    with pytest.raises(LidarlocError):
        pf.initialize(region=(5, 6, 5, 8))


def test_estimate_mean_covariance_ellipse(toy_world):
    _, table = toy_world
    pf = ParticleFilter(paper_pf(n_particles=4), table, [0, 0, 0], [40, 40, 4], seed=0)
    pf.states = np.zeros((4, 11))
    pf.states[:, 0] = [0, 2, 0, 2]
    pf.states[:, 1] = [0, 0, 1, 1]
    pf.states[:, 3] = [math.pi - 0.1, -math.pi + 0.1, math.pi - 0.1, -math.pi + 0.1]  # circular mean: π
    pf.log_weights = np.log(np.full(4, 0.25))
    est = pf.estimate()
    np.testing.assert_allclose(est.state[:2], [1.0, 0.5])
    assert abs(wrap_angle(est.state[3] - math.pi)) < 1e-9
    np.testing.assert_allclose(est.cov_xyz[:2, :2], [[1.0, 0.0], [0.0, 0.25]], atol=1e-12)
    np.testing.assert_allclose(est.std_xyz, [1.0, 0.5, 0.0], atol=1e-12)
    a, b, angle = est.ellipse_xy
    assert a == pytest.approx(2.0) and b == pytest.approx(1.0) and abs(math.sin(angle)) < 1e-9
    assert est.n_eff == pytest.approx(4.0)
    np.testing.assert_allclose(est.pose, pose_matrix(*est.state[:6]))
    pf.log_weights = np.log([0.1, 0.6, 0.2, 0.1])
    assert pf.estimate().best_index == 1


def test_update_normalises_in_log_space_without_underflow(toy_world):
    pts, table = toy_world
    rng = np.random.default_rng(0)
    # 20 000 scan points: raw likelihoods are e^(−10⁵…−10⁶), far below the smallest double
    scan = (pts[rng.integers(0, len(pts), 20_000)] - [12, 10, 1.7]).astype(np.float32)
    pf = ParticleFilter(paper_pf(n_particles=200), table, [0, 0, 0], [40, 40, 4], seed=0)
    pf.update(scan)
    assert np.all(np.isfinite(pf.log_weights))
    assert pf.weights.sum() == pytest.approx(1.0) and pf.log_likelihoods.max() < -1e3
    assert np.logaddexp.reduce(pf.log_weights) == pytest.approx(0.0, abs=1e-9)


def test_live_parameters_take_effect_at_the_next_update(toy_world):
    pts, table = toy_world
    rng = np.random.default_rng(0)
    scan = (pts[rng.integers(0, len(pts), 2000)] - [12, 10, 1.7]).astype(np.float32)
    pf = ParticleFilter(paper_pf(n_particles=50), table, [0, 0, 0], [40, 40, 4], seed=0)
    pf.initialize(pose=pose_matrix(12, 10, 1.7, 0, 0, 0), pose_std=2.0)
    states = pf.states.copy()
    pf.set_d_max(2.0)  # below the built 5 m: no rebuild
    pf.set_sigma(0.8)
    pf.update(scan)
    expected = log_likelihood(states, scan, table, 2.0, 0.8)
    keep = expected > expected.max() - 800
    np.testing.assert_allclose(pf.log_likelihoods[keep], expected[keep], rtol=1e-6)
    pf.set_d_max(50.0)  # beyond the table: capped at the built value
    assert pf.d_max == table.d_max_built
    pf.set_q_std(np.zeros(11))
    before = pf.states.copy()
    pf.predict(0.1)
    np.testing.assert_allclose(pf.states[:, 6], before[:, 6])  # no noise now
    with pytest.raises(LidarlocError):
        pf.set_sigma(0.0)
    with pytest.raises(LidarlocError):
        pf.set_q_std(np.ones(5))


def test_set_particle_and_reweight(toy_world):
    pts, table = toy_world
    rng = np.random.default_rng(0)
    truth = np.zeros(11)
    truth[:6] = [12, 10, 1.7, 0.2, 0, 0]
    scan = toy_scan(pts, truth, rng, 0)
    pf = ParticleFilter(paper_pf(n_particles=300), table, [0, 0, 0], [40, 40, 4], seed=0)
    pf.update(scan)
    j = int(np.argmin(pf.log_weights))
    pf.set_particle(j, truth)
    ll = pf.reweight(j)
    assert pf.estimate().best_index == j  # the corrected particle now dominates
    assert ll == pytest.approx(log_likelihood(truth[None], scan, table, 5.0, 0.5)[0], rel=1e-6)
    assert pf.weights.sum() == pytest.approx(1.0)


# ------------------------------------------------------------------------------ on the real drive
def test_filter_step_on_real_scans_tracks_from_near_the_truth(kitti_raw_map):
    seq, prior, table = kitti_raw_map
    lo, hi = prior.bounds
    pf = ParticleFilter(paper_pf(n_particles=500), table, lo, hi, seed=0, map_points=prior.points)
    pf.initialize(
        pose=seq.pose(10),
        pose_std=(1.0, 1.0, 0.2, 3 * DEG, 1 * DEG, 1 * DEG),
        speed=float(np.linalg.norm(seq.pose(11)[:3, 3] - seq.pose(10)[:3, 3]) / 0.1),
    )
    errors = []
    for k in range(11, 31):
        scan = voxel_downsample_random(seq.scan(k), 0.5, k)
        est = pf.step(scan, seq.timestamp(k) - seq.timestamp(k - 1))
        errors.append(np.linalg.norm(est.state[:3] - seq.pose(k)[:3, 3]))
    assert np.median(errors) < 1.0 and max(errors[5:]) < 2.0, np.round(errors, 2)

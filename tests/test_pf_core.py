"""Particle-filter core on synthetic data: motion model, scan down-sampling, likelihood,
systematic resampling, the filter's convergence, determinism and live parameters."""

import math
import time

import numpy as np
import pytest

from lidarloc.core.config import PFConfig
from lidarloc.core.errors import LidarlocError
from lidarloc.core.geometry import inv_pose, pose_matrix, rotation_zyx, transform_points, wrap_angle
from lidarloc.core.likelihood import log_likelihood, log_likelihood_floored
from lidarloc.core.lookup import LookupTable
from lidarloc.core.motion import propagate
from lidarloc.core.pf import ParticleFilter, SupportGrid, systematic_resample
from lidarloc.core.scanprep import voxel_downsample_random

ZERO_Q = np.zeros(11)


# ------------------------------------------------------------------------------ a toy world
def toy_map() -> np.ndarray:
    """40 × 40 m of flat ground, an L of two 4 m walls (x = 0 and y = 0) and a 2 × 2 m pillar:
    every x-y position has its own view of the walls."""
    sp = 0.2
    gx, gy = np.meshgrid(np.arange(0, 40, 0.25), np.arange(0, 40, 0.25), indexing="ij")
    ground = np.c_[gx.ravel(), gy.ravel(), np.zeros(gx.size)]
    wy, wz = np.meshgrid(np.arange(0, 40, sp), np.arange(0, 4, sp), indexing="ij")
    wall_a = np.c_[np.zeros(wy.size), wy.ravel(), wz.ravel()]
    wx, wz = np.meshgrid(np.arange(0, 25, sp), np.arange(0, 4, sp), indexing="ij")
    wall_b = np.c_[wx.ravel(), np.zeros(wx.size), wz.ravel()]
    s, z = np.meshgrid(np.arange(0, 2, sp), np.arange(0, 3, sp), indexing="ij")
    s, z = s.ravel(), z.ravel()
    pillar = np.concatenate([np.c_[30 + s, 25 + 0 * s, z], np.c_[30 + s, 27 + 0 * s, z],
                             np.c_[30 + 0 * s, 25 + s, z], np.c_[32 + 0 * s, 25 + s, z]])
    return np.concatenate([ground, wall_a, wall_b, pillar]).astype(np.float32)


def toy_scan(world: np.ndarray, state: np.ndarray, rng, k: int) -> np.ndarray:
    """What a sensor at ``state`` sees (25 m range, 2 cm noise), prepared at 0.5 m."""
    T = pose_matrix(*state[:6])
    near = world[np.linalg.norm(world[:, :2] - state[:2], axis=1) < 25]
    local = transform_points(inv_pose(T), near) + rng.normal(0, 0.02, (len(near), 3))
    return voxel_downsample_random(local, 0.5, k)


@pytest.fixture(scope="module")
def world():
    pts = toy_map()
    return pts, LookupTable.build(pts, 0.25, 5.0)


def planar_cfg(**kw) -> PFConfig:
    """A 2-D problem (x, y, speed): heading and height known, no angular noise."""
    q = np.zeros(11)
    q[0] = q[1] = 0.3
    q[6] = 0.1
    base = dict(n_particles=2000, init_yaw=0.0, init_pitch=0.0, init_roll=0.0, init_rate_std=0.0, v_max=2.0,
                q_std=tuple(q))
    base.update(kw)
    return PFConfig(**base)


def run_toy(world_pts, table, cfg, seed, steps=12):
    rng = np.random.default_rng(100)
    truth = np.zeros(11)
    truth[:6] = [12, 10, 1.7, 0, 0, 0]
    truth[6] = 1.0
    lo, hi = world_pts.min(axis=0).astype(float), world_pts.max(axis=0).astype(float)
    lo[2] = hi[2] = 1.7
    pf = ParticleFilter(cfg, table, lo, hi, seed=seed)
    first, est = None, None
    for k in range(steps):
        truth = propagate(truth[None], 0.1, ZERO_Q, None)[0]
        est = pf.step(toy_scan(world_pts, truth, rng, k), 0.1)
        first = pf if first is None else first
    return pf, est, truth


# ------------------------------------------------------------------------------ motion model
def test_straight_line_matches_closed_form():
    s = np.zeros((1, 11))
    yaw, pitch, v0, a = 0.7, -0.1, 3.0, 0.5
    s[0, 3], s[0, 4], s[0, 6], s[0, 10] = yaw, pitch, v0, a
    dt, n = 0.1, 50
    for _ in range(n):
        s = propagate(s, dt, ZERO_Q, None)
    T = n * dt
    direction = rotation_zyx(yaw, pitch, 0.3)[:, 0]           # roll does not move the x axis
    np.testing.assert_allclose(s[0, :3], direction * (v0 * T + 0.5 * a * T * T), atol=1e-9)
    assert s[0, 6] == pytest.approx(v0 + a * T)
    np.testing.assert_allclose(s[0, 3:6], [yaw, pitch, 0.0], atol=1e-12)


def test_constant_turn_matches_closed_form():
    v, omega, dt = 5.0, 0.2, 0.1
    n = int(round(2 * math.pi / (omega * dt)))                  # one full circle: 314 steps
    omega = 2 * math.pi / (n * dt)
    s = np.zeros((1, 11))
    s[0, 6], s[0, 7] = v, omega
    path = []
    for _ in range(n):
        s = propagate(s, dt, ZERO_Q, None)
        path.append(s[0, :3].copy())
    path = np.array(path)
    # the first-order hold sums v·dt·(cos θ_k, sin θ_k) with θ_k = k·ω·dt: closed form
    k = np.arange(1, n + 1)
    h = omega * dt
    closed_x = v * dt * np.sin(k * h / 2) / np.sin(h / 2) * np.cos((k - 1) * h / 2)
    closed_y = v * dt * np.sin(k * h / 2) / np.sin(h / 2) * np.sin((k - 1) * h / 2)
    np.testing.assert_allclose(path[:, 0], closed_x, atol=1e-8)
    np.testing.assert_allclose(path[:, 1], closed_y, atol=1e-8)
    np.testing.assert_allclose(path[-1], [0, 0, 0], atol=1e-8)   # back at the start after 2π
    # … and it is the continuous circle of radius v/ω to first order in dt
    radius = v / omega
    centre = np.array([0.0, radius])                             # start at 0 heading +x, turning left
    assert np.abs(np.linalg.norm(path[:, :2] - centre, axis=1) - radius).max() < v * dt
    assert s[0, 3] == pytest.approx(wrap_angle(n * h))


def test_noise_statistics_and_angle_wrapping():
    rng = np.random.default_rng(0)
    s = np.zeros((50_000, 11))
    s[:, 3] = math.pi - 1e-3
    q = np.linspace(0.01, 0.5, 11)
    out = propagate(s, 0.1, q, rng)
    assert s[:, 3].max() == pytest.approx(math.pi - 1e-3)      # input untouched
    lin = [0, 1, 2, 6, 7, 8, 9, 10]
    np.testing.assert_allclose(out[:, lin].std(axis=0), q[lin], rtol=0.03)
    assert np.all(out[:, 3:6] >= -math.pi) and np.all(out[:, 3:6] < math.pi)
    assert (out[:, 3] < 0).mean() > 0.3                          # yaw wrapped past +π


# ------------------------------------------------------------------------------ scan preparation
def test_voxel_downsample_keeps_one_random_real_point_per_voxel():
    rng = np.random.default_rng(0)
    pts = rng.uniform(-40, 40, (120_000, 4)).astype(np.float32)
    pts[:, 2] *= 0.05
    voxel = 0.5
    out = voxel_downsample_random(pts, voxel, 7)
    keys_in = {tuple(k) for k in np.floor(pts[:, :3] / voxel).astype(np.int64)}
    keys_out = np.floor(out / voxel).astype(np.int64)
    assert out.shape[1] == 3 and out.dtype == np.float32
    assert len({tuple(k) for k in keys_out}) == len(out) == len(keys_in)   # one per occupied voxel
    assert len(np.intersect1d(out.view("V12"), pts[:, :3].copy().view("V12"))) == len(out)  # real points
    np.testing.assert_array_equal(out, voxel_downsample_random(pts, voxel, 7))             # deterministic
    assert not np.array_equal(out, voxel_downsample_random(pts, voxel, 8))
    np.testing.assert_array_equal(out, voxel_downsample_random(pts, voxel, np.random.default_rng(7)))


def test_voxel_downsample_picks_uniformly_inside_a_voxel():
    pts = np.c_[np.linspace(0.01, 0.49, 4), np.zeros(4), np.zeros(4)].astype(np.float32)
    picks = [voxel_downsample_random(pts, 0.5, s)[0, 0] for s in range(400)]
    counts = np.unique(picks, return_counts=True)[1]
    assert len(counts) == 4 and counts.min() > 60


def test_voxel_downsample_is_fast():
    rng = np.random.default_rng(0)
    scan = rng.uniform(-60, 60, (120_000, 4)).astype(np.float32)
    voxel_downsample_random(scan, 0.5, 0)
    times = []
    for i in range(7):
        t0 = time.perf_counter()
        voxel_downsample_random(scan, 0.5, i)
        times.append(time.perf_counter() - t0)
    # brief: ≤ 15 ms; the margin is for the shared, loaded test machines
    assert np.median(times) < 0.05


# ------------------------------------------------------------------------------ likelihood
def test_log_likelihood_is_the_papers_sum(world):
    pts, table = world
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
            expected.append(-np.sum(np.minimum(d * d, d_max * d_max)) / sigma ** 2)
        np.testing.assert_allclose(ll, expected, rtol=1e-4)
    # the parallel kernel (> 64 particles) and its serial twin give the same sums bit for bit:
    # PF.reweight() (one particle) must agree exactly with PF.update() (all of them)
    many = np.repeat(states, 3, axis=0)
    np.testing.assert_array_equal(log_likelihood(many, scan, table, 5.0, 0.5)[::3], log_likelihood(states, scan, table, 5.0, 0.5))
    # a lower d_max changes the values (no rebuild: the same table)
    assert not np.allclose(log_likelihood(states, scan, table, 2.0, 0.5), log_likelihood(states, scan, table, 5.0, 0.5))


def test_likelihood_reads_far_or_non_finite_poses_as_misses(world):
    """Particles off the grid — far away, beyond int32 cells, ±inf or NaN — read d_max for
    every point (a miss), never memory outside the table."""
    pts, table = world
    scan = pts[:500] - [12, 10, 1.7]
    states = np.zeros((6, 11))
    states[:, :3] = [[-1e3, 0, 0], [1e12, 1e12, 1e12], [np.inf, 0, 0], [-np.inf, 0, 0], [np.nan, 0, 0], [0, 0, 1e9]]
    for n_copies in (1, 20):           # serial twin and parallel kernel
        ll = log_likelihood(np.repeat(states, n_copies, axis=0), scan, table, 5.0, 0.5)
        np.testing.assert_array_equal(ll, -len(scan) * 5.0 ** 2 / 0.5 ** 2)


def test_floored_likelihood_gives_the_same_weights(world):
    pts, table = world
    rng = np.random.default_rng(1)
    scan = pts[rng.integers(0, len(pts), 4000)] - [15, 12, 1.7]
    states = np.zeros((500, 11))
    states[:, :3] = [15, 12, 1.7] + rng.normal(0, [3, 3, 0.3], (500, 3))
    states[:, 3] = rng.normal(0, 0.3, 500)
    prior = np.log(rng.dirichlet(np.ones(500)))
    exact = prior + log_likelihood(states, scan, table, 5.0, 0.5)
    floored = prior + log_likelihood_floored(states, scan, table, 5.0, 0.5, prior)
    w_exact = np.exp(exact - exact.max())
    w_floor = np.exp(floored - floored.max())
    np.testing.assert_allclose(w_floor / w_floor.sum(), w_exact / w_exact.sum(), rtol=1e-9, atol=1e-300)
    kept = exact > exact.max() - 800
    np.testing.assert_allclose(floored[kept], exact[kept], rtol=1e-9)
    assert np.all(floored[~kept] == pytest.approx(exact.max() - 800, rel=1e-9))
    assert (~kept).sum() > 100                                   # the floor did apply


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


def test_resampling_keeps_the_protected_particle(world):
    _, table = world
    cfg = PFConfig(n_particles=500)
    pf = ParticleFilter(cfg, table, [0, 0, 0], [40, 40, 4], seed=0)
    lw = np.full(500, -50.0)
    lw[:5] = 0.0                                                 # five particles hold all weight
    pf.log_weights = lw - np.log(np.exp(lw).sum())
    protected = 321                                              # a particle of weight ≈ e^−50
    kept = pf.states[protected].copy()
    heavy = pf.states[:5].copy()
    assert pf.resample_if_needed(protect=protected)
    np.testing.assert_array_equal(pf.states[protected], kept)    # survives, at its own index
    copies_of_heavy = np.all(pf.states[:, None] == heavy[None], axis=2).any(axis=1)
    assert copies_of_heavy.sum() == 499 and not copies_of_heavy[protected]
    assert pf.n_eff() == pytest.approx(500)
    assert not pf.resample_if_needed(protect=protected)          # N_eff = N: nothing to do


def test_set_n_particles_resamples_to_the_new_count(world):
    _, table = world
    pf = ParticleFilter(PFConfig(n_particles=300), table, [0, 0, 0], [40, 40, 4], seed=0)
    pf.set_n_particles(1200)
    assert pf.states.shape == (1200, 11) and pf.log_weights.shape == (1200,) and pf.n == 1200
    assert pf.weights.sum() == pytest.approx(1.0)


# ------------------------------------------------------------------------------ the filter
def test_converges_to_the_truth_from_a_uniform_start(world):
    pts, table = world
    pf, est, truth = run_toy(pts, table, planar_cfg(), seed=3)
    assert np.linalg.norm(est.state[:2] - truth[:2]) < 0.3
    assert est.std_xyz[:2].max() < 0.5
    # the uniform start really was uniform over the 40 × 40 m box
    fresh = ParticleFilter(planar_cfg(), table, [0, 0, 1.7], [40, 40, 1.7], seed=3)
    assert fresh.states[:, 0].std() > 10 and fresh.states[:, 1].std() > 10


def test_same_seed_same_particles_other_seed_differs(world):
    pts, table = world
    a, _, _ = run_toy(pts, table, planar_cfg(n_particles=300), seed=11, steps=4)
    b, _, _ = run_toy(pts, table, planar_cfg(n_particles=300), seed=11, steps=4)
    c, _, _ = run_toy(pts, table, planar_cfg(n_particles=300), seed=12, steps=4)
    np.testing.assert_array_equal(a.states, b.states)
    np.testing.assert_array_equal(a.log_weights, b.log_weights)
    assert not np.array_equal(a.states, c.states)


def test_paper_initialisation_ranges(world):
    _, table = world
    cfg = PFConfig(n_particles=5000)
    pf = ParticleFilter(cfg, table, [0, 0, 0], [40, 30, 4], seed=0)
    s = pf.states
    assert np.all(s[:, :3] >= [0, 0, 0]) and np.all(s[:, :3] <= [40, 30, 4])
    assert s[:, 3].min() < -3.0 and s[:, 3].max() > 3.0
    assert np.abs(s[:, 4]).max() <= cfg.init_pitch and np.abs(s[:, 5]).max() <= cfg.init_roll
    assert np.abs(s[:, 4]).max() > 0.9 * cfg.init_pitch
    assert s[:, 7:10].std(axis=0) == pytest.approx([0.1] * 3, rel=0.05)
    assert s[:, 6].min() >= 0 and s[:, 6].max() <= cfg.v_max and np.all(s[:, 10] == 0)
    np.testing.assert_allclose(pf.weights, 1 / 5000)


def test_map_support_init_stays_on_the_map_at_sensor_height(world):
    pts, table = world
    # a map whose points only cover x < 10: the other 30 m of the box must get no particles
    part = pts[pts[:, 0] < 10]
    cfg = PFConfig(n_particles=4000, init_mode="map_support")
    pf = ParticleFilter(cfg, table, [0, 0, 0], [40, 40, 4], seed=0, map_points=part)
    s = pf.states
    assert s[:, 0].max() <= 10.5
    assert np.all(np.abs(s[:, 2] - cfg.sensor_height) < 0.01)   # ground at z = 0 everywhere
    assert np.abs(s[:, 4]).max() < math.radians(10) and np.abs(s[:, 5]).max() < math.radians(10)
    grid = SupportGrid.from_points(part)
    pf2 = ParticleFilter(cfg, table, [0, 0, 0], [40, 40, 4], seed=0, support=grid)
    np.testing.assert_array_equal(pf2.states, s)
    with pytest.raises(LidarlocError):
        ParticleFilter(cfg, table, [0, 0, 0], [40, 40, 4], seed=0)   # no map for map_support


def test_initialize_in_region_and_around_pose(world):
    _, table = world
    pf = ParticleFilter(PFConfig(n_particles=2000), table, [0, 0, 0], [40, 40, 4], seed=0)
    pf.initialize(region=(5, 6, 9, 8))
    assert pf.states[:, 0].min() >= 5 and pf.states[:, 0].max() <= 9
    assert pf.states[:, 1].min() >= 6 and pf.states[:, 1].max() <= 8
    T = pose_matrix(20, 15, 1.7, 1.0, 0.0, 0.0)
    pf.initialize(pose=T, pose_std=(0.5, 0.5, 0.1, 0.05, 0.01, 0.01))
    np.testing.assert_allclose(pf.states[:, :4].mean(axis=0), [20, 15, 1.7, 1.0], atol=0.05)
    np.testing.assert_allclose(pf.states[:, :2].std(axis=0), [0.5, 0.5], rtol=0.1)
    with pytest.raises(LidarlocError):
        pf.initialize(region=(5, 6, 5, 8))


def test_estimate_mean_covariance_ellipse(world):
    _, table = world
    pf = ParticleFilter(PFConfig(n_particles=4), table, [0, 0, 0], [40, 40, 4], seed=0)
    pf.states = np.zeros((4, 11))
    pf.states[:, 0] = [0, 2, 0, 2]
    pf.states[:, 1] = [0, 0, 1, 1]
    pf.states[:, 3] = [math.pi - 0.1, -math.pi + 0.1, math.pi - 0.1, -math.pi + 0.1]   # circular mean: π
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


def test_update_normalises_in_log_space_without_underflow(world):
    pts, table = world
    rng = np.random.default_rng(0)
    # 20 000 scan points: raw likelihoods are e^(−10⁵…−10⁶), far below the smallest double
    scan = (pts[rng.integers(0, len(pts), 20_000)] - [12, 10, 1.7]).astype(np.float32)
    pf = ParticleFilter(PFConfig(n_particles=200), table, [0, 0, 0], [40, 40, 4], seed=0)
    pf.update(scan)
    assert np.all(np.isfinite(pf.log_weights))
    assert pf.weights.sum() == pytest.approx(1.0) and pf.log_likelihoods.max() < -1e3
    assert np.logaddexp.reduce(pf.log_weights) == pytest.approx(0.0, abs=1e-9)


def test_live_parameters_take_effect_at_the_next_update(world):
    pts, table = world
    rng = np.random.default_rng(0)
    scan = (pts[rng.integers(0, len(pts), 2000)] - [12, 10, 1.7]).astype(np.float32)
    pf = ParticleFilter(PFConfig(n_particles=50), table, [0, 0, 0], [40, 40, 4], seed=0)
    pf.initialize(pose=pose_matrix(12, 10, 1.7, 0, 0, 0), pose_std=2.0)
    states = pf.states.copy()
    pf.set_d_max(2.0)                      # below the built 5 m: no rebuild
    pf.set_sigma(0.8)
    pf.update(scan)
    expected = log_likelihood(states, scan, table, 2.0, 0.8)
    keep = expected > expected.max() - 800
    np.testing.assert_allclose(pf.log_likelihoods[keep], expected[keep], rtol=1e-6)
    pf.set_d_max(50.0)                     # beyond the table: capped at the built value
    assert pf.d_max == table.d_max_built
    pf.set_q_std(np.zeros(11))
    before = pf.states.copy()
    pf.predict(0.1)
    np.testing.assert_allclose(pf.states[:, 6], before[:, 6])   # no noise now
    with pytest.raises(LidarlocError):
        pf.set_sigma(0.0)
    with pytest.raises(LidarlocError):
        pf.set_q_std(np.ones(5))


def test_set_particle_and_reweight(world):
    pts, table = world
    rng = np.random.default_rng(0)
    truth = np.zeros(11)
    truth[:6] = [12, 10, 1.7, 0.2, 0, 0]
    scan = toy_scan(pts, truth, rng, 0)
    pf = ParticleFilter(PFConfig(n_particles=300), table, [0, 0, 0], [40, 40, 4], seed=0)
    pf.update(scan)
    j = int(np.argmin(pf.log_weights))
    pf.set_particle(j, truth)
    ll = pf.reweight(j)
    assert pf.estimate().best_index == j                         # the corrected particle now dominates
    assert ll == pytest.approx(log_likelihood(truth[None], scan, table, 5.0, 0.5)[0], rel=1e-6)
    assert pf.weights.sum() == pytest.approx(1.0)

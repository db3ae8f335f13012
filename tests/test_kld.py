"""KLD-sampling (core/filter/kld.py and the filter's adaptive particle count): Fox's bound against the
χ² quantile it approximates, the stopping rule, the count shrinking once the cloud converges and
growing back when it spreads or is re-initialised, the protected particle, determinism."""

import math

import numpy as np
import pytest
from helpers import paper_pf, toy_scan
from lidarloc.core.errors import LidarlocError
from lidarloc.core.filter.kld import bin_keys, kld_bound, kld_count
from lidarloc.core.filter.motion import propagate
from lidarloc.core.filter.pf import ParticleFilter
from scipy.stats import chi2

DEG = math.pi / 180


def test_bound_approximates_the_chi_square_quantile():
    """Fox: n = χ²_{k−1, 1−δ} / (2ε), here with Wilson–Hilferty's approximation (z = 2.326: δ = 0.01)."""
    for k in (5, 10, 50, 300, 2000):
        exact = chi2.ppf(0.99, k - 1) / (2 * 0.05)
        assert kld_bound(k, 0.05, 2.326) == pytest.approx(exact, rel=0.01)
    assert kld_bound(1, 0.05, 2.326) == 0.0 and kld_bound(0, 0.05, 2.326) == 0.0
    b = kld_bound(np.arange(2, 100), 0.05, 2.326)
    assert np.all(np.diff(b) > 0)  # more bins, more particles
    assert kld_bound(10, 0.02, 2.326) > kld_bound(10, 0.05, 2.326)  # tighter ε, more particles


def test_stopping_rule():
    one_bin = np.zeros(1000, np.int64)
    assert kld_count(one_bin, 0.05, 2.326, 100, 1000) == (100, 1)
    all_distinct = np.arange(1000, dtype=np.int64)
    assert kld_count(all_distinct, 0.05, 2.326, 100, 1000) == (1000, 1000)
    ten_bins = np.tile(np.arange(10, dtype=np.int64), 100)  # every bin seen within the first 10 draws
    n, k = kld_count(ten_bins, 0.05, 2.326, 50, 1000)
    assert k == 10 and n == math.ceil(kld_bound(10, 0.05, 2.326))
    assert kld_count(ten_bins, 0.05, 2.326, 500, 1000) == (500, 10)  # the floor
    assert kld_count(ten_bins, 0.05, 2.326, 50, 30)[0] == 30  # the budget
    with pytest.raises(LidarlocError):
        kld_count(ten_bins, 0.0, 2.326, 50, 1000)


def test_bins_are_x_y_yaw():
    s = np.zeros((5, 11))
    s[1, 0] = 0.99  # same 1 m bin as particle 0
    s[2, 0] = 1.01  # next bin in x
    s[3, 3] = 11 * DEG  # next 10° yaw bin
    s[4, 2] = 50.0  # z does not count
    keys = bin_keys(s, 1.0, 10 * DEG)
    assert keys[0] == keys[1] == keys[4] and len(set(keys.tolist())) == 3
    s[0, 3], s[1, 3] = 0.5, 0.5 + 2 * math.pi  # the same angle, unwrapped
    assert bin_keys(s[:2], 1.0, 10 * DEG)[0] == bin_keys(s[:2], 1.0, 10 * DEG)[1]
    assert len(bin_keys(np.full((2, 11), np.nan), 1.0, 0.1)) == 2  # no crash on a lost particle


def planar_cfg(**kw):
    q = np.zeros(11)
    q[0] = q[1] = 0.3
    q[6] = 0.1
    base = dict(
        n_particles=2000,
        init_yaw=0.0,
        init_pitch=0.0,
        init_roll=0.0,
        init_rate_std=0.0,
        v_max=2.0,
        q_std=tuple(q),
        kld=True,
        kld_min=50,
    )
    base.update(kw)
    return paper_pf(**base)


def track(pf, pts, steps, seed=100):
    rng = np.random.default_rng(seed)
    truth = np.zeros(11)
    truth[:6] = [12, 10, 1.7, 0, 0, 0]
    truth[6] = 1.0
    counts = []
    for k in range(steps):
        truth = propagate(truth[None], 0.1, np.zeros(11), None)[0]
        est = pf.step(toy_scan(pts, truth, rng, k), 0.1)
        counts.append(pf.n)
    return counts, est, truth


def test_count_shrinks_once_localized_and_grows_back_on_reinit(toy_world):
    pts, table = toy_world
    pf = ParticleFilter(planar_cfg(temperature=20.0), table, [0, 0, 1.7], [40, 40, 1.7], seed=3)
    assert pf.n == 2000
    counts, est, truth = track(pf, pts, 15)
    assert np.linalg.norm(est.state[:2] - truth[:2]) < 0.5
    assert counts[-1] < 400 and len(pf.states) == len(pf.log_weights) == pf.n == counts[-1]
    assert pf.weights.sum() == pytest.approx(1.0)
    pf.initialize()  # a kidnap / re-initialisation
    assert pf.n == 2000 and pf.states.shape == (2000, 11)


def test_spread_cloud_keeps_the_budget_and_a_spreading_cloud_grows(toy_world):
    pts, table = toy_world
    cfg = planar_cfg(n_particles=1000)
    pf = ParticleFilter(cfg, table, [0, 0, 1.7], [40, 40, 1.7], seed=0)
    # 40 % of a uniformly spread cloud holds all weight: it occupies hundreds of bins
    lw = np.where(np.arange(1000) % 5 < 2, 0.0, -np.inf)
    pf.log_weights = lw - np.log(400)
    assert pf.resample_if_needed()
    assert pf.n == 1000 and pf.kld_bins > 300
    # converge: every particle in one bin → the floor
    pf.states[:, :2] = [12.5, 10.5]
    pf.states[:, 3] = 0.0
    pf.log_weights[:] = -np.inf
    pf.log_weights[0] = 0.0
    assert pf.resample_if_needed() and pf.n == cfg.kld_min and pf.kld_bins == 1
    # the 50 particles spread again over 40 × 40 m (e.g. an ambiguous stretch): resampling grows
    rng = np.random.default_rng(1)
    pf.states[:, :2] = rng.uniform(0, 40, (pf.n, 2))
    pf.log_weights = np.where(np.arange(pf.n) < 20, 0.0, -np.inf) - np.log(20)
    assert pf.resample_if_needed()
    assert pf.n > 3 * cfg.kld_min and pf.kld_bins == 20


@pytest.mark.parametrize("protect", [3, 900])
def test_protected_particle_survives_a_count_change(toy_world, protect):
    pts, table = toy_world
    pf = ParticleFilter(planar_cfg(n_particles=1000), table, [0, 0, 1.7], [40, 40, 1.7], seed=0)
    pf.states[:, :2] = [20.0, 20.0]  # all in one bin …
    kept = pf.states[protect].copy()
    kept[:2] = [5.0, 5.0]  # … but the protected one
    pf.states[protect] = kept
    pf.log_weights[:] = -np.inf
    pf.log_weights[7] = 0.0
    assert pf.resample_if_needed(protect=protect)
    assert pf.n == 50
    j = pf.protected_index
    assert j == (protect if protect < 50 else 49)
    np.testing.assert_array_equal(pf.states[j], kept)
    assert np.sum(np.all(pf.states == kept, axis=1)) == 1


def test_without_kld_the_count_and_the_protected_index_stay(toy_world):
    _, table = toy_world
    pf = ParticleFilter(paper_pf(n_particles=500), table, [0, 0, 0], [40, 40, 4], seed=0)
    pf.log_weights[:] = -np.inf
    pf.log_weights[0] = 0.0
    assert pf.resample_if_needed(protect=321)
    assert pf.n == 500 and pf.protected_index == 321 and pf.kld_bins is None
    assert not pf.resample_if_needed(protect=12) and pf.protected_index == 12
    assert not pf.resample_if_needed() and pf.protected_index is None


def test_same_seed_same_counts(toy_world):
    pts, table = toy_world
    runs = []
    for seed in (5, 5, 6):
        pf = ParticleFilter(planar_cfg(temperature=20.0, n_particles=800), table, [0, 0, 1.7], [40, 40, 1.7], seed=seed)
        counts, _, _ = track(pf, pts, 8)
        runs.append((counts, pf.states.copy()))
    assert runs[0][0] == runs[1][0]
    np.testing.assert_array_equal(runs[0][1], runs[1][1])
    assert runs[0][0] != runs[2][0] or not np.array_equal(runs[0][1], runs[2][1])


def test_a_set_count_is_the_new_ceiling(toy_world):
    """set_n_particles (tracking mode, the GUI's particle count) caps what KLD-sampling may draw
    and what a fresh cloud gets, also through a checkpoint; below kld_min it is kept as it is."""
    _, table = toy_world
    pf = ParticleFilter(paper_pf(n_particles=500, kld=True, kld_min=200), table, [0, 0, 0], [40, 40, 4], seed=0)
    pf.set_n_particles(120)
    pf.log_weights[:] = np.log(np.full(120, 1 / 120) * np.r_[1.0, np.full(119, 1e-6)])
    assert pf.resample_if_needed() and pf.n == 120  # kld_min 200 > 120: the set count holds
    restored = ParticleFilter(paper_pf(n_particles=500, kld=True, kld_min=200), table, [0, 0, 0], [40, 40, 4], seed=0)
    restored.restore(pf.checkpoint())
    restored.initialize()
    assert restored.n == 120 and len(restored.states) == 120
    pf.set_n_particles(500)
    pf.initialize()
    assert pf.n == 500

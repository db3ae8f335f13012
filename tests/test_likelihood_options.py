"""The likelihood's shape options (core/filter/likelihood.py): tempering, the unexplained-point share,
the per-point mean; the floored variant's weights under both; the paper's likelihood bit for bit
at the defaults; and residual_stats against exact nearest distances."""

import math

import numpy as np
import pytest
from helpers import assert_floor_keeps_the_weights, paper_pf
from lidarloc.core.errors import LidarlocError
from lidarloc.core.filter.likelihood import (
    PER_POINT,
    cost_table,
    log_likelihood,
    log_likelihood_floored,
    residual_stats,
    squared_cost_table,
)
from lidarloc.core.geometry import inv_pose, pose_matrix, transform_points
from lidarloc.core.maps.lookup import MISS_CODE
from scipy.spatial import cKDTree


def _problem(pts, n=40, m=3000, seed=0, spread=1.5):
    rng = np.random.default_rng(seed)
    scan = (pts[rng.integers(0, len(pts), m)] - [12, 10, 1.7]).astype(np.float32)
    states = np.zeros((n, 11))
    states[:, :3] = [12, 10, 1.7] + rng.normal(0, spread, (n, 3))
    states[:, 3:6] = rng.normal(0, 0.1, (n, 3))
    return scan, states


def test_defaults_are_the_papers_likelihood_bit_for_bit(toy_world):
    pts, table = toy_world
    scan, states = _problem(pts)
    np.testing.assert_array_equal(cost_table(table, 5.0, 0.5), squared_cost_table(table, 5.0, 0.5))
    np.testing.assert_array_equal(cost_table(table, 5.0, 0.5, 1.0, 0.0), squared_cost_table(table, 5.0, 0.5))
    plain = log_likelihood(states, scan, table, 5.0, 0.5)
    np.testing.assert_array_equal(
        log_likelihood(states, scan, table, 5.0, 0.5, temperature=1.0, unexplained_share=0.0), plain
    )
    prior = np.log(np.full(len(states), 1.0 / len(states)))
    np.testing.assert_array_equal(
        log_likelihood_floored(states, scan, table, 5.0, 0.5, prior, temperature=1.0, unexplained_share=0.0),
        log_likelihood_floored(states, scan, table, 5.0, 0.5, prior),
    )


def test_temperature_divides_the_log_likelihood(toy_world):
    pts, table = toy_world
    scan, states = _problem(pts)
    plain = log_likelihood(states, scan, table, 5.0, 0.5)
    for t in (1.5, 10.0, 100.0):
        np.testing.assert_allclose(log_likelihood(states, scan, table, 5.0, 0.5, temperature=t), plain / t, rtol=1e-12)
    # PER_POINT: T = the number of scan points (the per-point mean)
    np.testing.assert_allclose(
        log_likelihood(states, scan, table, 5.0, 0.5, temperature=PER_POINT), plain / len(scan), rtol=1e-12
    )


def test_unexplained_share_is_the_per_point_mixture(toy_world):
    pts, table = toy_world
    scan, states = _problem(pts, n=20)
    for z, d_max, sigma in ((0.1, 5.0, 0.5), (0.01, 2.0, 0.8)):
        ll = log_likelihood(states, scan, table, d_max, sigma, unexplained_share=z)
        expected = []
        for s in states:
            d = table.query(transform_points(pose_matrix(*s[:6]), scan), d_max=d_max).astype(np.float64)
            p = (1 - z) * np.exp(-np.minimum(d * d, d_max * d_max) / sigma**2) + z
            expected.append(np.sum(np.log(p)))
        np.testing.assert_allclose(ll, expected, rtol=1e-4)
    # a point the map cannot explain costs −log((1 − z)·e^(−d_max²/σ²) + z) ≈ −log z, not d_max²/σ²
    table_z = cost_table(table, 5.0, 0.5, 1.0, 0.1)
    assert table_z[MISS_CODE] == pytest.approx(-math.log(0.9 * math.exp(-100.0) + 0.1), rel=1e-12)
    assert table_z[0] == 0.0 and np.all(np.diff(table_z[:255]) >= 0)


def test_far_points_outvote_the_scan_less_with_an_unexplained_share(toy_world):
    """An object that is not in the map (500 points floating 10 m up) shifts every particle's
    log-likelihood by the same amount, 500 × the cost of a miss: with z = 0.1 that is 2.3 nats
    per point, not 100."""
    pts, table = toy_world
    scan, states = _problem(pts, n=20)
    ghost = np.random.default_rng(5).uniform([-3, -3, 10], [3, 3, 12], (500, 3)).astype(np.float32)
    both = np.concatenate([scan, ghost])
    for z in (0.0, 0.1):
        shift = log_likelihood(states, both, table, 5.0, 0.5, unexplained_share=z) - log_likelihood(
            states, scan, table, 5.0, 0.5, unexplained_share=z
        )
        miss = cost_table(table, 5.0, 0.5, 1.0, z)[MISS_CODE]
        np.testing.assert_allclose(shift, -500 * miss, rtol=1e-9)
    assert cost_table(table, 5.0, 0.5, 1.0, 0.1)[MISS_CODE] < 2.31


@pytest.mark.parametrize("temperature, share", [(3.0, 0.0), (1.0, 0.05), (2.0, 0.02)])
def test_floored_variant_gives_the_same_weights_with_scaled_costs(toy_world, temperature, share):
    """The floor's margin is in nats of the final log-likelihood: with scaled per-point costs
    the floored weights are still those of the plain sum."""
    pts, table = toy_world
    rng = np.random.default_rng(1)
    scan = (pts[rng.integers(0, len(pts), 4000)] - [15, 12, 1.7]).astype(np.float32)
    states = np.zeros((500, 11))
    states[:, :3] = [15, 12, 1.7] + rng.normal(0, [3, 3, 0.3], (500, 3))
    states[:, 3] = rng.normal(0, 0.3, 500)
    prior = np.log(rng.dirichlet(np.ones(500)))
    kw = dict(temperature=temperature, unexplained_share=share)
    exact = prior + log_likelihood(states, scan, table, 5.0, 0.5, **kw)
    floored = prior + log_likelihood_floored(states, scan, table, 5.0, 0.5, prior, **kw)
    assert_floor_keeps_the_weights(exact, floored, min_floored=50)


def test_a_high_temperature_floors_nothing(toy_world):
    pts, table = toy_world
    scan, states = _problem(pts, n=200, spread=3.0)
    prior = np.full(200, -math.log(200))
    exact = log_likelihood(states, scan, table, 5.0, 0.5, temperature=PER_POINT)
    np.testing.assert_allclose(
        log_likelihood_floored(states, scan, table, 5.0, 0.5, prior, temperature=PER_POINT), exact, rtol=1e-12
    )


@pytest.mark.parametrize(
    "kw",
    [
        dict(temperature=0.5),
        dict(temperature=-1.0),
        dict(temperature=math.inf),
        dict(unexplained_share=1.0),
        dict(unexplained_share=-0.1),
    ],
)
def test_impossible_shapes_are_refused(toy_world, kw):
    pts, table = toy_world
    scan, states = _problem(pts, n=2, m=10)
    with pytest.raises(LidarlocError):
        log_likelihood(states, scan, table, 5.0, 0.5, **kw)
    with pytest.raises(LidarlocError):
        log_likelihood_floored(states, scan, table, 5.0, 0.5, np.zeros(2), **kw)


# ------------------------------------------------------------------------------ residual_stats
def test_residual_stats_matches_exact_nearest_distances(toy_world):
    """Inlier share and mean residual against a k-d tree of the map, within what the table can
    resolve: its node is up to δ·√3/2 from the point, plus half a quantisation step."""
    pts, table = toy_world
    tree = cKDTree(pts.astype(np.float64))
    tol = table.resolution * math.sqrt(3) / 2 + table.step / 2 + 1e-6
    rng = np.random.default_rng(3)
    pose = np.array([14.0, 11.0, 1.7, 0.6, 0.02, -0.01])
    T = pose_matrix(*pose)
    for d_max in (1.0, 2.0, 5.0):
        # map points with noise, and points floating at every height up to 8 m: all distances occur
        world = np.concatenate(
            [
                pts[rng.integers(0, len(pts), 3000)] + rng.normal(0, 0.05, (3000, 3)),
                rng.uniform([2, 2, 0], [38, 38, 8], (3000, 3)),
            ]
        )
        scan = transform_points(inv_pose(T), world).astype(np.float32)
        d_true, _ = tree.query(world)
        share, mean = residual_stats(pose, scan, table, d_max)
        assert np.mean(d_true < d_max - tol) <= share <= np.mean(d_true < d_max + tol)
        # the lookup distance of every point is within tol of the truth, so is their mean over any
        # inlier set lying between the two bracketing sets
        lo_set, hi_set = d_true < d_max - tol, d_true < d_max + tol
        assert min(d_true[lo_set].mean(), d_true[hi_set].mean()) - tol <= mean
        assert mean <= max(d_true[lo_set].mean(), d_true[hi_set].mean()) + tol
    # points clearly inside or outside the band: the share is exact and the mean within tol
    near = pts[rng.integers(0, len(pts), 2000)] + rng.normal(0, 0.03, (2000, 3))
    far = rng.uniform([5, 5, 9], [35, 35, 12], (500, 3))  # ≥ 5 m above everything
    scan = transform_points(inv_pose(T), np.concatenate([near, far])).astype(np.float32)
    share, mean = residual_stats(pose, scan, table, 2.0)
    assert share == 2000 / 2500
    assert abs(mean - tree.query(near)[0].mean()) <= tol


def test_residual_stats_edge_cases(toy_world):
    pts, table = toy_world
    share, mean = residual_stats(np.zeros(6), np.zeros((0, 3)), table, 5.0)
    assert share == 0.0 and math.isnan(mean)
    share, mean = residual_stats([1e4, 0, 0, 0, 0, 0], pts[:100], table, 5.0)  # far off the map
    assert share == 0.0 and math.isnan(mean)
    share, mean = residual_stats(np.zeros(11), pts[:100], table, 50.0)  # d_max capped at the table's
    assert share == 1.0 and 0 <= mean < 0.3
    with pytest.raises(LidarlocError):
        residual_stats(np.zeros(3), pts[:10], table, 5.0)
    with pytest.raises(LidarlocError):
        residual_stats(np.zeros(6), pts[:10], table, 0.0)


@pytest.mark.parametrize("temperature, share", [(1.0, 0.0), (PER_POINT, 0.0), (10.0, 0.1)])
def test_filter_reweight_agrees_with_its_update(toy_world, temperature, share):
    """The S2M landing re-weighs one particle with reweight(): for an unchanged particle it must
    give back the update's own log-likelihood (same T, same z, same points), whatever the shape."""
    from lidarloc.core.filter.pf import ParticleFilter

    pts, table = toy_world
    scan, _ = _problem(pts, m=2500)
    pf = ParticleFilter(
        paper_pf(n_particles=200, temperature=temperature, unexplained_share=share),
        table,
        [0, 0, 0],
        [40, 40, 4],
        seed=0,
    )
    pf.initialize(pose=pose_matrix(12, 10, 1.7, 0, 0, 0), pose_std=1.0)
    pf.update(scan)
    j = int(np.argmax(pf.log_weights))
    before = pf.log_weights.copy()
    expected = log_likelihood(
        pf.states[j : j + 1], scan, table, 5.0, 0.5, temperature=temperature, unexplained_share=share
    )[0]
    assert pf.reweight(j, scan) == pytest.approx(expected, rel=1e-9)
    np.testing.assert_allclose(pf.log_weights, before, rtol=0, atol=1e-9)


# ------------------------------------------------------------------------------ point budget
def test_subset_for_spreads_the_budget_over_the_whole_scan():
    from lidarloc.core.filter.likelihood import subset_for

    assert subset_for(5000, 0) is None and subset_for(5000, 5000) is None and subset_for(5000, 9000) is None
    pick = subset_for(15000, 2000)
    assert len(pick) == len(np.unique(pick)) == 2000 and np.all(np.diff(pick) > 0)
    # evenly spread: every tenth of the scan holds ~a tenth of the picks
    counts = np.bincount(pick * 10 // 15000, minlength=10)
    assert counts.min() >= 190 and counts.max() <= 210


def test_point_weight_scales_the_log_likelihood(toy_world):
    pts, table = toy_world
    scan, states = _problem(pts)
    plain = log_likelihood(states, scan, table, 5.0, 0.5, temperature=100.0)
    np.testing.assert_allclose(
        log_likelihood(states, scan, table, 5.0, 0.5, temperature=100.0, point_weight=4.0), 4.0 * plain, rtol=1e-12
    )
    with pytest.raises(LidarlocError):
        log_likelihood(states, scan, table, 5.0, 0.5, point_weight=0.5)


@pytest.mark.parametrize("temperature", [1.0, 3000.0, PER_POINT])
def test_filter_with_a_point_budget_estimates_the_whole_scans_likelihood(toy_world, temperature):
    """max_points weighs an evenly spread subset whose sum is scaled to the whole scan: the
    particles' log-likelihoods are those of the whole scan up to the subset's sampling error
    (here a few %), their ranking is kept, reweight() agrees with the update, and a budget
    of 0 or ≥ the scan's points is the filter without a budget, bit for bit."""
    from lidarloc.core.filter.pf import ParticleFilter

    pts, table = toy_world
    scan, _ = _problem(pts, m=6000, seed=3)

    def filtered(max_points):
        pf = ParticleFilter(
            paper_pf(n_particles=200, temperature=temperature, max_points=max_points),
            table,
            [0, 0, 0],
            [40, 40, 4],
            seed=0,
        )
        pf.initialize(pose=pose_matrix(12, 10, 1.7, 0, 0, 0), pose_std=1.0)
        pf.update(scan)
        return pf

    whole = filtered(0)
    np.testing.assert_array_equal(filtered(6000).log_likelihoods, whole.log_likelihoods)
    budget = filtered(1500)
    assert len(budget.weighed_points) == 1500
    exact = log_likelihood(budget.states, scan, table, 5.0, 0.5, temperature=temperature)
    estimate = budget.log_likelihoods
    if temperature == 1.0:
        # untempered, all but a few particles sit at the weight floor: compare those above it
        keep = budget.log_weights > np.max(budget.log_weights) - 700
        estimate, exact = estimate[keep], exact[keep]
        assert np.argmax(estimate) == np.argmax(exact)
    else:
        assert np.corrcoef(estimate, exact)[0, 1] > 0.99
        # what sets the weights is how particles differ: the subset keeps that to ~10 % of its spread
        err = (estimate - estimate.mean()) - (exact - exact.mean())
        assert np.std(err) < 0.1 * np.std(exact)
    assert abs(np.mean(estimate) / np.mean(exact) - 1) < 0.05  # no bias
    j = int(np.argmax(budget.log_weights))
    assert budget.reweight(j, scan) == pytest.approx(budget.log_likelihoods[j], rel=1e-9)


def test_a_negative_point_budget_is_refused():
    from lidarloc.core.config import load_config

    with pytest.raises(LidarlocError, match="max_points"):
        load_config(None, ["pf.max_points=-1"])

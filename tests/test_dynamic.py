"""Dynamic-point rejection (core/filter/dynamic.py and the filter's use of it): points that stay far
from the map over consecutive scans are left out, points that fit the map never are, a cluster
seen once is kept, a moving object is followed, a wrong pose rejects nothing, and with the
option off (or nothing to reject) the filter is unchanged."""

import math

import numpy as np
import pytest
from helpers import paper_pf, toy_scan
from lidarloc.core.errors import LidarlocError
from lidarloc.core.filter.dynamic import DynamicPointFilter
from lidarloc.core.filter.likelihood import log_likelihood, scrambled_order
from lidarloc.core.filter.motion import propagate
from lidarloc.core.filter.pf import ParticleFilter
from lidarloc.core.geometry import inv_pose, pose_matrix, transform_points

POSE = np.array([12.0, 10.0, 1.7, 0.3, 0.0, 0.0])


def box(centre, rng, n=200, size=(2.0, 1.5, 1.2)):
    """n points in a box around ``centre`` (world frame): a car-sized object."""
    return np.asarray(centre) + rng.uniform(-0.5, 0.5, (n, 3)) * size


def sensor_scan(world_pts, pose=POSE):
    return transform_points(inv_pose(pose_matrix(*pose)), world_pts).astype(np.float32)


def test_a_cluster_far_from_the_map_is_rejected_from_its_second_scan(toy_world):
    pts, table = toy_world
    rng = np.random.default_rng(0)
    f = DynamicPointFilter(table, distance=1.0, scans=2)
    for k in range(3):
        static = pts[rng.integers(0, len(pts), 3000)] + rng.normal(0, 0.02, (3000, 3))
        car = box([18, 14, 2.5], rng)  # 1.9 m above the ground: far from the map
        keep = f.keep_mask(sensor_scan(np.concatenate([static, car])), POSE)
        assert keep[:3000].all()  # map-consistent points are always kept
        if k == 0:
            assert keep.all() and f.n_far == 200  # one scan's misfit rejects nothing
        else:
            assert not keep[3000:].any() and f.n_rejected == 200


def test_more_scans_needed_when_asked_and_a_passing_cluster_is_kept(toy_world):
    pts, table = toy_world
    rng = np.random.default_rng(1)
    f = DynamicPointFilter(table, distance=1.0, scans=3)
    static = pts[rng.integers(0, len(pts), 2000)]
    rejected = []
    for _k in range(4):
        keep = f.keep_mask(sensor_scan(np.concatenate([static, box([18, 14, 2.5], rng)])), POSE)
        rejected.append(int((~keep[2000:]).sum()))
    assert rejected == [0, 0, 200, 200]
    # a cluster that shows up once, elsewhere, and then disappears starts over at 1
    f.reset()
    f.keep_mask(sensor_scan(np.concatenate([static, box([18, 14, 2.5], rng)])), POSE)
    keep = f.keep_mask(sensor_scan(np.concatenate([static, box([25, 30, 2.5], rng)])), POSE)
    assert keep.all()


def test_a_moving_object_is_followed_from_cell_to_cell(toy_world):
    """A car moving 1 m per scan (36 km/h at 10 Hz) keeps being rejected."""
    pts, table = toy_world
    rng = np.random.default_rng(2)
    f = DynamicPointFilter(table, distance=1.0, scans=2)
    static = pts[rng.integers(0, len(pts), 2000)]
    rejected = []
    for k in range(5):
        keep = f.keep_mask(sensor_scan(np.concatenate([static, box([14 + k, 16, 2.5], rng)])), POSE)
        rejected.append(int((~keep[2000:]).sum()))
        assert keep[:2000].all()
    assert rejected[0] == 0 and min(rejected[1:]) >= 190, rejected


def test_a_wrong_pose_rejects_nothing(toy_world):
    """When most of the scan is far, the pose is what is wrong: every point is kept and the far
    cells are forgotten."""
    pts, table = toy_world
    rng = np.random.default_rng(3)
    f = DynamicPointFilter(table, distance=1.0, scans=1)
    world = pts[rng.integers(0, len(pts), 3000)]
    scan = sensor_scan(world)
    wrong = POSE + [0, 0, 3.0, 0, 0, 0]  # 3 m up: the ground is 3 m away
    for _ in range(3):
        assert f.keep_mask(scan, wrong).all() and f.suspect and f.n_cells == 0
    assert f.keep_mask(scan, POSE).all() and not f.suspect


def test_bad_arguments(toy_world):
    _, table = toy_world
    with pytest.raises(LidarlocError):
        DynamicPointFilter(table, distance=0.0, scans=2)
    with pytest.raises(LidarlocError):
        DynamicPointFilter(table, distance=1.0, scans=0)
    f = DynamicPointFilter(table, distance=1.0, scans=2)
    with pytest.raises(LidarlocError):
        f.keep_mask(np.zeros((5, 2)), POSE)
    assert f.keep_mask(np.zeros((0, 3)), POSE).shape == (0,)


# ------------------------------------------------------------------------------ in the filter
def tracking_filter(table, **kw):
    q = np.zeros(11)
    q[0] = q[1] = 0.1
    cfg = paper_pf(
        n_particles=300, init_yaw=0.0, init_pitch=0.0, init_roll=0.0, init_rate_std=0.0, q_std=tuple(q), **kw
    )
    pf = ParticleFilter(cfg, table, [0, 0, 1.7], [40, 40, 1.7], seed=4)
    pf.initialize(pose=pose_matrix(*POSE), pose_std=(0.3, 0.3, 0.0, 0.0, 0.0, 0.0), speed=0.0)
    return pf


def test_the_filter_leaves_out_the_rejected_points(toy_world):
    pts, table = toy_world
    rng = np.random.default_rng(5)
    truth = np.zeros(11)
    truth[:6] = POSE
    pf = tracking_filter(table, dynamic_rejection=True, dynamic_distance=1.0, dynamic_scans=2)
    for k in range(3):
        clean = toy_scan(pts, truth, rng, k)
        car = sensor_scan(box([16, 13, 2.5], rng))
        scan = np.concatenate([clean, car])
        pf.predict(0.1)
        states = pf.states.copy()
        pf.update(scan)
        if k == 0:
            assert pf.dynamic.n_rejected == 0
        else:
            assert pf.dynamic.n_rejected == len(car)
            # the weights are those of the scan without the car …
            expected = log_likelihood(states, clean[scrambled_order(len(clean))], table, 5.0, 0.5)
            keep = expected > expected.max() - 800
            np.testing.assert_allclose(pf.log_likelihoods[keep], expected[keep], rtol=1e-9)
            # … and so is a reweight of the same scan array (the S2M landing)
            j = int(np.argmax(pf.log_weights))
            assert pf.reweight(j, scan) == pytest.approx(expected[j], rel=1e-9)
        pf.resample_if_needed()
    # a new (re-)initialisation forgets the far cells
    pf.initialize(pose=pose_matrix(*POSE), pose_std=0.3)
    assert pf.dynamic.n_cells == 0


def test_no_change_with_the_option_off_or_nothing_to_reject(toy_world):
    """On scans that fit the map, rejection on gives the filter of rejection off, bit for bit."""
    pts, table = toy_world
    runs = []
    for on in (False, True):
        rng = np.random.default_rng(6)
        truth = np.zeros(11)
        truth[:6] = POSE
        truth[6] = 1.0
        pf = tracking_filter(table, dynamic_rejection=on)
        for k in range(6):
            truth = propagate(truth[None], 0.1, np.zeros(11), None)[0]
            pf.step(toy_scan(pts, truth, rng, k), 0.1)
        runs.append(pf)
        assert (pf.dynamic is not None) == on
    np.testing.assert_array_equal(runs[0].states, runs[1].states)
    np.testing.assert_array_equal(runs[0].log_weights, runs[1].log_weights)
    assert runs[1].dynamic.n_rejected == 0


def test_a_spread_cloud_rejects_nothing(toy_world):
    pts, table = toy_world
    rng = np.random.default_rng(7)
    pf = ParticleFilter(
        paper_pf(n_particles=300, dynamic_rejection=True, dynamic_scans=1), table, [0, 0, 1.7], [40, 40, 1.7], seed=0
    )  # uniform over the map
    scan = np.concatenate([sensor_scan(pts[rng.integers(0, len(pts), 1000)]), sensor_scan(box([16, 13, 2.5], rng))])
    pf.update(scan)
    assert len(pf.weighed_points) == len(scan) and pf.dynamic.n_cells == 0
    assert math.isfinite(pf.log_weights.max())

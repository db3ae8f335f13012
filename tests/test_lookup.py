"""The nearest-distance lookup table L (core/maps/lookup.py): accuracy against a k-d tree (on a
synthetic street and on the real drive's map), the d_max clamp, its cache (save/load, keyed
directory, reuse for a smaller d_max, corrupt entries)."""

import json
import math

import numpy as np
import pytest
from lidarloc.core.errors import DataError, LidarlocError
from lidarloc.core.maps.lookup import LookupTable, load_or_build_lookup
from lidarloc.core.maps.mapping import PriorMap
from scipy.spatial import cKDTree

RES = 0.25
D_MAX = 3.0


def street_points(seed=0) -> np.ndarray:
    """A small street: uneven ground, two facades, a few poles and scattered clutter, sampled
    irregularly like a fused LiDAR map (so nearest points are not on the lookup grid)."""
    rng = np.random.default_rng(seed)
    n = 60_000
    gx, gy = rng.uniform(0, 40, n), rng.uniform(0, 30, n)
    ground = np.c_[gx, gy, 0.1 * np.sin(gx / 3.0) + rng.normal(0, 0.03, n)]
    m = 20_000
    facade_a = np.c_[rng.uniform(0, 40, m), np.full(m, 2.0) + rng.normal(0, 0.02, m), rng.uniform(0, 8, m)]
    facade_b = np.c_[rng.uniform(0, 40, m), np.full(m, 27.0) + rng.normal(0, 0.02, m), rng.uniform(0, 6, m)]
    poles = np.concatenate(
        [
            np.c_[
                np.full(500, x) + rng.normal(0, 0.05, 500),
                np.full(500, y) + rng.normal(0, 0.05, 500),
                rng.uniform(0, 4, 500),
            ]
            for x, y in [(8, 10), (20, 15), (33, 20)]
        ]
    )
    clutter = rng.uniform([0, 0, 0], [40, 30, 3], (300, 3))
    return np.concatenate([ground, facade_a, facade_b, poles, clutter]).astype(np.float32)


@pytest.fixture(scope="module")
def street():
    pts = street_points()
    return pts, LookupTable.build(pts, RES, D_MAX), cKDTree(pts.astype(np.float64))


def test_distances_match_kdtree_within_half_cell_diagonal(street):
    pts, table, tree = street
    rng = np.random.default_rng(1)
    lo, hi = pts.min(axis=0) - 4.0, pts.max(axis=0) + 4.0
    # Uniform points (mostly far, many beyond d_max) plus points close to the surfaces (inside
    # the d_max band), including some outside the map's own bounding box.
    uniform = rng.uniform(lo, hi, (20_000, 3))
    near = pts[rng.integers(0, len(pts), 20_000)] + rng.normal(0, 0.8, (20_000, 3))
    q = np.concatenate([uniform, near])
    truth = np.minimum(tree.query(q, distance_upper_bound=D_MAX + 1)[0], D_MAX)
    got = table.query(q)
    assert got.dtype == np.float32
    assert (truth < D_MAX).sum() > 20_000 and (truth >= D_MAX).sum() > 2_000  # both sides of the band
    err = np.abs(got - truth)
    # A query reads its cell's centre node: 1-Lipschitz distance ⇒ ≤ δ·√3/2 from the node, plus the
    # uint8 quantisation (half a step) of the stored value.
    bound = RES * math.sqrt(3) / 2 + table.step / 2 + 1e-6
    assert err.max() <= bound, f"max error {err.max():.4f} m > {bound:.4f} m"
    assert np.median(err) < RES / 4  # typical error far below the worst case


def test_node_values_are_exact_nearest_distances(street):
    pts, table, tree = street
    rng = np.random.default_rng(2)
    nodes = table.origin + (rng.integers(0, table.shape, (30_000, 3)) + 0.5) * RES
    truth = np.minimum(tree.query(nodes, distance_upper_bound=D_MAX + 1)[0], D_MAX)
    err = np.abs(table.query(nodes) - truth)
    in_band = truth < D_MAX
    assert in_band.sum() > 3_000
    # Exact up to quantisation at (nearly) every node; the rare misses of the nearest-point
    # propagation are a few centimetres.
    assert np.mean(err[in_band] <= table.step / 2 + 1e-6) >= 0.995
    assert err.max() < 0.1


def test_outside_the_grid_and_misses_read_d_max(street):
    _, table, _ = street
    far = np.array([[1e4, 0, 0], [-1e4, 5, 5], [20, 15, 500], [20, 15, -500]])
    assert np.all(table.query(far) == np.float32(D_MAX))


def test_lower_d_max_is_a_read_time_clamp(street):
    pts, table, tree = street
    rng = np.random.default_rng(3)
    q = pts[rng.integers(0, len(pts), 5000)] + rng.normal(0, 1.0, (5000, 3))
    full = table.query(q)
    clamped = table.query(q, d_max=1.0)
    np.testing.assert_array_equal(clamped, np.minimum(full, np.float32(1.0)))
    assert (full > 1.0).any()
    # asking for more than was built gives the built cap (the table holds nothing farther)
    np.testing.assert_array_equal(table.query(q, d_max=10.0), full)


def test_memory_is_block_sparse(street):
    _, table, _ = street
    dense = np.prod(table.shape)  # one byte per cell
    assert table.nbytes < dense
    assert table.nbytes == table.brick_index.nbytes + table.bricks.nbytes


def test_save_load_roundtrip(street, tmp_path):
    _, table, _ = street
    table.save(tmp_path / "L")
    loaded = LookupTable.load(tmp_path / "L")
    assert loaded.resolution == table.resolution and loaded.d_max_built == table.d_max_built
    np.testing.assert_array_equal(loaded.origin, table.origin)
    np.testing.assert_array_equal(loaded.bricks, table.bricks)
    np.testing.assert_array_equal(loaded.brick_index, table.brick_index)


def test_cache_is_keyed_reused_for_smaller_d_max_and_rebuilt_when_corrupt(tmp_path):
    pts = street_points(seed=5)[::4]
    prior = PriorMap(points=pts, points_bev=pts, voxel_size=0.2)
    fractions = []
    t1, _, cached = load_or_build_lookup(prior, tmp_path, RES, D_MAX, progress=fractions.append)
    assert not cached and fractions and fractions[-1] == pytest.approx(1.0)
    entry = tmp_path / f"lookup-r{RES:g}-d{D_MAX:g}"
    assert (entry / "lookup.json").is_file()
    assert not [p for p in tmp_path.iterdir() if ".tmp-" in p.name]  # atomic: no leftovers
    t2, _, cached = load_or_build_lookup(prior, tmp_path, RES, D_MAX)
    assert cached and np.array_equal(t2.bricks, t1.bricks)
    # a smaller d_max needs no rebuild: the larger table is reused and clamped at read time
    t3, _, cached = load_or_build_lookup(prior, tmp_path, RES, 1.5)
    assert cached and t3.d_max_built == D_MAX
    # a corrupt entry is rebuilt, not trusted
    (entry / "bricks.npy").write_bytes(b"not a numpy file")
    t4, _, cached = load_or_build_lookup(prior, tmp_path, RES, D_MAX)
    assert not cached and np.array_equal(t4.bricks, t1.bricks)
    meta = json.loads((entry / "lookup.json").read_text())
    assert meta["d_max_built"] == D_MAX and meta["resolution"] == RES


def test_bad_inputs_are_one_line_errors(tmp_path):
    with pytest.raises(LidarlocError):
        LookupTable.build(np.zeros((10, 3)), 0.0, 5.0)
    with pytest.raises(LidarlocError):
        LookupTable.build(np.zeros((10, 3)), 0.25, -1.0)
    with pytest.raises(DataError):
        LookupTable.build(np.zeros((0, 3)), 0.25, 5.0)
    with pytest.raises(DataError):
        LookupTable.build(np.array([[0, 0, np.nan]]), 0.25, 5.0)
    with pytest.raises(DataError):
        LookupTable.load(tmp_path / "missing")


def test_lookup_matches_kdtree_on_the_real_map(kitti_raw_map):
    _, prior, table = kitti_raw_map
    rng = np.random.default_rng(0)
    pts = prior.points
    q = np.concatenate(
        [
            pts[rng.integers(0, len(pts), 15_000)] + rng.normal(0, 1.0, (15_000, 3)),
            rng.uniform(pts.min(axis=0), pts.max(axis=0), (15_000, 3)),
        ]
    )
    truth = np.minimum(cKDTree(pts).query(q, distance_upper_bound=6.0)[0], 5.0)
    err = np.abs(table.query(q) - truth)
    assert err.max() <= 0.25 * math.sqrt(3) / 2 + table.step / 2 + 1e-6

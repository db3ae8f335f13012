"""The prior map (core/maps/mapping.py): voxel centroids, road removal on a real scan, and a real map
built once and then read from its cache."""

import numpy as np
from lidarloc.core.config import MapConfig
from lidarloc.core.geometry import pose_matrix
from lidarloc.core.maps import voxel_grid
from lidarloc.core.maps.mapping import flat_surface_mask, load_or_build_map, range_filter
from lidarloc.core.maps.voxel_grid import VoxelAccumulator, voxel_centroids
from lidarloc.core.sequences.base import Limited


def test_voxel_accumulator_centroids_and_growth():
    acc = VoxelAccumulator(1.0, capacity=16)  # tiny capacity forces several table growths
    rng = np.random.default_rng(1)
    cells = rng.integers(-50, 50, size=(400, 3))
    pts = np.repeat(cells, 3, axis=0) + rng.uniform(0.01, 0.99, size=(1200, 3))
    acc.add(pts[:600])
    acc.add(pts[600:])
    out = acc.points()
    uniq = np.unique(cells, axis=0)
    assert len(out) == len(uniq)
    # each output point is the centroid of the inputs in its voxel
    keys = np.floor(pts).astype(int)
    for c in uniq[:20]:
        mask = (keys == c).all(axis=1)
        centroid = pts[mask].mean(axis=0)
        assert np.min(np.linalg.norm(out - centroid, axis=1)) < 1e-5


def test_voxel_centroids_streamed_in_chunks_equal_one_pass(monkeypatch):
    """The centroids of a map read a chunk at a time (so that a city map is never copied whole)
    are those of one pass over every point, from a read-only memory map too; past ``cap`` voxels
    the answer is None."""
    rng = np.random.default_rng(3)
    pts = rng.uniform(-20, 20, size=(5000, 3)).astype(np.float32)
    whole = VoxelAccumulator(2.0)
    whole.add(pts)
    expected = whole.points()
    monkeypatch.setattr(voxel_grid, "CENTROID_CHUNK", 333)  # 16 chunks, voxels split across them
    read_only = pts.copy()
    read_only.flags.writeable = False
    got = voxel_centroids(read_only, 2.0)
    assert got is not None and got.dtype == np.float32
    order = lambda a: a[np.lexsort(a.T)]  # noqa: E731
    np.testing.assert_allclose(order(got), order(expected), atol=1e-5)
    assert len(expected) > 900  # 20³ voxels, most hit: the comparison is not of a handful
    assert voxel_centroids(pts, 2.0, cap=100) is None
    assert voxel_centroids(pts, 2.0, cap=len(expected)) is not None


def test_adding_a_scan_at_a_pose_equals_filtering_and_transforming_it_first():
    """add_scan (the map's fusion: one pass per scan) gives the very same centroids, bit for bit,
    as range_filter, the rigid transform and add; returns at exactly the range limits count the
    same way too."""
    cfg = MapConfig()
    rng = np.random.default_rng(3)
    direction = rng.normal(size=(30_000, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    ranges = rng.uniform(0.5 * cfg.scan_min_range, 1.2 * cfg.scan_max_range, len(direction))
    ranges[:20], ranges[20:40] = cfg.scan_min_range, cfg.scan_max_range  # on the limits
    scan = np.concatenate([direction * ranges[:, None], rng.uniform(0, 1, (len(ranges), 1))], axis=1)
    scan = scan.astype(np.float32)
    fused, reference = VoxelAccumulator(cfg.voxel_size, capacity=64), VoxelAccumulator(cfg.voxel_size, capacity=64)
    for k in range(3):
        T = pose_matrix(100.0 * k + 0.3, -40.0 + k, 1.7, 0.4 * k, 0.02, -0.01)
        fused.add_scan(scan, T, cfg.scan_min_range, cfg.scan_max_range)
        pts = range_filter(scan, cfg)[:, :3].astype(np.float64)
        reference.add(pts @ T[:3, :3].T + T[:3, 3])
    assert fused.size == reference.size > 10_000
    np.testing.assert_array_equal(fused.points(), reference.points())


def test_road_removal_keeps_walls_drops_road(kitti_raw_seq):
    pts = kitti_raw_seq.scan(10)[:, :3]
    pts = pts[np.linalg.norm(pts, axis=1) < 30]
    flat = flat_surface_mask(pts, MapConfig())
    road = (pts[:, 2] < -1.4) & (np.linalg.norm(pts[:, :2], axis=1) < 12)  # sensor is 1.73 m above the road
    tall = pts[:, 2] > 0.5  # above the car roofs: walls, trees
    assert flat[road].mean() > 0.8, "most road points should be removed"
    assert (~flat[tall]).mean() > 0.7, "most wall/tree points should be kept"


def test_real_map_build_and_cache(kitti_raw_seq, tmp_path):
    seq = Limited(kitti_raw_seq, 20)
    m1, d, cached = load_or_build_map(seq, MapConfig(), tmp_path)
    assert not cached and len(m1.points) > 100_000 and len(m1.points_bev) < len(m1.points)
    m2, d2, cached2 = load_or_build_map(seq, MapConfig(), tmp_path)
    assert cached2 and d2 == d and np.array_equal(m1.points, m2.points)
    # one point per 0.2 m voxel (centroids are stored as float32, so a handful that sit on a
    # voxel boundary may round into the neighbouring cell)
    keys = np.floor(m1.points.astype(np.float64) / 0.2).astype(np.int64)
    assert len(np.unique(keys, axis=0)) >= 0.9999 * len(keys)

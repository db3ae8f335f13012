"""A large map held as point tiles on disk (core/maps/point_tiles.py): reads across tile borders
give what the whole map gives, the S2M matcher's ground heights and GICP target from the tiles
match the whole map's, and a run on a large tiled map keeps its map on disk and matches from the
tiles in the S2M process."""

from __future__ import annotations

import math

import numpy as np
import pytest
from helpers import short_town
from lidarloc.core.config import Config
from lidarloc.core.errors import DataError
from lidarloc.core.maps import mapping
from lidarloc.core.maps.mapping import load_or_build_map, range_filter
from lidarloc.core.maps.point_tiles import PointTiles
from lidarloc.core.maps.voxel_grid import voxel_centroids
from lidarloc.core.matching.gicp import GICPRefiner, LocalGICPRefiner
from lidarloc.core.matching.ground import GroundGrid, TiledGround


@pytest.fixture(scope="module")
def cloud():
    rng = np.random.default_rng(3)
    pts = np.c_[rng.uniform(-130, 220, 60_000), rng.uniform(-40, 210, 60_000), rng.uniform(-2, 8, 60_000)]
    return pts.astype(np.float32)


def brute(pts, x0, y0, x1, y1):
    keep = (pts[:, 0] >= x0) & (pts[:, 0] <= x1) & (pts[:, 1] >= y0) & (pts[:, 1] <= y1)
    return pts[keep]


def rows(a):
    return a[np.lexsort(a.T[::-1])]


def test_reads_across_tile_borders_are_the_whole_maps(cloud, tmp_path):
    tiles = PointTiles.load_or_build(cloud, tmp_path, "cloud", tile_m=50.0)
    assert (tiles.ntx, tiles.nty) == (8, 6)  # x from −150, y from −50
    assert sum(len(tiles.tile(tx, ty)) for tx in range(tiles.ntx) for ty in range(tiles.nty)) == len(cloud)
    assert np.allclose(tiles.bounds[0], cloud.min(axis=0)) and np.allclose(tiles.bounds[1], cloud.max(axis=0))
    for rect in [(-3.0, -3.0, 3.0, 3.0), (40.0, 90.0, 160.5, 101.0), (-500.0, -500.0, 500.0, 500.0), (0, 0, 50, 50)]:
        got = tiles.points_in(*rect)
        assert np.array_equal(rows(got), rows(brute(cloud, *rect)))
    assert len(tiles.points_in(1000.0, 1000.0, 1100.0, 1100.0)) == 0
    # a tile keeps its points in the map's order
    t = tiles.tile(3, 2)
    first = [int(np.flatnonzero((cloud == p).all(axis=1))[0]) for p in t[:50]]
    assert first == sorted(first)


def test_the_cut_is_cached_and_a_damaged_tile_is_cut_again(cloud, tmp_path):
    tiles = PointTiles.load_or_build(cloud, tmp_path, "cloud", tile_m=50.0)
    stamp = (tmp_path / "tiles.json").stat().st_mtime_ns
    again = PointTiles.load_or_build(cloud, tmp_path, "cloud", tile_m=50.0)
    assert (tmp_path / "tiles.json").stat().st_mtime_ns == stamp and again.rebuilt == []
    want = np.array(tiles.tile(2, 2))
    path = tmp_path / "t2_2.points.npy"
    path.write_bytes(path.read_bytes()[:-12])  # cut short
    reopened = PointTiles.load_or_build(cloud, tmp_path, "cloud", tile_m=50.0)
    assert np.array_equal(reopened.tile(2, 2), want) and reopened.rebuilt == [(2, 2)]
    path.write_bytes(path.read_bytes()[:-12])
    with pytest.raises(DataError, match="t2_2.points.npy"):
        PointTiles.open(tmp_path).tile(2, 2)  # without the map's points: named, not guessed
    other = PointTiles.load_or_build(cloud[:1000], tmp_path, "another map", tile_m=50.0)
    assert other.n_points == 1000


def test_two_cuts_of_one_map_at_once_do_not_mix(cloud, tmp_path):
    """Two processes (here threads) opening the same large map for the first time both cut it: each
    in a staging folder of its own, so neither tile holds the other's copy of a point."""
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(2) as pool:
        list(pool.map(lambda _: PointTiles.load_or_build(cloud, tmp_path, "cloud", tile_m=50.0), range(2)))
    tiles = PointTiles.open(tmp_path)
    assert tiles.n_points == len(cloud)
    assert np.array_equal(rows(tiles.points_in(-500, -500, 500, 500)), rows(cloud))
    assert not [d for d in tmp_path.iterdir() if d.is_dir()]  # no staging folder left


def test_non_finite_points_are_refused(cloud, tmp_path):
    bad = cloud.copy()
    bad[7, 1] = np.nan
    with pytest.raises(DataError, match="non-finite"):
        PointTiles.load_or_build(bad, tmp_path, "bad", tile_m=50.0)


def test_ground_heights_from_tiles_are_the_whole_maps(cloud, tmp_path):
    tiles = PointTiles.load_or_build(cloud, tmp_path, "cloud", tile_m=50.0)
    whole, tiled = GroundGrid(cloud, 1.0), TiledGround(tiles, 1.0)
    rng = np.random.default_rng(0)
    spots = np.r_[rng.uniform([-140, -50], [230, 220], (40, 2)), [[0.2, 0.1], [49.9, 50.1], [-130.0, -40.0]]]
    for x, y in spots:
        a, b = whole.height(x, y), tiled.height(x, y)
        assert (math.isnan(a) and math.isnan(b)) or a == b


@pytest.fixture(scope="module")
def town_map(cache_root):
    seq = short_town(30)
    cfg = Config()
    return seq, cfg, load_or_build_map(seq.map_source, cfg.map, cache_root).value


@pytest.mark.slow
def test_gicp_from_tiles_registers_as_against_the_whole_map(town_map, tmp_path):
    seq, cfg, prior = town_map
    args = dict(
        voxel=cfg.s2m.gicp_voxel,
        max_corr=cfg.s2m.gicp_max_corr,
        target_voxel=max(float(prior.voxel_size), cfg.s2m.gicp_voxel / 2.0),
    )
    whole = GICPRefiner(prior.points, **args)
    local = LocalGICPRefiner(PointTiles.load_or_build(prior.points, tmp_path, "town", 100.0), **args)
    rng = np.random.default_rng(1)
    for k in range(0, 30, 3):
        scan = range_filter(seq.scan(k), cfg.map)
        init = seq.pose(k).copy()
        init[:2, 3] += rng.uniform(-0.5, 0.5, 2)
        a, b = whole.refine(scan, init), local.refine(scan, init)
        # the same map points within the scan's reach: the same registration, to float rounding
        assert np.abs(a.pose[:3, 3] - b.pose[:3, 3]).max() < 1e-3
        assert a.converged == b.converged
    assert local.builds <= 3  # one target per tile under the drive, reused meanwhile
    off_map = np.eye(4)
    off_map[:3, 3] = (5000.0, 5000.0, 0.0)
    assert not local.refine(scan, off_map).converged


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_a_run_on_a_large_tiled_map_keeps_it_on_disk_and_matches_from_the_tiles(cache_root, monkeypatch):
    """The short town stands in for a city (LARGE_MAP_POINTS lowered): the map is memory-mapped,
    its point tiles cut, and the S2M child registers against them — its matches land."""
    from lidarloc.core.localizer import Localizer

    monkeypatch.setattr(mapping, "LARGE_MAP_POINTS", 1000)
    seq = short_town(30)
    cfg = Config()
    cfg.pf.n_particles = 300
    cfg.pf.lookup_tile_m = 100.0
    stages = set()
    with Localizer(seq, cfg, cache_root, progress=lambda stage, f: stages.add(stage)) as loc:
        assert loc.prior_map.on_disk and loc.prior_map.tiles is not None
        assert "point tiles" in stages  # the user sees what the first start does
        assert (loc.map_dir / "tiles-points" / "tiles.json").is_file()
        loc.reset(pose=seq.poses[0])
        loc.run(30)
        landed = [e for e in loc.events if e.kind == "s2m_accepted"]
        errors = [r.error_m for r in loc.records[-10:]]
    assert landed, "no S2M match landed"
    assert max(errors) < 1.0


def test_thinned_tiles_hold_the_whole_maps_voxel_centroids_and_are_cached(cloud, tmp_path):
    """Tiles of 50 m thinned to 0.5 m voxels: the voxels lie inside the tiles, so every tile's
    centroids are the whole map's voxel centroids there; made once, then opened."""
    tiles = PointTiles.load_or_build(cloud, tmp_path / "tiles", "cloud", tile_m=50.0)
    thin = tiles.thinned(0.5)
    assert thin.voxel == 0.5 and tiles.thinned(0.5) is thin
    whole = voxel_centroids(cloud, 0.5)
    assert whole is not None and thin.index["points"] == len(whole) < len(cloud)
    rect = (-20.0, 30.0, 75.0, 120.0)
    assert np.allclose(rows(thin.points_in(*rect)), rows(brute(whole, *rect)), atol=1e-5)
    stamp = (thin.directory / "tiles.json").stat().st_mtime_ns
    again = PointTiles.load_or_build(cloud, tmp_path / "tiles", "cloud", tile_m=50.0).thinned(0.5)
    assert again.directory == thin.directory and (thin.directory / "tiles.json").stat().st_mtime_ns == stamp
    # a damaged thinned tile is thinned again from its parent
    path = thin.directory / "t2_2.points.npy"
    want = np.array(thin.tile(2, 2))
    path.write_bytes(path.read_bytes()[:-12])
    fresh = PointTiles.load_or_build(cloud, tmp_path / "tiles", "cloud", tile_m=50.0).thinned(0.5)
    assert np.allclose(rows(np.array(fresh.tile(2, 2))), rows(want)) and fresh.rebuilt == [(2, 2)]

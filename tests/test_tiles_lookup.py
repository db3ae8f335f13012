"""The tiled lookup table (core/maps/tiled_lookup.py): every cell of the town's map read exactly as
from one table (tile borders included), a window assembled from tiles, tiles mapped in and
dropped, and a damaged or foreign tile cache detected and rebuilt."""

import numpy as np
import pytest
from lidarloc.core.config import load_config
from lidarloc.core.errors import LidarlocError
from lidarloc.core.maps.lookup import LookupTable
from lidarloc.core.maps.tile_cache import INDEX
from lidarloc.core.maps.tiled_lookup import TiledLookup, build_tiles, tile_cells_for
from lidarloc.core.maps.world import open_world
from lidarloc.core.sim.town import TownSequence

RES, D_MAX = 0.25, 5.0


@pytest.fixture(scope="module")
def town(cache_root, tmp_path_factory):
    seq = TownSequence(seed=3, extent_m=150.0, n_scans=40)
    pts = open_world(seq.map_source, load_config(), cache_root, lookup=False, pyramid=False).prior_map.points
    mono = LookupTable.build(pts, RES, D_MAX)
    d = tmp_path_factory.mktemp("tiles")
    return pts, mono, TiledLookup.load_or_build(pts, d, "town-3", RES, D_MAX, 50.0), d


def cell_centres(table, ix0, ix1):
    sx, sy, sz = table.shape
    axes = [
        table.origin[0] + (np.arange(ix0, ix1) + 0.5) * RES,
        table.origin[1] + (np.arange(sy) + 0.5) * RES,
        table.origin[2] + (np.arange(sz) + 0.5) * RES,
    ]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


@pytest.mark.slow
def test_every_cell_reads_as_the_monolithic_table(town):
    pts, mono, tiled, _ = town
    assert (tiled.ntx, tiled.nty) == (4, 4) and tiled.tile_cells == 192  # 48 m tiles: borders inside the map
    assert np.allclose(tiled.origin, mono.origin) and tiled.shape == mono.shape
    for ix in range(0, mono.shape[0], 96):
        q = cell_centres(mono, ix, min(ix + 96, mono.shape[0]))
        assert np.array_equal(tiled.query(q), mono.query(q))
    # a band across each tile border, on the cells' corners too (where rounding would show)
    border = np.arange(1, tiled.ntx) * tiled.tile_m + mono.origin[0]
    rng = np.random.default_rng(0)
    q = np.c_[
        np.repeat(border, 20_000) + rng.uniform(-3, 3, 20_000 * len(border)),
        rng.uniform(pts[:, 1].min(), pts[:, 1].max(), 20_000 * len(border)),
        rng.uniform(pts[:, 2].min() - 1, pts[:, 2].max() + 1, 20_000 * len(border)),
    ]
    q = np.r_[q, np.floor(q / RES) * RES]
    assert np.array_equal(tiled.query(q), mono.query(q))
    assert np.array_equal(tiled.query(q, d_max=2.0), mono.query(q, d_max=2.0))


def test_a_map_bucketed_a_chunk_at_a_time_gives_the_same_tiles(town, tmp_path):
    """A map larger than memory is bucketed into tiles a chunk of points at a time: the tiles are
    the same, file for file, as from one pass (here 7 chunks against the fixture's one), and the
    map is only read (a memory-mapped, read-only map builds)."""
    pts, _, tiled, built = town
    np.save(tmp_path / "map.npy", np.asarray(pts, np.float32))
    mapped = np.load(tmp_path / "map.npy", mmap_mode="r")
    index = build_tiles(mapped, tmp_path / "t", "town-3", RES, D_MAX, tiled.tile_cells, chunk=len(pts) // 7 + 1)
    assert index["origin"] == tiled.index["origin"] and index["shape"] == tiled.index["shape"]
    assert index["tiles"].keys() == tiled.index["tiles"].keys()
    for name in index["tiles"]:
        for part in ("index", "bricks"):
            got = np.load(tmp_path / "t" / f"{name}.{part}.npy")
            assert np.array_equal(got, np.load(built / f"{name}.{part}.npy")), (name, part)
    bad = np.array(pts[:100], np.float32)
    bad[57, 1] = np.nan
    with pytest.raises(LidarlocError, match="NaN or infinite"):
        build_tiles(bad, tmp_path / "u", "bad", RES, D_MAX, tiled.tile_cells, chunk=10)


def test_window_reads_as_the_table_and_tiles_are_dropped(town):
    pts, mono, tiled, _ = town
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    q = np.random.default_rng(1).uniform(lo - 3, hi + 3, (100_000, 3))
    assert np.array_equal(tiled.query(q), mono.query(q))
    win = tiled.window(-20.0, -20.0, 20.0, 20.0)
    inside = (np.abs(q[:, 0]) < 20) & (np.abs(q[:, 1]) < 20)
    assert np.array_equal(win.query(q[inside]), mono.query(q[inside]))
    assert win.nbytes < mono.nbytes
    tiled.drop_except(tiled.tiles_over(-20.0, -20.0, 20.0, 20.0))
    assert set(tiled.open_tiles) == set(tiled.tiles_over(-20.0, -20.0, 20.0, 20.0))
    assert tiled.cache_bytes > 0
    # a window copies its tiles: those mapped in only for the copy are unmapped after it, so a
    # window is not resident twice (tiles mapped before stay: query() keeps them for its reads)
    tiled.drop_except(())
    win = tiled.window(-20.0, -20.0, 20.0, 20.0)
    assert tiled.open_tiles == [] and np.array_equal(win.query(q[inside]), mono.query(q[inside]))
    tiled.query(q[:10])
    before = set(tiled.open_tiles)
    tiled.window(-20.0, -20.0, 20.0, 20.0)
    assert set(tiled.open_tiles) == before


def test_the_follower_keeps_one_window_and_no_tile_mapped(town):
    from lidarloc.core.maps.follow import TileFollower

    pts, mono, tiled, _ = town
    follower = TileFollower(tiled)
    cloud = np.random.default_rng(2).normal(0.0, 3.0, (500, 2))
    a = follower.follow(cloud, 40.0)
    assert follower.follow(cloud + 0.5, 40.0) is a and follower.windows == 1  # the same tiles: reused
    far = cloud + (pts.max(axis=0)[:2] - 30.0)
    b = follower.follow(far, 40.0)
    assert b is not a and follower.windows == 2 and tiled.open_tiles == []
    q = np.c_[far + np.random.default_rng(3).normal(0.0, 10.0, far.shape), np.zeros(len(far))]
    assert np.array_equal(b.query(q), mono.query(q))


def test_tile_sizes_are_whole_build_tiles():
    assert tile_cells_for(100.0, 0.25) == 384 and tile_cells_for(400.0, 0.25) == 1536
    with pytest.raises(LidarlocError, match="tile size"):
        tile_cells_for(0.0, 0.25)


def test_damaged_or_foreign_tiles_are_detected_and_rebuilt(town, caplog):
    pts, mono, _, d = town
    files = sorted(d.glob("t*.bricks.npy"), key=lambda p: p.stat().st_size)
    big, other = files[-1], files[-2]
    big.write_bytes(big.read_bytes()[: big.stat().st_size // 2])  # truncated
    data = bytearray(other.read_bytes())  # same size, another table's content
    data[-100:] = bytes(100)
    other.write_bytes(bytes(data))
    again = TiledLookup.load_or_build(pts, d, "town-3", RES, D_MAX, 50.0)
    q = np.random.default_rng(2).uniform(pts.min(axis=0) - 1, pts.max(axis=0) + 1, (200_000, 3))
    with caplog.at_level("WARNING", logger="lidarloc.cache"):
        assert np.array_equal(again.query(q), mono.query(q))
    names = {f"t{tx}_{ty}" for tx, ty in again.rebuilt}
    assert names == {big.name.split(".")[0], other.name.split(".")[0]}
    told = [r.getMessage() for r in caplog.records if "unreadable cache entry" in r.getMessage()]
    assert len(told) == 2 and all(any(n in m for m in told) for n in names)  # the user is told, per tile
    # rewritten: a third opening rebuilds nothing
    third = TiledLookup.load_or_build(pts, d, "town-3", RES, D_MAX, 50.0)
    assert np.array_equal(third.query(q), mono.query(q)) and third.rebuilt == []
    # without the points a damaged tile is a one-line error naming the file
    big.write_bytes(b"")
    blind = TiledLookup(d, third.index, points=None)
    with pytest.raises(LidarlocError, match="truncated tile file"):
        blind.query(q)
    # an index made for another map: the whole cache is rebuilt
    (d / INDEX).write_text((d / INDEX).read_text().replace("town-3", "town-4"))
    rebuilt = TiledLookup.load_or_build(pts, d, "town-3", RES, D_MAX, 50.0)
    assert np.array_equal(rebuilt.query(q), mono.query(q)) and rebuilt.rebuilt == []

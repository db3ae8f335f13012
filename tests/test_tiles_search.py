"""The tiled BEV pyramid (core/maps/tiled_bev.py) and the exact global search over it
(core/matching/tiled_search.py): the coarse levels are the whole pyramid's, and the search returns
the whole-map branch and bound's pose and score, for small and large tiles."""

import math

import numpy as np
import pytest
from lidarloc.core.config import load_config
from lidarloc.core.errors import DataError
from lidarloc.core.maps.tiled_bev import TiledBEV
from lidarloc.core.maps.world import open_world
from lidarloc.core.matching.m3rsm import match_global
from lidarloc.core.matching.tiled_search import match_global_tiled
from lidarloc.core.sim.town import TownSequence

STEP = 5.0 * math.pi / 180.0


@pytest.fixture(scope="module")
def town(cache_root):
    seq = TownSequence(seed=3, extent_m=150.0, n_scans=40)
    world = open_world(seq.map_source, load_config(), cache_root, lookup=False)
    scans = [seq.scan(i)[:, :2] for i in (0, 39)]
    return world, scans


@pytest.mark.parametrize("tile_m", [16.0, 64.0])
def test_coarse_levels_are_the_pyramids(town, tmp_path, tile_m):
    world, _ = town
    bev = TiledBEV.load_or_build(world.prior_map.points_bev, tmp_path, "town-3", 1.0, tile_m)
    assert bev.shape == world.pyramid.shape and np.array_equal(bev.origin, world.pyramid.origin)
    for i, coarse in enumerate(bev.coarse[:2]):
        assert np.array_equal(coarse, world.pyramid.levels[bev.tile_level + i])
    whole = bev.window(0, 0, *bev.shape)
    assert np.array_equal(whole.levels[0], world.pyramid.levels[0])


@pytest.fixture(scope="module")
def whole_map_answers(town):
    """The whole-map branch and bound's answer for each scan, searched once for every tile size."""
    world, scans = town
    return [match_global(world.pyramid, scan, STEP) for scan in scans]


@pytest.mark.slow
@pytest.mark.parametrize("tile_m", [16.0, 64.0])
def test_tiled_search_finds_the_whole_map_optimum(town, whole_map_answers, tmp_path, tile_m):
    world, scans = town
    bev = TiledBEV.load_or_build(world.prior_map.points_bev, tmp_path, "town-3", 1.0, tile_m)
    assert bev.ntx * bev.nty > 1
    for scan, whole in zip(scans, whole_map_answers):
        for workers in (1, 3):  # one tile at a time, or three at once on threads: the same answer
            tiled = match_global_tiled(bev, scan, STEP, workers=workers)
            assert tiled.score == whole.score
            assert (tiled.x, tiled.y, tiled.yaw) == (whole.x, whole.y, whole.yaw)
            assert tiled.candidates[0, 3] == whole.score


def _look_alike_blocks(seed: int = 5, side: float = 64.0, n: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """A map of n × n copies of one block of walls, every copy but the last missing a random 40 %
    of its points (places that look alike, none quite as well as the right one), and a scan taken
    at the centre of the intact copy (in its own frame, yaw 0)."""
    rng = np.random.default_rng(seed)
    walls = []
    for _ in range(30):
        a = rng.uniform(2.0, side - 2.0, 2)
        b = np.clip(a + rng.uniform(-12.0, 12.0, 2), 1.0, side - 1.0)
        t = np.linspace(0.0, 1.0, max(2, int(np.linalg.norm(b - a) / 0.2)))[:, None]
        walls.append(a + t * (b - a))
    block = np.concatenate(walls)
    copies = []
    for k in range(n * n):
        keep = np.ones(len(block), bool) if k == n * n - 1 else rng.random(len(block)) > 0.4
        copies.append(block[keep] + side * np.array([k // n, k % n]))
    centre = np.array([side / 2 + 0.5, side / 2 + 0.5])  # a lattice position: a cell centre
    scan = block[np.linalg.norm(block - centre, axis=1) < 25.0] - centre
    return np.concatenate(copies), scan


def test_the_tiled_search_expands_the_blocks_the_whole_map_search_does(tmp_path):
    """Tiles that look alike must not each be searched down to their own best pose: the tiled
    search expands the blocks whose bound beats the optimum, as the whole-map search does."""
    xy, scan = _look_alike_blocks()
    bev = TiledBEV.load_or_build(xy, tmp_path, "look-alike", 1.0, 64.0)
    assert bev.ntx * bev.nty == 16
    whole = match_global(bev.window(0, 0, *bev.shape), scan, STEP)
    tiled = match_global_tiled(bev, scan, STEP, workers=1)
    assert (tiled.score, tiled.x, tiled.y, tiled.yaw) == (whole.score, whole.x, whole.y, whole.yaw)
    assert abs(whole.x - 3 * 64 - 32.5) < 1.0 and abs(whole.y - 3 * 64 - 32.5) < 1.0  # the intact copy
    assert tiled.nodes_expanded <= 1.1 * whole.nodes_expanded, (tiled.nodes_expanded, whole.nodes_expanded)


def test_a_damaged_pyramid_tile_is_rebuilt_and_the_user_told(town, tmp_path, caplog):
    world, _ = town
    xy = world.prior_map.points_bev
    bev = TiledBEV.load_or_build(xy, tmp_path, "town-3", 1.0, 32.0)
    victim = max(tmp_path.glob("t*.L0.npy"), key=lambda p: p.stat().st_size)
    victim.write_bytes(victim.read_bytes()[:-8])  # truncated
    other = sorted(tmp_path.glob("t*.L0.npy"), key=lambda p: p.stat().st_size)[-2]
    data = bytearray(other.read_bytes())  # the right size, another table's content
    data[-64:] = bytes(64)
    other.write_bytes(bytes(data))
    again = TiledBEV.load_or_build(xy, tmp_path, "town-3", 1.0, 32.0)
    with caplog.at_level("WARNING", logger="lidarloc.cache"):
        whole = again.window(0, 0, *bev.shape)
    assert np.array_equal(whole.levels[0], world.pyramid.levels[0])  # as built from the map
    assert {f"t{tx}_{ty}" for tx, ty in again.rebuilt} == {victim.name.split(".")[0], other.name.split(".")[0]}
    told = [r.getMessage() for r in caplog.records if "unreadable cache entry" in r.getMessage()]
    assert len(told) == 2 and any(victim.name.split(".")[0] in m for m in told)
    # rewritten: the next opening reads it as it is
    third = TiledBEV.load_or_build(xy, tmp_path, "town-3", 1.0, 32.0)
    assert np.array_equal(third.window(0, 0, *bev.shape).levels[0], world.pyramid.levels[0]) and third.rebuilt == []
    # without the map's points a damaged tile is a one-line error naming the file
    victim.write_bytes(victim.read_bytes()[:-8])
    blind = TiledBEV(tmp_path, third.index, third.coarse)
    with pytest.raises(DataError, match="truncated tile file"):
        blind.window(0, 0, *bev.shape)

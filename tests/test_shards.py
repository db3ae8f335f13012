"""The exact tiled global search spread over shards (core/matching/shards.py, and over Ray in
app/bench/shards.py): the same pose, score and candidates as the one-machine search, whatever the
number of shards or threads, and the one-machine search's own result independent of its threads."""

import math

import numpy as np
import pytest
from lidarloc.core.config import load_config
from lidarloc.core.maps.tiled_bev import TiledBEV
from lidarloc.core.maps.world import open_world
from lidarloc.core.matching.m3rsm import match_global
from lidarloc.core.matching.shards import ShardedTiles, in_process, split_sweep
from lidarloc.core.matching.tiled_search import match_global_tiled
from lidarloc.core.sim.town import TownSequence
from ray_local import ray_local  # noqa: F401  (a fixture: the Ray tests share one local instance)

STEP = 15.0 * math.pi / 180.0


@pytest.fixture(scope="module")
def town(cache_root, tmp_path_factory):
    """The small town's world, its pyramid in 32 m tiles (30 tiles) and two of its scans."""
    seq = TownSequence(seed=3, extent_m=150.0, n_scans=40)
    world = open_world(seq.map_source, load_config(), cache_root, lookup=False)
    bev = TiledBEV.load_or_build(world.prior_map.points_bev, tmp_path_factory.mktemp("bev"), "town-3", 1.0, 32.0)
    scans = [seq.scan(i)[:, :2] for i in (0, 39)]
    return world, bev, scans


def answer(r):
    return (r.score, r.x, r.y, r.yaw, r.nodes_expanded, r.nodes_per_level, r.candidates.tobytes())


def test_sharded_search_is_the_one_machine_search(town):
    world, bev, scans = town
    assert bev.ntx * bev.nty >= 20
    for j, scan in enumerate(scans):
        single = match_global_tiled(bev, scan, STEP, workers=1)
        assert math.isfinite(single.score) and len(single.candidates) > 1
        if j == 0:  # the whole-map search's optimum (tests/test_tiles_search.py compares more)
            whole = match_global(world.pyramid, scan, STEP)
            assert (single.score, single.x, single.y, single.yaw) == (whole.score, whole.x, whole.y, whole.yaw)
        assert answer(match_global_tiled(bev, scan, STEP, workers=2)) == answer(single)
        for n_shards, threads in ((2, 2), (5, 1)):
            shards = in_process(bev, n_shards, threads)
            assert answer(match_global_tiled(bev, scan, STEP, shards=shards)) == answer(single), n_shards
            # every shard searched some of the tiles, each tile on one shard
            assert sorted(set(shards.owner.values())) == list(range(n_shards))


def test_equal_scores_are_settled_as_on_one_machine(tmp_path):
    """A map of four identical blocks: the best pose scores the same in each, and the answer is
    the one the one-machine search gives, however the tiles are spread."""
    rng = np.random.default_rng(2)
    block = rng.uniform(2.0, 30.0, (400, 2))
    xy = np.concatenate([block + 32.0 * np.array([i, j]) for i in range(2) for j in range(2)])
    bev = TiledBEV.load_or_build(xy, tmp_path, "four-blocks", 1.0, 16.0)
    scan = block[np.linalg.norm(block - 16.5, axis=1) < 12.0] - 16.5
    single = match_global_tiled(bev, scan, STEP, workers=1)
    ties = single.candidates[single.candidates[:, 3] == single.score]
    assert len(ties) >= 2  # the same place in more than one block: a tie the search must settle
    assert tuple(single.candidates[0]) == (single.x, single.y, single.yaw, single.score)  # the optimum first
    for n_shards, threads in ((2, 2), (3, 1), (4, 2)):
        assert answer(match_global_tiled(bev, scan, STEP, shards=in_process(bev, n_shards, threads))) == answer(single)
    assert answer(match_global_tiled(bev, scan, STEP, workers=2)) == answer(single)


def test_a_sweep_is_split_by_work_and_a_tile_stays_on_its_shard():
    owner, work = {}, {}
    assert split_sweep([4, 1, 7], owner, work, 2) == [[4, 7], [1]]
    work.update({4: 100, 1: 10, 7: 5})
    # 4, 1 and 7 stay where they were (105 nodes on shard 0, 10 on shard 1); each new tile,
    # counted as the busiest one (100), goes to the shard with less work so far
    assert split_sweep([4, 1, 7, 2, 3], owner, work, 2) == [[4, 7, 3], [1, 2]]
    assert owner == {4: 0, 1: 1, 7: 0, 2: 1, 3: 0}
    with pytest.raises(ValueError):
        ShardedTiles(0, lambda calls: [])


@pytest.mark.slow  # Ray's start and its workers' imports: 10–25 s on 2 cores
def test_ray_shards_give_the_one_machine_answer(town, ray_local):  # noqa: F811
    from lidarloc.app.bench.shards import RayShards

    _, bev, scans = town
    shards = RayShards(bev, 2)
    try:
        single = match_global_tiled(bev, scans[0], STEP, workers=1)
        assert answer(match_global_tiled(bev, scans[0], STEP, shards=shards.tiles)) == answer(single)
        assert sorted(set(shards.tiles.owner.values())) == [0, 1]  # both workers searched tiles
    finally:
        shards.close()

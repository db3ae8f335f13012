"""A run on a tiled lookup table (pf.lookup_tile_m, core/maps/follow.py): the table follows the
particles (tiles mapped in around them, across tile borders), and the run is the run on one table,
with tiles of 100 m and of 400 m (replay, seed fixed); the first window (the whole map) is let go
once the particles gather."""

import gc
import weakref

import numpy as np
import pytest
from helpers import short_town
from lidarloc.core.config import Config
from lidarloc.core.localizer import Localizer

N_SCANS = 25
RANGE_M = 30.0  # scans cropped so that the tiles under the particles are fewer than the small map's


class Cropped:
    """The short town with its scans cropped to RANGE_M (everything else the town's)."""

    def __init__(self, seq):
        self._seq = seq

    def __getattr__(self, name):
        return getattr(self._seq, name)

    def __len__(self):
        return len(self._seq)

    def scan(self, k):
        s = self._seq.scan(k)
        return s[np.linalg.norm(s[:, :3], axis=1) < RANGE_M]


@pytest.fixture(scope="module")
def town():
    return Cropped(short_town(N_SCANS))


def trajectory(seq, cache_root, tile_m: float):
    cfg = Config()
    cfg.pf.n_particles = 300
    cfg.pf.lookup_tile_m = tile_m
    with Localizer(seq, cfg, cache_root) as loc:
        first = weakref.ref(loc.lookup)  # a tiled run's first window: the whole map
        loc.reset(pose=seq.poses[0])
        loc.run(N_SCANS)
        tiles = loc.world.tiles
        gc.collect()
        moved = (
            (tiles.windows, len(tiles.tiles), tiles.tiled.ntx * tiles.tiled.nty, first() is None)
            if tiles is not None
            else None
        )
        return loc.pf.states.copy(), [(r.x, r.y, r.yaw, r.n_eff) for r in loc.records], moved


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_a_run_across_tiles_is_the_run_on_one_table(town, cache_root):
    states, records, _ = trajectory(town, cache_root, 0.0)
    for tile_m in (100.0, 400.0):
        tiled_states, tiled_records, (windows, under, total, first_let_go) = trajectory(town, cache_root, tile_m)
        assert np.array_equal(tiled_states, states)
        assert tiled_records == records
        if tile_m == 100.0:  # the whole map at the start, then only the tiles around the particles
            assert windows >= 2 and 1 < under < total
            assert first_let_go  # nothing keeps the first window (the whole map) alive

"""The BEV pyramid (core/maps/bev.py): stride-2 max pools down to a few cells, the cell values, and
its cache (save/load, atomic writes, a corrupt entry rebuilt)."""

import numpy as np
import pytest
from lidarloc.core.config import S2MConfig
from lidarloc.core.errors import LidarlocError
from lidarloc.core.maps.bev import BEVPyramid, load_or_build_pyramid, max_pool2, pyramid_cache_name
from lidarloc.core.maps.mapping import PriorMap


def test_pyramid_levels_are_stride2_max_pools_down_to_a_few_cells():
    rng = np.random.default_rng(3)
    xy = rng.uniform(-37.3, 61.9, (4000, 2))
    pyr = BEVPyramid.build(xy, 1.0, cell_value="count")
    L0 = pyr.levels[0]
    assert L0.sum() == len(xy)  # counts: every point in exactly one cell
    assert np.allclose(pyr.origin / pyr.resolution, np.round(pyr.origin / pyr.resolution))
    for lo, hi in zip(pyr.levels, pyr.levels[1:]):
        assert np.array_equal(hi, max_pool2(lo))
        nx, ny = lo.shape
        assert hi.shape == ((nx + 1) // 2, (ny + 1) // 2)
    assert pyr.levels[-1].size <= 9 and pyr.levels[-2].size > 9
    # each level-l cell is the max of its 2^l × 2^l L0 block
    l = 3
    for ix, iy in [(0, 0), (5, 7), (pyr.levels[l].shape[0] - 1, pyr.levels[l].shape[1] - 1)]:
        block = L0[ix * 8 : (ix + 1) * 8, iy * 8 : (iy + 1) * 8]
        assert pyr.levels[l][ix, iy] == block.max()


def test_cell_values():
    xy = np.array([[0.5, 0.5]] * 20 + [[3.5, 0.5]])
    for value, expect in [("count", 20), ("binary", 1), ("sat8", 8), ("log", np.log1p(20))]:
        pyr = BEVPyramid.build(xy, 1.0, cell_value=value)
        assert pyr.levels[0].max() == pytest.approx(expect)
    assert BEVPyramid.build(xy, 1.0, binary=True, cell_value="count").cell_value == "binary"
    with pytest.raises(LidarlocError):
        BEVPyramid.build(xy, 1.0, cell_value="sat-1")
    with pytest.raises(LidarlocError):
        BEVPyramid.build(np.zeros((0, 2)), 1.0)


def test_pyramid_save_load_and_cache(tmp_path):
    rng = np.random.default_rng(0)
    pts = np.c_[rng.uniform(0, 50, (500, 2)), rng.uniform(0, 5, 500)].astype(np.float32)
    prior = PriorMap(points=pts, points_bev=pts, voxel_size=0.2)
    cfg = S2MConfig()
    built, _, cached = load_or_build_pyramid(prior, tmp_path, cfg)
    assert not cached
    cache = tmp_path / pyramid_cache_name(cfg)
    assert (cache / "pyramid.json").is_file()
    assert not list(tmp_path.glob("*.tmp-*"))  # atomic: no temporary left behind
    loaded, directory, cached = load_or_build_pyramid(prior, tmp_path, cfg)
    assert cached and directory == cache
    assert loaded.resolution == built.resolution and np.array_equal(loaded.origin, built.origin)
    assert all(np.array_equal(a, b) for a, b in zip(loaded.levels, built.levels))
    (cache / "levels.npz").write_bytes(b"corrupt")  # an unreadable entry is rebuilt
    assert not load_or_build_pyramid(prior, tmp_path, cfg).cached
    binary = load_or_build_pyramid(prior, tmp_path, S2MConfig(binary_cells=True)).value
    assert binary.cell_value == "binary" and binary.levels[0].max() == 1

"""M3RSM branch and bound (core/matching/m3rsm.py): admissible bounds, exactness against brute force,
min-score pruning, the angle and translation lattices, the candidates and per-level node counts
kept for inspection (and that keeping them changes no result), recovery of synthetic 2D scans in
local and global mode."""

import math

import numpy as np
import pytest
from helpers import random_segments
from lidarloc.core.errors import LidarlocError
from lidarloc.core.maps import bev
from lidarloc.core.maps.bev import BEVPyramid, cell_dtype
from lidarloc.core.matching import bnb_kernels, m3rsm

DEG = math.pi / 180


def to_sensor(xy_world, x, y, yaw):
    c, s = math.cos(yaw), math.sin(yaw)
    d = xy_world - [x, y]
    return d @ np.array([[c, -s], [s, c]])  # R(yaw)ᵀ applied to each row


# ------------------------------------------------------------------------ admissible bounds
def test_bounds_are_admissible_for_every_block():
    """Level-l bound of a block ≥ the L0 score of every translation in it, including blocks that
    hang over the grid's edges (negative cells) — both bound kinds.

    Admissibility is a property of the search's inner kernels (``_Prepared``, ``angle_cells``,
    ``bound``, …), so this test calls them directly: the public ``match`` shows it only through
    its result (the exhaustive-optimum test below), and public names for numba kernels that
    nothing else should call would be artificial."""
    rng = np.random.default_rng(7)
    pyr = BEVPyramid.build(random_segments(rng, 12, 30, 12), 1.0, cell_value="sat4")
    prep = m3rsm._Prepared(pyr, dense_upto=99, strided_from=1)  # both bound kinds at every level
    B = m3rsm.scan_cells(rng.uniform(-9, 9, (60, 2)), 1.0)
    angles = np.array([0.3, -2.0])
    cx, cy = m3rsm.angle_cells(pyr, B, angles, (3.7, 21.2))
    top = prep.n_levels - 1
    ex, ey, ec, ew, eoff = bnb_kernels.level_entries(cx, cy, 1, top)
    checked = 0
    for l in range(1, top + 1):
        size = 1 << l
        for _ in range(15):
            r = int(rng.integers(len(angles)))
            kx = int(rng.integers(-40, 40)) // size * size
            ky = int(rng.integers(-40, 40)) // size * size
            exact = max(
                bnb_kernels.score_l0(prep.L0, cx[r], cy[r], kx + i, ky + j) for i in range(size) for j in range(size)
            )
            strided = bnb_kernels.bound(
                prep.G, prep.gnx, prep.gny, prep.goff, l, ex, ey, ec, ew, eoff[l, r], eoff[l, r + 1], kx >> l, ky >> l
            )
            dense = bnb_kernels.bound_dense(prep.S, prep.snx, prep.sny, prep.soff, l, cx[r], cy[r], kx, ky)
            assert strided >= exact and dense >= exact
            assert dense <= strided  # the stride-1 pooling is the tighter of the two
            checked += exact > 0
    assert checked > 20


# ------------------------------------------------------------------- branch and bound = brute force
@pytest.mark.parametrize("dense_upto", [0, 2, 99])
def test_branch_and_bound_finds_the_exhaustive_optimum(monkeypatch, dense_upto):
    monkeypatch.setattr(m3rsm, "DENSE_UPTO", dense_upto)
    same_pose = 0
    for seed in range(24):
        rng = np.random.default_rng(1000 * dense_upto + seed)
        xy = random_segments(rng, int(rng.integers(3, 12)), 40, 15) + rng.normal(0, 0.2, (1, 2))
        pyr = BEVPyramid.build(
            xy, float(rng.choice([0.5, 1.0])), cell_value=str(rng.choice(["sat4", "binary", "count"]))
        )
        scan = rng.uniform(-12, 12, (int(rng.integers(5, 60)), 2))
        step = float(rng.choice([3.0, 10.0, 30.0])) * DEG
        if seed % 2:
            args = (
                pyr,
                scan,
                rng.uniform(0, 40, 2),
                tuple(rng.uniform(1, 12, 2)),
                rng.uniform(-3, 3),
                float(rng.choice([0.5, math.pi])),
                step,
            )
            fast, slow = m3rsm.match(*args), m3rsm.exhaustive_match(*args)
        else:
            fast, slow = m3rsm.match_global(pyr, scan, step), m3rsm.exhaustive_match(pyr, scan, angle_step=step)
        assert fast.score == slow.score, seed
        assert fast.nodes_expanded <= slow.nodes_expanded
        # equal poses unless several poses tie for the optimum; a tie must really score the same
        if (fast.x, fast.y, fast.yaw) == (slow.x, slow.y, slow.yaw):
            same_pose += 1
        else:
            assert m3rsm.score_pose(pyr, scan, fast.x, fast.y, fast.yaw) == pytest.approx(slow.score)
    assert same_pose >= 12


def test_a_heap_block_takes_21_bytes_and_keeps_what_a_search_puts_in_it():
    """A city's global search holds tens of millions of blocks: each in 21 bytes (bound float64,
    level int8, angle int32, lattice corner int32), popped best first (ties: deeper level first)
    with its level, angle and corner as pushed, negative corners (a local search's region) and a
    grid of a million cells a side included."""
    rng = np.random.default_rng(3)
    pyr = BEVPyramid.build(random_segments(rng, 4, 20, 8), 1.0)
    prep = m3rsm._Prepared(pyr, m3rsm.DENSE_UPTO)
    cx, cy = m3rsm.angle_cells(pyr, m3rsm.scan_cells(rng.uniform(-5, 5, (20, 2)), 1.0), np.zeros(1), (0.5, 0.5))
    kernel_args = (prep.L0, prep.G, prep.gnx, prep.gny, prep.goff, prep.S, prep.snx, prep.sny, prep.soff,
                   m3rsm.DENSE_UPTO, cx, cy, *bnb_kernels.level_entries(cx, cy, m3rsm.DENSE_UPTO + 1, 0))  # fmt: skip
    # the heap a search starts with: level 0 only scores leaves, so nothing is pushed on it
    *heap, n = bnb_kernels._bnb_roots(*kernel_args, 0, 0, 0, 0, 0, -1.0, 0)[4:10]
    assert n == 0
    assert sum(a.dtype.itemsize for a in heap) == 21
    blocks = [
        (float(rng.integers(0, 50)), int(rng.integers(0, 40)), int(rng.integers(0, 3600)),
         int(rng.integers(-(10**6), 10**6)), int(rng.integers(-(10**6), 10**6)))
        for _ in range(3000)
    ]  # fmt: skip
    for s, l, r, x, y in blocks:
        *heap, n = bnb_kernels._heap_push(*heap, n, s, l, r, x, y)
    popped = []
    while n > 0:
        hs, hl, hr, hx, hy = heap
        popped.append((float(hs[0]), int(hl[0]), int(hr[0]), int(hx[0]), int(hy[0])))
        n = bnb_kernels._heap_pop(*heap, n)
    assert sorted(popped) == sorted(blocks)
    keys = [(-s, l) for s, l, *_ in popped]
    assert keys == sorted(keys)


@pytest.mark.parametrize("cell_value", ["sat8", "binary", "count", "log"])
def test_grids_in_the_narrowest_exact_type_change_no_result(monkeypatch, cell_value):
    """Integer cells (saturated counts, binary) are searched from one-byte grids; the search is
    the same, bit for bit, as from float32 grids: scores, poses, nodes, runners-up."""
    rng = np.random.default_rng(21)
    pyr = BEVPyramid.build(random_segments(rng, 14, 60, 20), 1.0, cell_value=cell_value)
    narrow = m3rsm._Prepared(pyr, dense_upto=3)
    want = {"sat8": np.uint8, "binary": np.uint8, "log": np.float32}.get(cell_value)
    if want is not None:
        assert narrow.dtype is want and narrow.S.dtype == want and narrow.G.dtype == want
        assert all(lv.dtype == want for lv in pyr.levels) and narrow.L0 is pyr.levels[0]
    else:  # raw counts: uint8 or uint16 by the map's densest cell
        assert narrow.dtype in (np.uint8, np.uint16)
        assert int(pyr.levels[0].max()) <= np.iinfo(narrow.dtype).max
    scans = [rng.uniform(-12, 12, (int(rng.integers(20, 80)), 2)) for _ in range(4)]

    def searches(pyramid):
        out = []
        for scan in scans:
            out.append(m3rsm.match(pyramid, scan, (30.0, 30.0), (12.0, 12.0), 0.5, math.pi, 5 * DEG))
            out.append(m3rsm.match_global(pyramid, scan, 10 * DEG))
        return out

    compact = searches(pyr)
    monkeypatch.setattr(bev, "cell_dtype", lambda level0: np.float32)  # the same cells in float32
    float32 = BEVPyramid(pyr.resolution, pyr.origin, [lv.astype(np.float32) for lv in pyr.levels], pyr.cell_value)
    wide = searches(float32)
    assert m3rsm._prepared(float32, m3rsm.DENSE_UPTO).S.dtype == np.float32
    for a, b in zip(compact, wide):
        assert (a.x, a.y, a.yaw, a.score, a.nodes_expanded) == (b.x, b.y, b.yaw, b.score, b.nodes_expanded)
        assert a.nodes_per_level == b.nodes_per_level and np.array_equal(a.candidates, b.candidates)


def test_cell_dtype_is_the_narrowest_exact_one(tmp_path):
    assert cell_dtype(np.array([[0.0, 8.0]], np.float32)) is np.uint8
    assert cell_dtype(np.array([[0.0, 300.0]], np.float32)) is np.uint16
    assert cell_dtype(np.array([[0.0, 70000.0]], np.float32)) is np.float32
    assert cell_dtype(np.array([[0.0, 0.5]], np.float32)) is np.float32
    assert cell_dtype(np.array([[-1.0, 2.0]], np.float32)) is np.float32
    assert cell_dtype(np.array([[0, 7]], np.int64)) is np.uint8
    # float32 levels (a cache written in float32) are narrowed; a saved pyramid loads the same cells
    rng = np.random.default_rng(3)
    pyr = BEVPyramid.build(random_segments(rng, 8, 30, 10), 1.0, cell_value="sat8")
    wide = BEVPyramid(pyr.resolution, pyr.origin, [lv.astype(np.float32) for lv in pyr.levels], pyr.cell_value)
    assert wide.levels[0].dtype == np.uint8
    pyr.save(tmp_path / "p")
    back = BEVPyramid.load(tmp_path / "p")
    assert [lv.dtype for lv in back.levels] == [np.uint8] * pyr.n_levels
    assert all(np.array_equal(a, b) for a, b in zip(back.levels, pyr.levels))


def test_min_score_prunes_and_reports_nothing_when_unbeaten():
    rng = np.random.default_rng(5)
    pyr = BEVPyramid.build(random_segments(rng, 10, 40, 15), 1.0)
    scan = rng.uniform(-10, 10, (40, 2))
    best = m3rsm.match(pyr, scan, (20, 20), (8, 8), 0.0, math.pi, 10 * DEG)
    none = m3rsm.match(pyr, scan, (20, 20), (8, 8), 0.0, math.pi, 10 * DEG, min_score=best.score)
    assert math.isnan(none.x) and none.score == best.score
    again = m3rsm.match(pyr, scan, (20, 20), (8, 8), 0.0, math.pi, 10 * DEG, min_score=best.score - 0.5)
    assert again.score == best.score and (again.x, again.y, again.yaw) == (best.x, best.y, best.yaw)


def test_local_lattices_translations_from_the_start_and_world_fixed_yaws():
    rng = np.random.default_rng(11)
    pyr = BEVPyramid.build(random_segments(rng, 10, 40, 15), 1.0)
    scan = rng.uniform(-10, 10, (50, 2))
    step = 2.5 * DEG
    lattice = m3rsm.angle_lattice(step)
    assert len(lattice) == 144 and lattice[0] == -math.pi
    # a start whose yaw is on the lattice is itself a candidate: the match scores at least as much
    start = (17.37, 22.81, float(lattice[100]))
    res = m3rsm.match(pyr, scan, start[:2], (5, 5), start[2], 0.3, step)
    assert res.score >= m3rsm.score_pose(pyr, scan, *start)
    # a region below one cell leaves the start position; a zero window the nearest lattice yaw
    only = m3rsm.match(pyr, scan, start[:2], (0.4, 0.4), start[2] + 0.4 * step, 0.0, step)
    assert (only.x, only.y, only.yaw) == pytest.approx(start)
    assert only.score == m3rsm.score_pose(pyr, scan, *start)
    # yaws are the lattice's, whatever the centre: ±0.3 rad holds ⌊0.3 / d_θ⌋ · 2 (+1) of them
    off_lattice = m3rsm.match(pyr, scan, start[:2], (3, 3), start[2] + 0.37 * step, 0.3, step)
    assert off_lattice.n_angles in (13, 14)
    assert np.min(np.abs(lattice - off_lattice.yaw)) < 1e-9


# ------------------------------------------------------------------- candidates kept for inspection
def _random_searches(seed):
    """One random map and scan; a local search (with and without a score to beat), a global one,
    and the exhaustive search over the same space as each."""
    rng = np.random.default_rng(seed)
    pyr = BEVPyramid.build(
        random_segments(rng, int(rng.integers(3, 12)), 40, 15),
        float(rng.choice([0.5, 1.0])),
        cell_value=str(rng.choice(["sat4", "binary", "count"])),
    )
    scan = rng.uniform(-12, 12, (int(rng.integers(5, 60)), 2))
    step = float(rng.choice([5.0, 10.0, 30.0])) * DEG
    local = (
        pyr,
        scan,
        rng.uniform(0, 40, 2),
        tuple(rng.uniform(1, 12, 2)),
        rng.uniform(-3, 3),
        float(rng.choice([0.5, math.pi])),
        step,
    )
    return pyr, scan, step, local


@pytest.mark.parametrize("seed", range(12))
def test_candidates_are_the_best_leaves_best_first_and_the_first_is_the_result(seed):
    pyr, scan, step, local = _random_searches(seed)
    found = m3rsm.match(*local)
    searches = [
        (found, m3rsm.exhaustive_match(*local)),
        (m3rsm.match_global(pyr, scan, step), m3rsm.exhaustive_match(pyr, scan, angle_step=step)),
    ]
    for bnb, brute in searches:
        for res in (bnb, brute):
            c = res.candidates
            assert c.shape[1] == 4 and 1 <= len(c) <= m3rsm.N_CANDIDATES
            assert np.all(np.diff(c[:, 3]) <= 0)  # best first
            assert tuple(c[0]) == (res.x, res.y, res.yaw, res.score)  # the result itself, exactly
            assert sum(res.nodes_per_level) == res.nodes_expanded
            assert len({tuple(row[:3]) for row in c}) == len(c)  # each pose once
        # the exhaustive search's are the search space's best; branch and bound's are among what it scored
        assert len(brute.candidates) == min(m3rsm.N_CANDIDATES, brute.nodes_expanded)
        assert np.all(bnb.candidates[:, 3] <= brute.candidates[: len(bnb.candidates), 3])
        # branch and bound never splits a leaf: level 0 expands nothing, the top level at least one node
        assert bnb.nodes_per_level[0] == 0 and len(bnb.nodes_per_level) >= 1
    # a score to beat that nothing beats: no result, but what the search scored is still there
    unbeaten = m3rsm.match(*local, min_score=found.score)
    assert math.isnan(unbeaten.x)
    assert np.all(unbeaten.candidates[:, 3] <= found.score)
    assert sum(unbeaten.nodes_per_level) == unbeaten.nodes_expanded


@pytest.mark.parametrize("seed", range(12))
def test_keeping_candidates_changes_no_result(seed):
    """The same search keeping none and keeping the default number: same pose, score and work, bit
    for bit (the leaves are only copied aside)."""
    pyr, scan, step, local = _random_searches(100 + seed)
    beat = m3rsm.match(*local).score - 1.0
    pairs = [
        (m3rsm.match(*local, keep_candidates=0), m3rsm.match(*local)),
        (m3rsm.match(*local, min_score=beat, keep_candidates=0), m3rsm.match(*local, min_score=beat)),
        (m3rsm.match_global(pyr, scan, step, keep_candidates=0), m3rsm.match_global(pyr, scan, step)),
        (m3rsm.exhaustive_match(*local, keep_candidates=0), m3rsm.exhaustive_match(*local)),
    ]
    for without, kept in pairs:
        assert len(without.candidates) == 0 and len(kept.candidates) > 0
        for f in ("x", "y", "yaw", "score", "nodes_expanded", "nodes_per_level", "n_points", "region", "n_angles"):
            a, b = getattr(without, f), getattr(kept, f)
            assert a == b or (isinstance(a, float) and math.isnan(a) and math.isnan(b)), f
    with pytest.raises(LidarlocError):
        m3rsm.match(*local, keep_candidates=-1)


# --------------------------------------------------------------------------- recovery
def _town_2d(seed):
    rng = np.random.default_rng(seed)
    walls = random_segments(rng, 60, 160, 25, step=0.1)
    return walls + rng.normal(0, 0.05, walls.shape)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_scan_cut_from_the_map_is_recovered_locally_and_globally(seed):
    world = _town_2d(seed)
    pyr = BEVPyramid.build(world, 1.0)
    rng = np.random.default_rng(100 + seed)
    d_m, d_t = 1.0, 2.5 * DEG
    # The true yaw is on the angle lattice (θ_r = −π + r·d_θ, and the local search's lattice is
    # anchored a whole number of steps away): off-lattice yaw errors make the best translation
    # compensate a rotation about the scan's centroid, which may exceed d_m (the real-scan test
    # covers arbitrary poses, with GICP). The translation is arbitrary.
    x, y, yaw = rng.uniform(50, 110), rng.uniform(50, 110), -math.pi + int(rng.integers(144)) * d_t
    near = world[np.hypot(world[:, 0] - x, world[:, 1] - y) < 40]
    scan = to_sensor(near, x, y, yaw)

    local = m3rsm.match(
        pyr,
        scan,
        (x + rng.uniform(-20, 20), y + rng.uniform(-20, 20)),
        (25, 25),
        yaw + int(rng.integers(-40, 40)) * d_t,
        math.pi,
        d_t,
    )
    glob = m3rsm.match_global(pyr, scan, d_t)
    for res in (local, glob):
        assert math.hypot(res.x - x, res.y - y) <= d_m, res
        assert abs((res.yaw - yaw + math.pi) % (2 * math.pi) - math.pi) <= d_t, res
        assert res.score >= m3rsm.score_pose(pyr, scan, res.x, res.y, res.yaw) - 1e-9


def test_scan_cells_downsamples_to_unique_cells():
    pts = np.array([[0.1, 0.1], [0.3, 0.5], [1.5, 0.2], [np.nan, 1.0]])
    cells = m3rsm.scan_cells(pts, 1.0)
    assert cells.shape == (2, 2)
    assert np.allclose(cells[0], [0.2, 0.3])
    with pytest.raises(LidarlocError):
        m3rsm.scan_cells(np.zeros((3, 1)), 1.0)


def test_scan_cells_are_the_row_sorted_centroids_bit_for_bit():
    """The cells in (ix, iy) order and their centroids summed in the scan's order, exactly as the
    row sort (np.unique over rows, np.add.at) made them: a scan in its own frame (counted over its
    box) and one far out in world coordinates (sorted)."""

    def by_rows(xy, d):
        idx = np.floor(xy / d).astype(np.int64)
        _, inverse, counts = np.unique(idx, axis=0, return_inverse=True, return_counts=True)
        sums = np.zeros((len(counts), 2))
        np.add.at(sums, inverse.ravel(), xy)
        return sums / counts[:, None]

    rng = np.random.default_rng(5)
    for centre, spread in [(0.0, 30.0), (-12.0, 0.7), (4000.0, 3000.0)]:
        xy = rng.normal(centre, spread, (5000, 2))
        for d in (0.25, 1.0):
            assert np.array_equal(m3rsm.scan_cells(xy, d), by_rows(xy, d))

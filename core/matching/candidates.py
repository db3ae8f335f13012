"""Global localization by candidates: the place index's look-up names a few places, the exact
M3RSM search verifies each in a small window, and GICP verifies the best in 3D.

Why: the exact whole-map search's cost grows with the map (~3.7 CPU-s per km²: a minute a match
on a 16 km² city), and it returns a look-alike street as confidently as the truth. Here:

1. **Look-up** (:func:`look_up`): the scan's first-hit descriptor
   (:mod:`lidarloc.core.maps.places`) against every place's, coarse sectors first, under every
   shift; the best places (at most one within ``separation`` of another) with the yaw their best
   shift says.
2. **Exact verification** (:func:`verify`): M3RSM's branch and bound over ± ``half`` metres and
   ± ``yaw_window`` around each place: the same lattice, the same scores as the whole-map search
   (on a city held in tiles, in a window of the tiles wide enough for every scan point).
3. **An honest answer** (:func:`distinct`, used by the scan-to-map matcher): verified places
   farther apart than ``distinct_m`` are distinct answers. Where a second distinct place scores at
   least ``ambiguity_ratio`` of the best and also passes GICP, the answer is "ambiguous: N places"
   and the filter is not moved; a wrong place is not returned as a confident answer because it
   happened to score a little higher.

The exact whole-map search stays as the fallback when the look-up finds nothing to compare
(too few rays hit) or no verified place passes GICP, and as a setting (``s2m.global_search``).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numba as nb
import numpy as np

from ..maps.bev import BEVPyramid
from ..maps.places import PlaceIndex, coarse_of, describe_scan
from . import m3rsm

#: A sector's difference counts at most this much (m): a van parked in front of the scan, or a
#: wall the survey did not reach, costs one sector, not the place.
SECTOR_CLIP_M = 5.0
#: Places kept from the coarse pass for the fine pass. On the town the true place ranked at most
#: 133rd of 9,074 in the coarse pass (60 scans); on a city the fine pass still costs only ~10 ms.
COARSE_KEEP = 2000


@dataclass(frozen=True)
class Place:
    """A place the look-up names: where, the yaw its best shift says, and how far its descriptor
    is from the scan's (mean clipped difference per sector, m; lower is closer)."""

    x: float
    y: float
    yaw: float
    distance: float


@dataclass(frozen=True)
class LookUp:
    places: list[Place]
    hits: int  # rays of the scan's descriptor that met a cell
    ms: float


@nb.njit(parallel=True, nogil=True, cache=True)
def _best_shifts(P, Q, clip, out_d, out_s):
    """For each row of ``P`` (n, m) the smallest Σ_l min(|P[i, l] − Q[s, l]|, clip) over the
    shifts s, and that s. ``Q[s]`` is the scan's descriptor shifted by s (:func:`_shifted`): every
    inner loop then reads two rows in step, which the compiler turns into vector instructions
    (3–4 times faster than indexing the scan's descriptor modulo m)."""
    n, m = P.shape
    for i in nb.prange(n):
        best = 1 << 30
        best_s = 0
        row = P[i]
        for s in range(m):
            q = Q[s]
            acc = np.int32(0)
            for el in range(m):
                d = np.int16(row[el]) - q[el]
                d = d if d >= 0 else -d
                acc += d if d < clip else clip
            if acc < best:
                best = acc
                best_s = s
        out_d[i] = best
        out_s[i] = best_s


def _shifted(q: np.ndarray) -> np.ndarray:
    """(m, m) int16: row s is ``q`` seen with its sector j at sector j + s, Q[s, l] = q[(l − s) mod m]."""
    m = len(q)
    cols = (np.arange(m)[None, :] - np.arange(m)[:, None]) % m
    return np.ascontiguousarray(np.asarray(q, np.int16)[cols])


def _shifts(P: np.ndarray, q: np.ndarray, clip: int) -> tuple[np.ndarray, np.ndarray]:
    """Each row's best shift against the scan's descriptor ``q`` and its clipped distance."""
    d = np.empty(len(P), np.int64)
    s = np.empty(len(P), np.int64)
    if len(P):
        _best_shifts(np.ascontiguousarray(P), _shifted(q), np.int16(clip), d, s)
    return d, s


@nb.njit(cache=True, nogil=True)
def _apart(xy, separation, n):
    """Indices of the first ``n`` rows of ``xy`` (best first) farther than ``separation`` from every
    row taken before them."""
    chosen = np.empty(n, np.int64)
    k = 0
    s2 = separation * separation
    for i in range(xy.shape[0]):
        ok = True
        for j in range(k):
            dx = xy[i, 0] - xy[chosen[j], 0]
            dy = xy[i, 1] - xy[chosen[j], 1]
            if dx * dx + dy * dy <= s2:
                ok = False
                break
        if ok:
            chosen[k] = i
            k += 1
            if k == n:
                break
    return chosen[:k]


@nb.njit(parallel=True, nogil=True, cache=True)
def _bev_scores(L0, ox, oy, inv_d, bx, by, px, py, pyaw, out):
    """The BEV score (Σ L0 under the scan's cells ``bx``, ``by``) of each pose (px, py, pyaw)."""
    nx, ny = L0.shape
    for i in nb.prange(px.shape[0]):
        c, s = math.cos(pyaw[i]), math.sin(pyaw[i])
        acc = 0.0
        for j in range(bx.shape[0]):
            ix = int(math.floor((px[i] + c * bx[j] - s * by[j] - ox) * inv_d))
            iy = int(math.floor((py[i] + s * bx[j] + c * by[j] - oy) * inv_d))
            if 0 <= ix < nx and 0 <= iy < ny:
                acc += L0[ix, iy]
        out[i] = acc


#: Distinct places the descriptors hand to the BEV score's re-ranking: on the 16 km² city, where
#: suburbs repeat, the true place ranked 18th–292nd by descriptor for 10 of 18 scans whose first
#: 16 missed it.
RERANK_PLACES = 300
#: Cells either side of a place its re-ranking scores: the look-up keeps one place within
#: ``separation`` (10 m) of another, so the truth can lie metres from the place that stands for
#: it. On the 16 km² city ±1 cell left the truth 20th of a straight street's places; ±3 put it
#: first (scans 2367, 2271 and 2383 of the city's drive).
RERANK_REACH_CELLS = 3
#: Every how many of the scan's cells the re-ranking reads: every second ranked those streets'
#: true places as all of them did, in half the time (55 against 110 ms a scan on the city).
RERANK_CELL_STEP = 2


def rerank(places: list[Place], grid, bev_xy: np.ndarray, n_places: int, angle_step: float) -> list[Place]:
    """The ``n_places`` of ``places`` whose BEV score is highest (``grid``: (L0, origin, d), the
    map's finest BEV level), each moved to its best pose: scored at its cell and the
    :data:`RERANK_REACH_CELLS` around it, at its yaw and 2 lattice steps either side, and the same
    turned by 180° — a straight street looks much the same both ways, and the descriptor's best
    shift named the wrong way on two of the city's streets."""
    if len(places) <= n_places:
        return places
    L0, origin, d = grid
    B = m3rsm.scan_cells(bev_xy, d)[::RERANK_CELL_STEP]
    reach = np.arange(-RERANK_REACH_CELLS, RERANK_REACH_CELLS + 1) * d
    off = np.array([(dx, dy) for dx in reach for dy in reach])
    steps = np.arange(-2, 3) * angle_step
    turns = np.concatenate([steps, steps + math.pi])
    P = np.array([(p.x, p.y, p.yaw) for p in places])
    shape = (len(places), len(off), len(turns))
    px = np.broadcast_to(P[:, None, None, 0] + off[None, :, None, 0], shape).ravel()
    py = np.broadcast_to(P[:, None, None, 1] + off[None, :, None, 1], shape).ravel()
    pyaw = np.broadcast_to(P[:, None, None, 2] + turns[None, None, :], shape).ravel()
    out = np.empty(len(px))
    _bev_scores(L0, float(origin[0]), float(origin[1]), 1.0 / d, np.ascontiguousarray(B[:, 0]),
                np.ascontiguousarray(B[:, 1]), px, py, pyaw, out)  # fmt: skip
    per_place = out.reshape(len(places), -1)
    where = per_place.argmax(axis=1)
    order = np.argsort(-per_place.max(axis=1), kind="stable")[:n_places]
    moved = []
    for i in order:
        k = i * per_place.shape[1] + where[i]
        moved.append(Place(float(px[k]), float(py[k]), float(m3rsm._wrap(pyaw[k])), places[i].distance))
    return moved


def look_up(
    index: PlaceIndex,
    scan_xyz: np.ndarray,
    n_places: int = 8,
    separation: float = 10.0,
    grid=None,
    bev_xy: np.ndarray | None = None,
    angle_step: float = math.radians(2.5),
) -> LookUp:
    """The ``n_places`` places whose descriptors are closest to the scan's (``scan_xyz``: the whole
    scan, sensor frame, levelled), at most one within ``separation`` m of another, best first.
    With ``grid`` (the map's L0, its origin and d_m) and the scan's BEV ``bev_xy``: the
    :data:`RERANK_PLACES` closest by descriptor, the ``n_places`` of them the BEV scores highest
    (:func:`rerank`)."""
    n_wanted = n_places
    if grid is not None and bev_xy is not None:
        n_places = max(n_places, RERANK_PLACES)
    t0 = time.perf_counter()
    st = index.settings
    q, hits = describe_scan(scan_xyz, index.resolution, st)
    if hits < st.min_hits or len(index) == 0:
        return LookUp([], hits, (time.perf_counter() - t0) * 1e3)
    clip = max(1, round(SECTOR_CLIP_M / st.range_unit))
    dc, _ = _shifts(index.coarse, coarse_of(q[None], st.coarse_group)[0], clip)
    keep = min(COARSE_KEEP, len(index))
    rows = np.argpartition(dc, keep - 1)[:keep] if keep < len(index) else np.arange(len(index))
    df, sf = _shifts(index.profiles[rows], q, clip)
    order = np.argsort(df, kind="stable")
    xy = index.xy[rows[order]].astype(np.float64)
    chosen = _apart(xy, separation, n_places)
    sector = 2.0 * math.pi / st.sectors
    places = [
        Place(
            float(xy[i, 0]),
            float(xy[i, 1]),
            float(m3rsm._wrap(sf[order[i]] * sector)),
            float(df[order[i]]) * st.range_unit / st.sectors,
        )
        for i in chosen
    ]
    if grid is not None and bev_xy is not None:
        places = rerank(places, grid, bev_xy, n_wanted, angle_step)
    return LookUp(places, hits, (time.perf_counter() - t0) * 1e3)


def window_of(bev, x: float, y: float, reach: float) -> BEVPyramid:
    """The pyramid to verify a place at (x, y) on: a :class:`BEVPyramid` itself, or for a city
    held in tiles a window of them ``reach`` metres around (x, y)."""
    if isinstance(bev, BEVPyramid):
        return bev
    d = bev.resolution
    cx, cy = (np.array([x, y]) - bev.origin) / d
    r = int(math.ceil(reach / d)) + 1
    return bev.window(int(cx) - r, int(cy) - r, int(cx) + r + 1, int(cy) + r + 1)


def verify(
    bev,
    bev_xy: np.ndarray,
    places: list[Place],
    half: float,
    yaw_window: float,
    angle_step: float,
    scan_reach: float,
    beat: float | None = None,
) -> list[m3rsm.MatchResult]:
    """M3RSM around each place (± ``half`` m, ± ``yaw_window`` around its yaw), the scan's points
    reaching at most ``scan_reach`` m, reporting only optima strictly above ``beat`` (any where
    None): one result a place, in the places' order (x NaN where nothing beat ``beat``)."""
    out = []
    for p in places:
        pyr = window_of(bev, p.x, p.y, half + scan_reach)
        out.append(m3rsm.match(pyr, bev_xy, (p.x, p.y), (half, half), p.yaw, yaw_window, angle_step, min_score=beat))
    return out


def combined(
    results: list[m3rsm.MatchResult], best: m3rsm.MatchResult | None, ms: float, beat: float, scored=()
) -> m3rsm.MatchResult:
    """The windows' searches as one search, for the inspection: ``best``'s optimum (none: x NaN,
    score ``beat``), the nodes expanded in all windows, the best leaves any of them scored (and
    the poses ``scored`` besides, rows of x, y, yaw, score), and the rectangle around the windows."""
    levels = max((len(r.nodes_per_level) for r in results), default=0)
    per_level = tuple(sum(r.nodes_per_level[i] for r in results if i < len(r.nodes_per_level)) for i in range(levels))
    rows = [np.asarray(r.candidates).reshape(-1, 4) for r in results] + [np.asarray(scored, np.float64).reshape(-1, 4)]
    cands = np.concatenate(rows)
    cands = cands[np.argsort(-cands[:, 3], kind="stable")[: m3rsm.N_CANDIDATES]]
    if best is not None and len(cands) and cands[0, 3] != best.score:  # the optimum first, as a search has it
        cands = np.vstack([np.asarray(best.candidates).reshape(-1, 4)[:1], cands])[: m3rsm.N_CANDIDATES]
    regions = np.array([r.region for r in results], np.float64).reshape(-1, 4)
    region = (
        (float(regions[:, 0].min()), float(regions[:, 1].min()), float(regions[:, 2].max()), float(regions[:, 3].max()))
        if len(regions)
        else ()
    )
    common = dict(
        nodes_expanded=int(sum(r.nodes_expanded for r in results)),
        ms=ms,
        n_points=max((r.n_points for r in results), default=0),
        region=region,
        n_angles=max((r.n_angles for r in results), default=0),
        candidates=cands,
        nodes_per_level=per_level,
    )
    if best is None:
        return m3rsm.MatchResult(x=math.nan, y=math.nan, yaw=math.nan, score=float(beat), **common)
    return m3rsm.MatchResult(x=best.x, y=best.y, yaw=best.yaw, score=best.score, **common)


def distinct(results: list[m3rsm.MatchResult], distinct_m: float) -> list[m3rsm.MatchResult]:
    """The verified optima by score, best first, at most one within ``distinct_m`` of a better one
    (two windows that found the same place are one answer)."""
    kept: list[m3rsm.MatchResult] = []
    for r in sorted(results, key=lambda r: -r.score):
        if all(math.hypot(r.x - k.x, r.y - k.y) > distinct_m for k in kept):
            kept.append(r)
    return kept

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
def _best_shifts(P, q, clip, out_d, out_s):
    """For each row of ``P`` (n, m) the smallest Σ_l min(|P[i, l] − q[(l − s) mod m]|, clip) over
    the shifts s, and that s (row i seen with the scan's sector j at its sector j + s)."""
    n, m = P.shape
    qq = np.empty(2 * m, np.int32)
    for j in range(m):
        qq[j] = q[j]
        qq[j + m] = q[j]
    for i in nb.prange(n):
        best = 1 << 30
        best_s = 0
        for s in range(m):
            acc = 0
            for el in range(m):
                d = abs(np.int32(P[i, el]) - qq[el - s + m])
                acc += d if d < clip else clip
            if acc < best:
                best = acc
                best_s = s
        out_d[i] = best
        out_s[i] = best_s


def _shifts(P: np.ndarray, q: np.ndarray, clip: int) -> tuple[np.ndarray, np.ndarray]:
    d = np.empty(len(P), np.int64)
    s = np.empty(len(P), np.int64)
    if len(P):
        _best_shifts(np.ascontiguousarray(P), np.ascontiguousarray(q), np.int32(clip), d, s)
    return d, s


def look_up(index: PlaceIndex, scan_xyz: np.ndarray, n_places: int = 8, separation: float = 10.0) -> LookUp:
    """The ``n_places`` places whose descriptors are closest to the scan's (``scan_xyz``: the whole
    scan, sensor frame, levelled), at most one within ``separation`` m of another, best first."""
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
    chosen: list[int] = []
    for i in range(len(order)):
        if all(math.hypot(xy[i, 0] - xy[j, 0], xy[i, 1] - xy[j, 1]) > separation for j in chosen):
            chosen.append(i)
            if len(chosen) == n_places:
                break
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

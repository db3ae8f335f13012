"""The city's streets and ground plan: one grid of straight streets over the whole city, each
district leaving out the streets its style has no use for, street classes with their own
widths and speed limits, and the ground-plan raster kept compact (a 4 km city is 67 M cells).

The network: street lines 52–84 m apart across the city (one block size, that of downtown);
every fourth to sixth line is an arterial; four lines around downtown carry the highway ring.
Then, by the district of each street segment (:mod:`.districts`): downtown keeps every segment;
suburbs leave out every other cross street (long blocks, their direction changing from one
neighbourhood to the next) and a few more at random; the industrial strip keeps one line in
three (superblocks); parks and the highway's corridor keep no local street (only arterials
cross the ring). The arterials, the ring and the city's outermost lines are always kept, so
every place stays connected; segments left dangling are removed until no street ends blind.

The plan's rasters differ from a town's only in size and type: distances in float32, the
direction to the nearest road computed on demand from int16 indices, no distance to a driven
path (nothing in a city is placed with a particular drive in mind: every drive stays in its
lane, clear of everything beside the road).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from .constants import CELL, GROUND_MARGIN, STOP_PROB
from .districts import DOWNTOWN, HIGHWAY, INDUSTRIAL, PARK, SUBURB, DistrictMap, plan_districts
from .layout import Grid, Plan, Street
from .raster import HeightField, Raster

LOCAL, ARTERIAL, RING = 0, 1, 2
KIND_NAMES = ("local", "arterial", "highway")
#: speed limits (km/h) of the highway and the arterials …
CLASS_SPEED_KMH = {RING: 90.0, ARTERIAL: 50.0}
#: … and of local streets, by district
LOCAL_SPEED_KMH = {DOWNTOWN: 40.0, SUBURB: 30.0, INDUSTRIAL: 40.0, PARK: 30.0, HIGHWAY: 30.0}


@dataclass
class CityGrid(Grid):
    """A :class:`~.layout.Grid` whose street parameters are per segment (a street changes class
    and width from one district to the next): ``h_*`` arrays are (na−1, nb) for the E–W
    segments, ``v_*`` (na, nb−1) for the N–S ones. (The per-line parameters of a town's grid
    are placeholders here, except ``speed_x``/``speed_y``: each line's top speed limit.)"""

    h_kind: np.ndarray | None = None  # street class: LOCAL, ARTERIAL or RING
    v_kind: np.ndarray | None = None
    h_hw: np.ndarray | None = None  # m, half width
    v_hw: np.ndarray | None = None
    h_speed: np.ndarray | None = None  # m/s, speed limit
    v_speed: np.ndarray | None = None
    h_sidewalk: np.ndarray | None = None  # m
    v_sidewalk: np.ndarray | None = None
    h_parking: np.ndarray | None = None  # bool
    v_parking: np.ndarray | None = None
    h_style: np.ndarray | None = None  # district style of the segment's middle
    v_style: np.ndarray | None = None

    def _edge(self, n0, n1):
        if n0[1] == n1[1]:
            return "h", min(n0[0], n1[0]), n0[1]
        return "v", n0[0], min(n0[1], n1[1])

    def edge_street(self, n0, n1):
        kind, a, b = self._edge(n0, n1)
        return (self.h_hw[a, b], self.h_speed[a, b]) if kind == "h" else (self.v_hw[a, b], self.v_speed[a, b])

    def edge_kind(self, n0, n1) -> int:
        kind, a, b = self._edge(n0, n1)
        return int(self.h_kind[a, b] if kind == "h" else self.v_kind[a, b])

    def crossing_half_width(self, prev, node):
        across = [m for m in self.neighbours(node) if (m[1] == node[1]) != (prev[1] == node[1])]
        return max((self.edge_street(node, m)[0] for m in across), default=5.5)

    def stop_probability(self, prev, node, nxt) -> float:
        """Right of way by street class: a drive on the bigger street goes on (slowing only to
        turn), one arriving from a smaller street stops at the bigger one most of the time
        (sign or light), and between equals it stops as often as in a town (arterials meet at
        lights: half the time). Nobody stops on the ring."""
        k_in = self.edge_kind(prev, node)
        if k_in == RING and self.edge_kind(node, nxt) == RING:
            return 0.0
        across = [self.edge_kind(node, m) for m in self.neighbours(node) if (m[1] == node[1]) != (prev[1] == node[1])]
        k_across = max(across, default=-1)
        straight = (nxt[0] - node[0], nxt[1] - node[1]) == (node[0] - prev[0], node[1] - prev[1])
        if k_in > k_across:
            return 0.0 if straight else 0.1
        if k_in < k_across:
            return 0.8
        return 0.5 if k_in == ARTERIAL else STOP_PROB

    def present(self):
        """Nodes with at least one street."""
        return [(a, b) for a in range(self.na) for b in range(self.nb) if self.neighbours((a, b))]


def _lines(rng: np.random.Generator, extent: float) -> np.ndarray:
    """Street line positions along one axis: block sides of a few standard lengths, jittered."""
    standard = np.array([52.0, 60.0, 68.0, 76.0, 84.0])
    positions = []
    p = rng.uniform(20.0, 40.0)
    while p < extent - 20.0:
        positions.append(p)
        p += rng.choice(standard) + rng.uniform(-4.0, 4.0)
    return np.round(np.asarray(positions) / CELL) * CELL + CELL / 2


def _degree(h_edge, v_edge):
    na, nb = v_edge.shape[0], h_edge.shape[1]
    deg = np.zeros((na, nb), np.int64)
    deg[:-1, :] += h_edge
    deg[1:, :] += h_edge
    deg[:, :-1] += v_edge
    deg[:, 1:] += v_edge
    return deg


def plan_city_grid(rng: np.random.Generator, extent: float) -> tuple[CityGrid, DistrictMap]:
    xs, ys = _lines(rng, extent), _lines(rng, extent)
    na, nb = len(xs), len(ys)

    def arterials(n):
        k = int(rng.integers(4, 7))
        flags = (np.arange(n) - int(rng.integers(k))) % k == 0
        flags[[0, -1]] = True  # the outermost lines close the city's network
        return flags

    art_x, art_y = arterials(na), arterials(nb)
    cx, cy = rng.uniform(0.45, 0.55, 2) * extent
    reach = rng.uniform(0.3, 0.36) * extent
    a0, a1 = int(np.argmin(np.abs(xs - (cx - reach)))), int(np.argmin(np.abs(xs - (cx + reach))))
    b0, b1 = int(np.argmin(np.abs(ys - (cy - reach)))), int(np.argmin(np.abs(ys - (cy + reach))))
    art_x[[a0, a1]] = art_y[[b0, b1]] = False  # the ring's lines are the highway where it runs
    districts = plan_districts(rng, extent, GROUND_MARGIN, (cx, cy), (xs[a0], xs[a1], ys[b0], ys[b1]))

    # Segments: E–W h[a, b] from (a, b) to (a+1, b); N–S v[a, b] from (a, b) to (a, b+1).
    hx = np.broadcast_to(0.5 * (xs[:-1] + xs[1:])[:, None], (na - 1, nb))
    hy = np.broadcast_to(ys[None, :], (na - 1, nb))
    vx = np.broadcast_to(xs[:, None], (na, nb - 1))
    vy = np.broadcast_to(0.5 * (ys[:-1] + ys[1:])[None, :], (na, nb - 1))
    h_style, v_style = districts.style_at(hx, hy), districts.style_at(vx, vy)
    h_kind = np.where(art_y[None, :], ARTERIAL, LOCAL).repeat(na - 1, axis=0).astype(np.int8)
    v_kind = np.where(art_x[:, None], ARTERIAL, LOCAL).repeat(nb - 1, axis=1).astype(np.int8)
    h_kind[a0:a1, [b0, b1]] = RING
    v_kind[[a0, a1], b0:b1] = RING
    h_edge, v_edge = np.ones((na - 1, nb), bool), np.ones((na, nb - 1), bool)
    h_local, v_local = h_kind == LOCAL, v_kind == LOCAL

    # What each district leaves out (local streets only).
    for style in (PARK, HIGHWAY):
        h_edge[h_local & (h_style == style)] = False
        v_edge[v_local & (v_style == style)] = False
    keep_x = (np.arange(na) - int(rng.integers(3))) % 3 == 0
    keep_y = (np.arange(nb) - int(rng.integers(3))) % 3 == 0
    h_edge[h_local & (h_style == INDUSTRIAL) & ~keep_y[None, :]] = False
    v_edge[v_local & (v_style == INDUSTRIAL) & ~keep_x[:, None]] = False
    # Suburbs: long blocks, E–W in some neighbourhoods (every other N–S street left out) and
    # N–S in others; a few more segments left out at random.
    across = rng.random((na // 4 + 1, nb // 4 + 1)) < 0.5
    odd_x = (np.arange(na) - int(rng.integers(2))) % 2 == 1
    odd_y = (np.arange(nb) - int(rng.integers(2))) % 2 == 1
    A, B = np.meshgrid(np.arange(na), np.arange(nb), indexing="ij")
    v_orient = across[A[:, :-1] // 4, B[:, :-1] // 4]
    h_orient = across[A[:-1, :] // 4, B[:-1, :] // 4]
    v_edge[v_local & (v_style == SUBURB) & v_orient & odd_x[:, None]] = False
    h_edge[h_local & (h_style == SUBURB) & ~h_orient & odd_y[None, :]] = False
    for edge, local, style in ((h_edge, h_local, h_style), (v_edge, v_local, v_style)):
        edge[local & np.isin(style, (SUBURB, DOWNTOWN)) & (rng.random(edge.shape) < 0.06)] = False

    _prune(h_edge, v_edge, h_local, v_local)
    grid = _with_streets(rng, xs, ys, h_edge, v_edge, h_kind, v_kind, h_style, v_style)
    return grid, districts


def _prune(h_edge, v_edge, h_local, v_local) -> None:
    """Remove local segments until no street ends blind and every street is reachable."""
    while True:
        deg = _degree(h_edge, v_edge)
        blind = deg == 1
        drop_h = h_edge & h_local & (blind[:-1, :] | blind[1:, :])
        drop_v = v_edge & v_local & (blind[:, :-1] | blind[:, 1:])
        if not (drop_h.any() or drop_v.any()):
            break
        h_edge[drop_h] = False
        v_edge[drop_v] = False
    # Reachability from the city's corner (on its outermost streets, which are always kept).
    na, nb = v_edge.shape[0], h_edge.shape[1]
    seen = np.zeros((na, nb), bool)
    seen[0, 0] = True
    todo = [(0, 0)]
    while todo:
        a, b = todo.pop()
        for m, ok in (
            ((a + 1, b), a + 1 < na and h_edge[a, b]),
            ((a - 1, b), a > 0 and h_edge[a - 1, b]),
            ((a, b + 1), b + 1 < nb and v_edge[a, b]),
            ((a, b - 1), b > 0 and v_edge[a, b - 1]),
        ):
            if ok and not seen[m]:
                seen[m] = True
                todo.append(m)
    h_edge &= seen[:-1, :] & seen[1:, :]
    v_edge &= seen[:, :-1] & seen[:, 1:]


def _with_streets(rng, xs, ys, h_edge, v_edge, h_kind, v_kind, h_style, v_style) -> CityGrid:
    """The grid with each street's width, sidewalk, parking and speed limit drawn once per
    stretch of one class through one district."""
    na, nb = len(xs), len(ys)
    arrays = {}
    for name, edge, kind, style in (("h", h_edge, h_kind, h_style), ("v", v_edge, v_kind, v_style)):
        hw = np.zeros(edge.shape)
        speed = np.zeros(edge.shape)
        sidewalk = np.zeros(edge.shape)
        parking = np.zeros(edge.shape, bool)
        # along the line: axis 0 for E–W segments (index a along line b), axis 1 for N–S
        lines = edge.T if name == "h" else edge
        for line in range(lines.shape[0]):
            k = 0
            n = lines.shape[1]
            while k < n:
                idx = (k, line) if name == "h" else (line, k)
                key = (kind[idx], style[idx])
                end = k
                while (
                    end + 1 < n
                    and (
                        (kind[(end + 1, line)], style[(end + 1, line)])
                        if name == "h"
                        else (kind[(line, end + 1)], style[(line, end + 1)])
                    )
                    == key
                ):
                    end += 1
                params = _street_params(rng, int(key[0]), int(key[1]))
                sl = (slice(k, end + 1), line) if name == "h" else (line, slice(k, end + 1))
                hw[sl], speed[sl], sidewalk[sl], parking[sl] = params
                k = end + 1
        arrays[name] = (hw, speed, sidewalk, parking)
    (h_hw, h_speed, h_sw, h_park), (v_hw, v_speed, v_sw, v_park) = arrays["h"], arrays["v"]
    # Per-line summaries that the town's Grid interface carries (the drive reads the top speed).
    speed_x = np.maximum(np.max(np.where(v_edge, v_speed, 0.0), axis=1), 1e-3)
    speed_y = np.maximum(np.max(np.where(h_edge, h_speed, 0.0), axis=0), 1e-3)
    grid = CityGrid(
        xs,
        ys,
        np.full(na, 6.0),
        np.full(nb, 6.0),
        np.full(na, 3.0),
        np.full(nb, 3.0),
        speed_x,
        speed_y,
        np.zeros(na, bool),
        np.zeros(nb, bool),
        h_edge,
        v_edge,
        (0, 0, 0, 0),
        h_kind=h_kind,
        v_kind=v_kind,
        h_hw=h_hw,
        v_hw=v_hw,
        h_speed=h_speed,
        v_speed=v_speed,
        h_sidewalk=h_sw,
        v_sidewalk=v_sw,
        h_parking=h_park,
        v_parking=v_park,
        h_style=h_style,
        v_style=v_style,
    )
    return grid


def _street_params(rng, kind: int, style: int):
    """(half width m, speed limit m/s, sidewalk m, parking) of a street stretch."""
    if kind == RING:
        return 11.0, CLASS_SPEED_KMH[RING] / 3.6, 4.0, False
    if kind == ARTERIAL:
        return (
            7.5,
            CLASS_SPEED_KMH[ARTERIAL] / 3.6,
            round(rng.uniform(3.0, 4.5) / CELL) * CELL,
            bool(rng.random() < 0.5),
        )
    if style == DOWNTOWN:
        return (
            float(rng.choice([6.5, 7.5])),
            LOCAL_SPEED_KMH[DOWNTOWN] / 3.6,
            round(rng.uniform(3.5, 5.0) / CELL) * CELL,
            bool(rng.random() < 0.8),
        )
    if style == INDUSTRIAL:
        return 7.0, LOCAL_SPEED_KMH[INDUSTRIAL] / 3.6, 2.5, bool(rng.random() < 0.4)
    if style == PARK:
        return 5.5, LOCAL_SPEED_KMH[PARK] / 3.6, 3.0, False
    return (
        float(rng.choice([5.5, 6.0])),
        LOCAL_SPEED_KMH[SUBURB] / 3.6,
        round(rng.uniform(2.5, 3.5) / CELL) * CELL,
        bool(rng.random() < 0.85),
    )


def city_streets(grid: CityGrid, extent: float) -> tuple[list[Street], np.ndarray]:
    """One :class:`~.layout.Street` per stretch of present segments with the same parameters,
    the arterials continued out of the city at its edges; and the junctions (where three or
    more streets meet, or a street turns)."""
    streets = []
    lo, hi = -GROUND_MARGIN, extent + GROUND_MARGIN
    for name, positions, cross in (("v", grid.xs, grid.ys), ("h", grid.ys, grid.xs)):
        edge = grid.v_edge if name == "v" else grid.h_edge.T
        kinds = grid.v_kind if name == "v" else grid.h_kind.T
        styles = grid.v_style if name == "v" else grid.h_style.T
        hw = grid.v_hw if name == "v" else grid.h_hw.T
        sw = grid.v_sidewalk if name == "v" else grid.h_sidewalk.T
        park = grid.v_parking if name == "v" else grid.h_parking.T
        for a, pos in enumerate(positions):
            k = 0
            n = edge.shape[1]
            while k < n:
                if not edge[a, k]:
                    k += 1
                    continue
                key = (hw[a, k], sw[a, k], park[a, k], kinds[a, k], styles[a, k])
                end = k
                while (
                    end + 1 < n
                    and edge[a, end + 1]
                    and (hw[a, end + 1], sw[a, end + 1], park[a, end + 1], kinds[a, end + 1], styles[a, end + 1]) == key
                ):
                    end += 1
                u0, u1 = cross[k], cross[end + 1]
                pts = np.array([[pos, u0], [pos, u1]]) if name == "v" else np.array([[u0, pos], [u1, pos]])
                streets.append(Street(pts, float(key[0]), float(key[1]), bool(key[2]), KIND_NAMES[key[3]], int(key[4])))
                k = end + 1
            if kinds[a].max() == ARTERIAL and edge[a, 0] and edge[a, -1]:  # out of the city at both ends
                for u0, u1, kk in ((lo, cross[0], 0), (cross[-1], hi, n - 1)):
                    pts = np.array([[pos, u0], [pos, u1]]) if name == "v" else np.array([[u0, pos], [u1, pos]])
                    streets.append(
                        Street(pts, float(hw[a, kk]), float(sw[a, kk]), False, "arterial", int(styles[a, kk]))
                    )
    deg = _degree(grid.h_edge, grid.v_edge)
    junctions = []
    for a in range(grid.na):
        for b in range(grid.nb):
            nbrs = grid.neighbours((a, b))
            straight = len(nbrs) == 2 and (nbrs[0][0] == nbrs[1][0] or nbrs[0][1] == nbrs[1][1])
            if deg[a, b] >= 3 or (deg[a, b] == 2 and not straight):
                junctions.append((grid.xs[a], grid.ys[b]))
    return streets, np.asarray(junctions, float).reshape(-1, 2)


# --------------------------------------------------------------------------------- ground plan
class RoadDirections:
    """``plan.road_dir`` of a city: the unit vector from a cell to its nearest road cell,
    computed where it is read from the nearest road cell's indices (2 × int16 per cell instead
    of 2 × float64)."""

    def __init__(self, ii: np.ndarray, jj: np.ndarray):
        self.ii, self.jj = ii, jj

    def __getitem__(self, key):
        i, j = key
        i, j = np.asarray(i), np.asarray(j)
        v = np.stack([self.ii[i, j].astype(np.float64) - i, self.jj[i, j].astype(np.float64) - j], axis=-1)
        return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-9)


def city_ground(rng: np.random.Generator, raster: Raster, extent: float) -> HeightField:
    """Rolling ground: a few long waves (4–8 m from lowest to highest over the city) and shorter
    hills (300–900 m across, ±1–2 m)."""
    X, Y = HeightField.node_coordinates(raster)
    z = np.zeros(X.shape)
    for wavelength_range, amplitude_range, n in (((0.8, 2.0), (0.5, 1.0), 3), ((300.0, 900.0), (0.4, 1.0), 4)):
        for _ in range(n):
            w = rng.uniform(*wavelength_range) * (extent if wavelength_range[1] < 10 else 1.0)
            ang, phase = rng.uniform(0, 2 * np.pi, 2)
            z += rng.uniform(*amplitude_range) * np.sin(2 * np.pi * (X * np.cos(ang) + Y * np.sin(ang)) / w + phase)
    z *= rng.uniform(4.0, 8.0) / max(np.ptp(z), 1e-9)
    return HeightField(raster, z)


def _road_mask(raster: Raster, streets: list[Street], junctions: np.ndarray) -> np.ndarray:
    """Cells within each street's half width of its (axis-aligned) centre line, with a disc at
    each end, and the inside corners of every junction rounded (4 m)."""
    road = np.zeros(raster.shape, bool)
    xs, ys = raster.centres()

    def span(centres, lo, hi):
        return int(np.searchsorted(centres, lo, side="left")), int(np.searchsorted(centres, hi, side="right"))

    def disc(cx, cy, r):
        i0, i1 = span(xs, cx - r, cx + r)
        j0, j1 = span(ys, cy - r, cy + r)
        road[i0:i1, j0:j1] |= np.hypot(xs[i0:i1, None] - cx, ys[None, j0:j1] - cy) <= r

    for st in streets:
        (x0, y0), (x1, y1) = st.points[0], st.points[-1]
        hw = st.half_width
        if x0 == x1:
            i0, i1 = span(xs, x0 - hw, x0 + hw)
            j0, j1 = span(ys, min(y0, y1), max(y0, y1))
        else:
            i0, i1 = span(xs, min(x0, x1), max(x0, x1))
            j0, j1 = span(ys, y0 - hw, y0 + hw)
        road[i0:i1, j0:j1] = True
        disc(x0, y0, hw)
        disc(x1, y1, hw)
    # Inside corners: fill what lies outside a 4 m circle tangent to both curbs (a closing
    # with a 4 m disc, as in a town, done junction by junction).
    r = 4.0
    for jx, jy in junctions:
        i0, i1 = span(xs, jx - 20.0, jx + 20.0)
        j0, j1 = span(ys, jy - 20.0, jy + 20.0)
        window = road[i0:i1, j0:j1]
        dist = ndimage.distance_transform_edt(~window, sampling=CELL)
        dilated = dist <= r
        window |= ndimage.distance_transform_edt(dilated, sampling=CELL) > r
    return road


def make_city_plan(
    rng, raster: Raster, ground: HeightField, streets, junctions, districts: DistrictMap, extent: float
) -> Plan:
    road = _road_mask(raster, streets, junctions)
    dist, (ii, jj) = ndimage.distance_transform_edt(~road, sampling=CELL, return_indices=True)
    dist_road = dist.astype(np.float32)
    del dist
    road_dir = RoadDirections(ii.astype(np.int16), jj.astype(np.int16))
    del ii, jj
    style = districts.on_raster(raster)
    xs, ys = raster.centres()
    inside = ((xs >= 0) & (xs <= extent))[:, None] & ((ys >= 0) & (ys <= extent))[None, :]
    build_area = inside & ~road & (style != HIGHWAY)
    park = (style == PARK) & ~road
    del style
    no_drive = np.broadcast_to(np.float32(np.inf), raster.shape)
    # No density raster: a city's buildings take their style from the districts.
    return Plan(
        raster,
        ground,
        streets,
        junctions,
        build_area,
        road,
        dist_road,
        road_dir,
        no_drive,
        np.zeros(raster.shape, bool),
        None,
        park,
        districts,
    )


def city_raster(extent: float) -> Raster:
    return Raster.covering(-GROUND_MARGIN, -GROUND_MARGIN, extent + GROUND_MARGIN, extent + GROUND_MARGIN)

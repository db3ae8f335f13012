"""Where the streets go and what the ground plan holds.

Two layouts: an irregular street grid (``plan_grid`` and ``grid_streets``), or the road under a
recorded drive with side streets branching off (``trajectory_streets``, with the ground height
taken from the drive by ``heights_from_track``). Either ends in a :class:`Plan` (``make_plan``):
road mask (from the streets' ``centre_lines``), distance fields, urban density and parks on the
raster, which the objects are placed on.
"""

from __future__ import annotations

import math
from collections import defaultdict
from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from ...errors import DataError
from .constants import (
    BUILD_REACH,
    CELL,
    GROUND_MARGIN,
    LANE_OFFSET,
    NODE_CELLS,
    SIDEWALK_MIN,
    SPEED_CHOICES_KMH,
    STOP_PROB,
)
from .raster import HeightField, Raster, densify, left_normal


# --------------------------------------------------------------------------------- streets
@dataclass
class Street:
    points: np.ndarray  # (K, 2) centre-line polyline, town frame
    half_width: float  # m, centre line to curb
    sidewalk: float  # m, curb to property line
    parking: bool  # parked cars along both curbs
    kind: str = "local"  # street class: local | arterial | highway (a city's; a town's are local)
    style: int = -1  # a city's district style the street runs through (see .districts); −1 in a town

    def __post_init__(self):
        self.points = np.asarray(self.points, dtype=np.float64)
        seg = np.linalg.norm(np.diff(self.points, axis=0), axis=1)
        self.cum = np.concatenate([[0.0], np.cumsum(seg)])

    @property
    def length(self) -> float:
        return float(self.cum[-1])

    def at(self, s):
        """Points and unit tangents at arc lengths s."""
        s = np.clip(np.asarray(s, float), 0.0, self.length)
        k = np.clip(np.searchsorted(self.cum, s, side="right") - 1, 0, len(self.points) - 2)
        d = self.points[k + 1] - self.points[k]
        seg = np.maximum(self.cum[k + 1] - self.cum[k], 1e-9)
        t = d / seg[..., None]
        p = self.points[k] + t * (s - self.cum[k])[..., None]
        return p, t


# --------------------------------------------------------------------------------- grid layout
def _street_positions(rng: np.random.Generator, size: float) -> np.ndarray:
    """Street positions along one axis: block sides drawn from a few standard lengths (towns repeat
    their lot sizes) with some jitter, so the pattern is realistic but no two blocks are alike."""
    standard = np.array([52.0, 64.0, 80.0, 104.0]) * min(1.0, size / 300.0)
    standard = np.maximum(standard, 34.0)
    positions = []
    p = rng.uniform(0.08, 0.14) * size
    while p < size * 0.9:
        positions.append(p)
        p += rng.choice(standard) + rng.uniform(-4.0, 4.0)
    if len(positions) < 2:
        positions = [size / 3.0, 2.0 * size / 3.0]
    return np.round(np.asarray(positions) / CELL) * CELL + CELL / 2  # on cell centres


@dataclass
class Grid:
    xs: np.ndarray  # x of the N–S streets (index a)
    ys: np.ndarray  # y of the E–W streets (index b)
    hw_x: np.ndarray
    hw_y: np.ndarray
    sw_x: np.ndarray
    sw_y: np.ndarray
    speed_x: np.ndarray  # m/s, speed limit
    speed_y: np.ndarray
    park_x: np.ndarray
    park_y: np.ndarray
    h_edge: np.ndarray  # (na-1, nb): (a, b)–(a+1, b) present, along E–W street b
    v_edge: np.ndarray  # (na, nb-1): (a, b)–(a, b+1) present, along N–S street a
    loop: tuple[int, int, int, int]

    @property
    def na(self):
        return len(self.xs)

    @property
    def nb(self):
        return len(self.ys)

    def node_xy(self, node):
        return np.array([self.xs[node[0]], self.ys[node[1]]])

    def neighbours(self, node):
        a, b = node
        out = []
        if a + 1 < self.na and self.h_edge[a, b]:
            out.append((a + 1, b))
        if a > 0 and self.h_edge[a - 1, b]:
            out.append((a - 1, b))
        if b + 1 < self.nb and self.v_edge[a, b]:
            out.append((a, b + 1))
        if b > 0 and self.v_edge[a, b - 1]:
            out.append((a, b - 1))
        return out

    def edge_street(self, n0, n1):
        """(half width, speed limit) of the street an edge runs along."""
        if n0[1] == n1[1]:
            return self.hw_y[n0[1]], self.speed_y[n0[1]]
        return self.hw_x[n0[0]], self.speed_x[n0[0]]

    def crossing_half_width(self, prev, node):
        """Half width of the street crossed when arriving at ``node`` from ``prev``."""
        return self.hw_x[node[0]] if prev[1] == node[1] else self.hw_y[node[1]]

    def stop_probability(self, prev, node, nxt) -> float:
        """Chance that a drive from ``prev`` through ``node`` to ``nxt`` stops at ``node``."""
        return STOP_PROB


def plan_grid(rng: np.random.Generator, size: float, loop_distance: float) -> Grid:
    xs, ys = _street_positions(rng, size), _street_positions(rng, size)

    def street_params(n):
        hw = rng.choice([5.5, 6.5, 7.5], size=n, p=[0.45, 0.35, 0.2])
        speed_kmh = np.where(hw >= 7.5, 50.0, rng.choice(SPEED_CHOICES_KMH, size=n, p=[0.2, 0.4, 0.4]))
        sw = np.round(rng.uniform(SIDEWALK_MIN, 4.5, size=n) / CELL) * CELL
        park = rng.random(n) < 0.8
        return hw, sw, speed_kmh / 3.6, park

    hw_x, sw_x, speed_x, park_x = street_params(len(xs))
    hw_y, sw_y, speed_y, park_y = street_params(len(ys))
    na, nb = len(xs), len(ys)
    h_edge = np.ones((na - 1, nb), bool)
    v_edge = np.ones((na, nb - 1), bool)

    # The loop the drive closes: a rectangle of streets whose perimeter is about half of the
    # distance the drive covers (≈ 6.5 m/s on average in town), so the start is revisited.
    target = float(np.clip(rng.uniform(0.45, 0.65) * loop_distance, 250.0, 900.0))
    best, best_err = None, np.inf
    for a0 in range(na - 1):
        for a1 in range(a0 + 1, na):
            for b0 in range(nb - 1):
                for b1 in range(b0 + 1, nb):
                    perimeter = 2 * ((xs[a1] - xs[a0]) + (ys[b1] - ys[b0]))
                    err = abs(perimeter - target) + rng.uniform(0, 30.0)  # ties broken at random
                    if err < best_err:
                        best, best_err = (a0, a1, b0, b1), err
    a0, a1, b0, b1 = best
    protected = set()
    for a in range(a0, a1):
        protected.add(("h", a, b0))
        protected.add(("h", a, b1))
    for b in range(b0, b1):
        protected.add(("v", a0, b))
        protected.add(("v", a1, b))
    grid = Grid(xs, ys, hw_x, hw_y, sw_x, sw_y, speed_x, speed_y, park_x, park_y, h_edge, v_edge, best)

    # Drop some street segments (merging blocks) while every intersection keeps ≥ 2 streets
    # (no dead ends for the drive) and the network stays connected.
    edges = [("h", a, b) for a in range(na - 1) for b in range(nb)] + [
        ("v", a, b) for a in range(na) for b in range(nb - 1)
    ]
    for idx in rng.permutation(len(edges)):
        kind, a, b = edges[idx]
        if (kind, a, b) in protected or rng.random() > 0.22:
            continue
        n0, n1 = ((a, b), (a + 1, b)) if kind == "h" else ((a, b), (a, b + 1))
        if len(grid.neighbours(n0)) < 3 or len(grid.neighbours(n1)) < 3:
            continue
        arr = h_edge if kind == "h" else v_edge
        arr[a, b] = False
        if not _connected(grid):
            arr[a, b] = True
    return grid


def _connected(grid: Grid) -> bool:
    seen = {(0, 0)}
    todo = [(0, 0)]
    while todo:
        for m in grid.neighbours(todo.pop()):
            if m not in seen:
                seen.add(m)
                todo.append(m)
    return len(seen) == grid.na * grid.nb


def grid_streets(grid: Grid, size: float) -> tuple[list[Street], np.ndarray]:
    """Street polylines (every street continues out of town at the edges) and junction centres."""
    lo, hi = -GROUND_MARGIN, size + GROUND_MARGIN
    streets = []
    for axis, positions, cross, present, hw, sw, park in (
        (0, grid.xs, grid.ys, grid.v_edge, grid.hw_x, grid.sw_x, grid.park_x),
        (1, grid.ys, grid.xs, grid.h_edge.T, grid.hw_y, grid.sw_y, grid.park_y),
    ):
        for a, pos in enumerate(positions):
            # Intervals along the street: stub from the town edge, present edges, stub to the edge.
            intervals = [[lo, cross[0]]]
            for b in range(len(cross) - 1):
                if present[a, b]:
                    if intervals[-1][1] == cross[b]:
                        intervals[-1][1] = cross[b + 1]
                    else:
                        intervals.append([cross[b], cross[b + 1]])
            if intervals[-1][1] == cross[-1]:
                intervals[-1][1] = hi
            else:
                intervals.append([cross[-1], hi])
            for u0, u1 in intervals:
                pts = np.array([[pos, u0], [pos, u1]]) if axis == 0 else np.array([[u0, pos], [u1, pos]])
                streets.append(Street(pts, float(hw[a]), float(sw[a]), bool(park[a])))
    junctions = np.array([[x, y] for x in grid.xs for y in grid.ys])
    return streets, junctions


# --------------------------------------------------------------------------------- trajectory layout
def trajectory_streets(rng, ego_xy: np.ndarray):
    """Streets around a recorded drive: the road under the trajectory (centre line LANE_OFFSET to
    its left, right-hand traffic), each stretch once even where the drive passes twice, plus side
    streets branching off. Returns (streets, junction centres)."""
    step = np.linalg.norm(np.diff(ego_xy, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(step)])
    keep = np.concatenate([[True], step > 1e-3])
    cum_k, xy_k = cum[keep], ego_xy[keep]
    s = np.arange(0.0, cum_k[-1] + 1e-9, 1.0)
    path = np.stack([np.interp(s, cum_k, xy_k[:, 0]), np.interp(s, cum_k, xy_k[:, 1])], axis=1)
    if len(path) < 3:
        raise DataError("town: the trajectory moves less than 3 m; nothing to lay a town around")
    tangent = np.gradient(path, axis=0)
    tangent = ndimage.gaussian_filter1d(tangent, 3.0, axis=0, mode="nearest")
    tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-9)
    centre = path + LANE_OFFSET * left_normal(tangent)

    # A centre-line point is "old" if the drive already passed within 7 m more than 40 m earlier.
    tree = cKDTree(centre)
    new = np.ones(len(centre), bool)
    for k, near in enumerate(tree.query_ball_point(centre, 7.0)):
        if near and min(near) < k - 40:
            new[k] = False
    streets, junctions = [], []
    hw_main = 6.0
    runs = np.flatnonzero(np.diff(np.concatenate([[0], new.astype(np.int8), [0]])))
    for r0, r1 in zip(runs[::2], runs[1::2]):
        lo, hi = max(r0 - 1, 0), min(r1 + 1, len(centre))  # overlap the old road by a point
        if hi - lo < 6:
            continue
        streets.append(Street(centre[lo:hi], hw_main, float(rng.uniform(SIDEWALK_MIN, 4.0)), bool(rng.random() < 0.8)))
        if r0 > 0:
            junctions.append(centre[r0])
        if r1 < len(centre):
            junctions.append(centre[r1 - 1])

    # Side streets: perpendicular-ish branches every 50–120 m, ending where they meet other road.
    main_tree = cKDTree(centre)
    lo_xy, hi_xy = path.min(axis=0) - BUILD_REACH, path.max(axis=0) + BUILD_REACH
    for st in list(streets):
        s_branch = rng.uniform(20.0, 60.0)
        while s_branch < st.length - 20.0:
            if rng.random() < 0.7:
                p, t = st.at(s_branch)
                side = rng.choice([-1.0, 1.0])
                ang = math.atan2(*(side * left_normal(t))[::-1]) + rng.uniform(-0.25, 0.25)
                direction = np.array([math.cos(ang), math.sin(ang)])
                hw = float(rng.choice([4.5, 5.0, 5.5]))
                pts = [p]
                for u in np.arange(hw_main, rng.uniform(40.0, 110.0), 1.0):
                    q = p + u * direction
                    if np.any(q < lo_xy) or np.any(q > hi_xy):
                        break
                    pts.append(q)
                    if u > 15.0 and main_tree.query(q)[0] < hw_main:
                        break  # joined another stretch of the road
                if len(pts) > 10:
                    streets.append(
                        Street(np.array(pts), hw, float(rng.uniform(SIDEWALK_MIN, 3.5)), bool(rng.random() < 0.5))
                    )
                    junctions.append(p)
            s_branch += rng.uniform(50.0, 120.0)
    return streets, np.asarray(junctions, float).reshape(-1, 2), path


def heights_from_track(raster: Raster, ground_points: np.ndarray) -> np.ndarray:
    """Height-field nodes that pass through the ground under a recorded drive.

    First a normalised Gaussian smoothing of the samples (6 m), blended into a wide (50 m)
    smoothing far from them. Then a local correction towards the *lowest* sample nearby: where
    the recorded heights of two passes disagree (GPS/INS drift: KITTI 09 closes its loop 3 m
    apart in z) no ground can carry both, and the car is better floating above it than sunk in it.
    """
    X, Y = HeightField.node_coordinates(raster)
    spacing = raster.cell * NODE_CELLS
    i = np.clip(np.round((ground_points[:, 0] - raster.x0) / spacing).astype(int), 0, X.shape[0] - 1)
    j = np.clip(np.round((ground_points[:, 1] - raster.y0) / spacing).astype(int), 0, X.shape[1] - 1)
    W = np.zeros(X.shape)
    S = np.zeros(X.shape)
    np.add.at(W, (i, j), 1.0)
    np.add.at(S, (i, j), ground_points[:, 2])
    mean = float(ground_points[:, 2].mean())
    Ws = ndimage.gaussian_filter(W, 3.0, mode="constant")
    Ss = ndimage.gaussian_filter(S, 3.0, mode="constant")
    Wl = ndimage.gaussian_filter(W, 25.0, mode="constant")
    Sl = ndimage.gaussian_filter(S, 25.0, mode="constant")
    wide = np.where(Wl > 1e-9, Sl / np.maximum(Wl, 1e-12), mean)
    near = np.where(Ws > 1e-9, Ss / np.maximum(Ws, 1e-12), wide)
    alpha = np.clip(Ws / 0.05, 0.0, 1.0)
    z = alpha * near + (1.0 - alpha) * wide

    residual = ground_points[:, 2] - HeightField(raster, z)(ground_points[:, 0], ground_points[:, 1])
    lowest = np.full(X.shape, np.inf)
    np.minimum.at(lowest, (i, j), residual)
    lowest = ndimage.minimum_filter(lowest, size=5, mode="constant", cval=np.inf)  # ±4 m
    known = np.isfinite(lowest)
    Wc = ndimage.gaussian_filter(known.astype(float), 1.5, mode="constant")
    Sc = ndimage.gaussian_filter(np.where(known, lowest, 0.0), 1.5, mode="constant")
    correction = np.where(Wc > 1e-6, Sc / np.maximum(Wc, 1e-12), 0.0) * np.clip(Wc / 0.3, 0.0, 1.0)
    return z + correction


# --------------------------------------------------------------------------------- ground plan
@dataclass
class Plan:
    raster: Raster
    ground: HeightField
    streets: list
    junctions: np.ndarray
    build_area: np.ndarray  # bool, where buildings may stand
    road: np.ndarray  # bool
    dist_road: np.ndarray  # m, from each cell to the road (0 on road)
    road_dir: np.ndarray  # (nx, ny, 2), unit vector from a cell to its nearest road cell
    dist_ego: np.ndarray  # m, from each cell to the driven path
    occupied: np.ndarray  # bool, taken by something solid
    density: np.ndarray  # [0, 1], urban density (tall, dense, close to the street when high); None in a city
    park: np.ndarray  # bool
    districts: object = None  # a city's DistrictMap (see .districts); None in a town


def _smooth_noise(rng: np.random.Generator, raster: Raster, feature: float) -> np.ndarray:
    """A smooth random field in [0, 1] on the raster with blobs about ``feature`` metres across."""
    coarse_shape = (int(raster.nx * raster.cell / feature) + 4, int(raster.ny * raster.cell / feature) + 4)
    coarse = rng.random(coarse_shape)
    u = (np.arange(raster.nx) + 0.5) * raster.cell / feature + 1.5
    v = (np.arange(raster.ny) + 0.5) * raster.cell / feature + 1.5
    U, V = np.meshgrid(u, v, indexing="ij")
    field = ndimage.map_coordinates(coarse, [U.ravel(), V.ravel()], order=3, mode="nearest").reshape(raster.shape)
    lo, hi = np.percentile(field, [1, 99])
    return np.clip((field - lo) / max(hi - lo, 1e-9), 0.0, 1.0)


def centre_lines(raster: Raster, streets: list[Street]) -> np.ndarray:
    """Cells the streets' centre lines pass through."""
    centre = np.zeros(raster.shape, bool)
    for st in streets:
        p = densify(st.points, CELL / 2)
        raster.paint(centre, p[:, 0], p[:, 1])
    return centre


def _road_mask(raster: Raster, streets: list[Street]) -> np.ndarray:
    """Cells within each street's half width of its centre line, with curb corners rounded."""
    road = np.zeros(raster.shape, bool)
    by_width = defaultdict(list)
    for st in streets:
        by_width[round(st.half_width / CELL) * CELL].append(st)
    for hw, group in by_width.items():
        centre = centre_lines(raster, group)
        road |= ndimage.distance_transform_edt(~centre, sampling=CELL) <= hw
    # Round the curbs: a closing with a 4 m disc fills inside corners (and slivers between roads).
    r = 4.0
    dilated = ndimage.distance_transform_edt(~road, sampling=CELL) <= r
    return road | (ndimage.distance_transform_edt(dilated, sampling=CELL) > r)


def make_plan(rng, raster, ground, streets, junctions, build_area, driven_xy, downtown=None) -> Plan:
    road = _road_mask(raster, streets)
    dist_road, (ii, jj) = ndimage.distance_transform_edt(~road, sampling=CELL, return_indices=True)
    xs, ys = raster.centres()
    vec = np.stack([xs[ii] - xs[:, None], ys[jj] - ys[None, :]], axis=-1)
    road_dir = vec / np.maximum(np.linalg.norm(vec, axis=-1, keepdims=True), 1e-9)
    ego = np.zeros(raster.shape, bool)
    dense = densify(driven_xy, CELL / 2)
    raster.paint(ego, dense[:, 0], dense[:, 1])
    dist_ego = ndimage.distance_transform_edt(~ego, sampling=CELL)
    density = _smooth_noise(rng, raster, 140.0)
    if downtown is not None:  # grid towns have a centre where it is densest
        cx, cy, spread = downtown
        X, Y = np.meshgrid(xs, ys, indexing="ij")
        density = np.clip(
            0.55 * density + 0.65 * np.exp(-((X - cx) ** 2 + (Y - cy) ** 2) / (2 * spread**2)) - 0.1, 0, 1
        )
    park = (_smooth_noise(rng, raster, 90.0) > 0.8) & ~road
    return Plan(
        raster,
        ground,
        streets,
        junctions,
        build_area & ~road,
        road,
        dist_road,
        road_dir,
        dist_ego,
        np.zeros(raster.shape, bool),
        density,
        park,
    )

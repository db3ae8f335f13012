"""The built-in world: a generated town, a drive through it, and a simulated HDL-64E scanning it.

Two ways to lay out the town:

- **grid** (default): an irregular street grid (block sides from a few standard lengths, some
  street segments missing so blocks merge), a drive that first closes one loop around a group of
  blocks (so the start is revisited) and then wanders on, right-hand traffic, stops at some
  intersections and a speed profile with 30–50 km/h cruising and braking for turns;
- **trajectory**: the drive is a real KITTI odometry ground truth (cam0 poses + Tr), and the town
  is grown around it at true scale: the road follows the trajectory's footprint, side streets
  branch off it, and buildings, trees, etc. are placed beside the road, never on it.

Both share one pipeline on a 0.5 m raster of the ground plan: street centrelines → road mask
(with rounded curb corners) → distance fields → buildings along the street frontages (varied
footprints, setbacks and heights driven by a smooth "urban density" field), back buildings,
parks, trees whose crowns are clouds of small triangles (rays pass through the gaps, so crowns
return scattered points as real foliage does), street lights and sign poles, walls, fences and
hedges on property lines, parked cars in the parking lanes, dashed centre lines, and a smooth
height field under everything with sidewalks and lots raised by a curb.

Scans are simulated on demand from (seed, index) and nothing is written to disk. The town is
built in its own frame ("town frame"); the sequence's world frame is the first LiDAR pose, as for
every :class:`~.base.Sequence`; :attr:`TownSequence.town_to_world` maps one to the other.
"""

from __future__ import annotations

import functools
import hashlib
import math
import time
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from ..config import TownConfig
from ..errors import DataError
from ..geometry import inv_pose, rotation_zyx
from .base import Sequence, check_poses, rebase_poses
from .kitti_io import cam0_to_lidar_poses, read_pose_lines, read_tr
from .lidar_sim import LidarModel, MeshPart, RaycastLidar

#: Bump whenever the generated geometry, the drive or the sensor model changes: it is part of
#: :meth:`TownSequence.identity`, which keys the prior-map cache.
TOWN_VERSION = 3

SENSOR_HEIGHT = 1.73      # m, KITTI's Velodyne above the road
LANE_OFFSET = 1.75        # m, right-hand traffic: the car drives this far right of the centre line
CELL = 0.5                # m, raster of the ground plan
NODE_CELLS = 4            # height-field node spacing in cells (2 m); road-level ground quads
BLOCK_CELLS = 8           # full raised ground quads are 8×8 cells (4 m)
CURB = 0.15               # m, sidewalks and lots above the road
GROUND_MARGIN = 40.0      # m of bare ground beyond the built area
BUILD_REACH = 70.0        # m, trajectory mode: buildings at most this far from a street
SIDEWALK_MIN = 2.5        # m, nothing built closer to the road than this
EGO_CLEARANCE = 1.3       # m, parked cars keep this far from the driven path's centre line
EGO_CLEARANCE_STATIC = 2.5  # m, poles, trees and walls keep this far
JUNCTION_CLEAR = 14.0     # m, no parking or centre-line dashes this close to a junction centre

# Driving (grid mode).
A_ACCEL = 1.5             # m/s², gentle urban acceleration
A_BRAKE = 2.5             # m/s²
A_LATERAL = 2.0           # m/s², comfortable cornering: v ≤ sqrt(a·R)
R_LEFT = 9.0              # m, turn radii of the lane path (left turns sweep wider)
R_RIGHT = 5.0
SPEED_CHOICES_KMH = (30.0, 40.0, 50.0)
STOP_PROB = 0.35          # chance of a full stop (sign, red light) at an intersection
DS = 0.1                  # m, arc-length step of the dense drive path

# Seeds of independent random streams: the town from [seed, TOWN_STREAM], scan i from [seed, i],
# the body's sway on its suspension from [seed, SWAY_STREAM].
TOWN_STREAM = (0x7A11, 0x70)
SWAY_STREAM = (0x7A11, 0x5A)
SWAY_STD = 0.13 * math.pi / 180   # rad, pitch and roll of the body on its suspension at speed
SWAY_TIME = 0.35                  # s, correlation time of the sway
SWAY_FULL_SPEED = 5.0             # m/s; the sway grows linearly up to this speed (none at a stop)


# --------------------------------------------------------------------------------- rasters
@dataclass
class Raster:
    """An axis-aligned grid of CELL-sized cells; array[i, j] is the cell at x index i, y index j."""

    x0: float
    y0: float
    nx: int
    ny: int
    cell: float = CELL

    @classmethod
    def covering(cls, xmin: float, ymin: float, xmax: float, ymax: float) -> "Raster":
        quantum = CELL * BLOCK_CELLS  # whole ground blocks, so block reshapes are exact
        x0 = math.floor(xmin / quantum) * quantum
        y0 = math.floor(ymin / quantum) * quantum
        nx = int(math.ceil((xmax - x0) / quantum)) * BLOCK_CELLS
        ny = int(math.ceil((ymax - y0) / quantum)) * BLOCK_CELLS
        return cls(x0, y0, nx, ny)

    @property
    def shape(self) -> tuple[int, int]:
        return (self.nx, self.ny)

    def ij(self, x, y):
        """Cell indices of points, clipped into the raster, and whether they were inside."""
        i = np.floor((np.asarray(x) - self.x0) / self.cell).astype(np.int64)
        j = np.floor((np.asarray(y) - self.y0) / self.cell).astype(np.int64)
        ok = (i >= 0) & (i < self.nx) & (j >= 0) & (j < self.ny)
        return np.clip(i, 0, self.nx - 1), np.clip(j, 0, self.ny - 1), ok

    def lookup(self, array, x, y, outside=0):
        i, j, ok = self.ij(x, y)
        return np.where(ok, array[i, j], outside)

    def paint(self, mask, x, y, value=True):
        i, j, ok = self.ij(x, y)
        mask[i[ok], j[ok]] = value

    def centres(self):
        xs = self.x0 + (np.arange(self.nx) + 0.5) * self.cell
        ys = self.y0 + (np.arange(self.ny) + 0.5) * self.cell
        return xs, ys


class HeightField:
    """Ground height z(x, y): bilinear interpolation of nodes every NODE_CELLS cells."""

    def __init__(self, raster: Raster, z: np.ndarray):
        self.x0, self.y0 = raster.x0, raster.y0
        self.spacing = raster.cell * NODE_CELLS
        self.z = np.asarray(z, dtype=np.float64)
        assert self.z.shape == (raster.nx // NODE_CELLS + 1, raster.ny // NODE_CELLS + 1)

    @staticmethod
    def node_coordinates(raster: Raster):
        spacing = raster.cell * NODE_CELLS
        xs = raster.x0 + np.arange(raster.nx // NODE_CELLS + 1) * spacing
        ys = raster.y0 + np.arange(raster.ny // NODE_CELLS + 1) * spacing
        return np.meshgrid(xs, ys, indexing="ij")

    def __call__(self, x, y) -> np.ndarray:
        u = np.clip((np.asarray(x, float) - self.x0) / self.spacing, 0.0, self.z.shape[0] - 1.000001)
        v = np.clip((np.asarray(y, float) - self.y0) / self.spacing, 0.0, self.z.shape[1] - 1.000001)
        i = u.astype(np.int64)
        j = v.astype(np.int64)
        fu, fv = u - i, v - j
        z = self.z
        return ((z[i, j] * (1 - fu) + z[i + 1, j] * fu) * (1 - fv)
                + (z[i, j + 1] * (1 - fu) + z[i + 1, j + 1] * fu) * fv)


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


# --------------------------------------------------------------------------------- streets
@dataclass
class Street:
    points: np.ndarray        # (K, 2) centre-line polyline, town frame
    half_width: float         # m, centre line to curb
    sidewalk: float           # m, curb to property line
    parking: bool             # parked cars along both curbs

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


def _left(t: np.ndarray) -> np.ndarray:
    return np.stack([-t[..., 1], t[..., 0]], axis=-1)


def _densify(points: np.ndarray, step: float) -> np.ndarray:
    """Points along a polyline at most ``step`` apart (for rasterising lines)."""
    points = np.asarray(points, float)
    out = [points[:1]]
    for a, b in zip(points[:-1], points[1:]):
        n = max(1, int(math.ceil(np.linalg.norm(b - a) / step)))
        f = (np.arange(1, n + 1) / n)[:, None]
        out.append(a + (b - a) * f)
    return np.concatenate(out)


# --------------------------------------------------------------------------------- the drive
@dataclass
class _LanePath:
    """The car's path in its lane, sampled every DS metres of arc length."""

    s: np.ndarray
    xy: np.ndarray
    heading: np.ndarray       # unwrapped, rad
    curvature: np.ndarray     # 1/m, signed (left positive)
    edge: np.ndarray          # route edge each sample lies on (arcs: the incoming edge)
    on_arc: np.ndarray        # bool
    vertex_s: np.ndarray      # per route vertex: s where its turn starts (or where it is passed)
    stop_back: np.ndarray     # per route vertex: (lane corner − node)·heading in, minus the turn's tangent length


def _lane_path(route: np.ndarray) -> _LanePath:
    """Offset a route through intersection centres into the right lane and round the turns."""
    P = np.asarray(route, float)
    d = np.diff(P, axis=0)
    seg_len = np.linalg.norm(d, axis=1)
    d /= seg_len[:, None]
    right = -_left(d)
    K = len(P)
    C = np.empty((K, 2))
    C[0] = P[0] + LANE_OFFSET * right[0]
    C[-1] = P[-1] + LANE_OFFSET * right[-1]
    theta = np.zeros(K)
    radius = np.zeros(K)
    for k in range(1, K - 1):
        cross = d[k - 1, 0] * d[k, 1] - d[k - 1, 1] * d[k, 0]
        theta[k] = math.atan2(cross, float(d[k - 1] @ d[k]))
        A = P[k] + LANE_OFFSET * right[k - 1]
        if abs(theta[k]) < 1e-6:
            C[k] = A
            continue
        B = P[k] + LANE_OFFSET * right[k]
        t = np.linalg.solve(np.stack([d[k - 1], -d[k]], axis=1), B - A)[0]
        C[k] = A + t * d[k - 1]
        radius[k] = R_LEFT if theta[k] > 0 else R_RIGHT
    tangent = radius * np.tan(np.abs(theta) / 2.0)

    xs, hs, ks, es, arcs = [], [], [], [], []
    vertex_s = np.zeros(K)
    s_now = 0.0
    s_list = []

    def emit(points, heading, kappa, edge, on_arc, lengths):
        nonlocal s_now
        xs.append(points)
        hs.append(heading)
        ks.append(np.full(len(points), kappa))
        es.append(np.full(len(points), edge))
        arcs.append(np.full(len(points), on_arc))
        s_list.append(s_now + lengths)

    for k in range(K - 1):
        a = C[k] + d[k] * tangent[k]
        b = C[k + 1] - d[k] * tangent[k + 1]
        length = float((b - a) @ d[k])
        if length < -1e-6:
            raise DataError("town: a street segment is too short for the turns at its ends")
        if length > 1e-6:  # (turns that meet leave no straight between them)
            n = max(1, int(math.ceil(length / DS)))
            u = np.arange(n) / n * length
            emit(a + u[:, None] * d[k], np.full(n, math.atan2(d[k, 1], d[k, 0])), 0.0, k, False, u)
            s_now += length
        vertex_s[k + 1] = s_now
        if k + 1 < K - 1 and radius[k + 1] > 0:
            R, th = radius[k + 1], theta[k + 1]
            sigma = 1.0 if th > 0 else -1.0
            phi0 = math.atan2(d[k, 1], d[k, 0])
            centre = b + sigma * R * _left(d[k])
            arc_len = R * abs(th)
            n = max(2, int(math.ceil(arc_len / DS)))
            u = np.arange(n) / n * arc_len
            phi = phi0 + sigma * u / R
            pts = centre + sigma * R * np.stack([np.sin(phi), -np.cos(phi)], axis=1)
            emit(pts, phi, sigma / R, k, True, u)
            s_now += arc_len
    emit(C[-1:], np.array([math.atan2(d[-1, 1], d[-1, 0])]), 0.0, K - 2, False, np.zeros(1))

    heading = np.unwrap(np.concatenate(hs))
    along = np.einsum("ij,ij->i", C[1:] - P[1:], d)  # (C_k − P_k)·d_in: corner beyond (+) or before (−) the node
    stop_back = np.concatenate([[0.0], along]) - tangent
    return _LanePath(
        s=np.concatenate(s_list), xy=np.concatenate(xs), heading=heading,
        curvature=np.concatenate(ks), edge=np.concatenate(es).astype(np.int64),
        on_arc=np.concatenate(arcs), vertex_s=vertex_s, stop_back=stop_back,
    )


def _speed_profile(path: _LanePath, edge_speed: np.ndarray, stops: list[tuple[float, float]],
                   slow_zones: list[tuple[float, float, float]]):
    """Speeds along the path from the limits (street, curvature, slow zones, stops) shaped by
    acceleration and braking limits. Returns (v, arrive, depart): speed at each path sample and
    the times the car reaches and leaves it (they differ only where it stops and waits)."""
    s = path.s
    limit = edge_speed[path.edge].copy()
    arc = path.on_arc
    limit[arc] = np.minimum(limit[arc], edge_speed[np.minimum(path.edge[arc] + 1, len(edge_speed) - 1)])
    curv = np.abs(path.curvature)
    curved = curv > 1e-9
    limit[curved] = np.minimum(limit[curved], np.sqrt(A_LATERAL / curv[curved]))
    for s0, s1, factor in slow_zones:
        zone = (s >= s0) & (s <= s1)
        limit[zone] *= factor
    stop_idx = np.searchsorted(s, [st for st, _ in stops]).clip(0, len(s) - 1)
    limit[stop_idx] = 0.0

    v = limit.copy()
    ds = np.diff(s)
    for i in range(len(s) - 1):  # accelerate no harder than A_ACCEL …
        v[i + 1] = min(v[i + 1], math.sqrt(v[i] * v[i] + 2.0 * A_ACCEL * ds[i]))
    for i in range(len(s) - 2, -1, -1):  # … and brake in time for every limit ahead
        v[i] = min(v[i], math.sqrt(v[i + 1] * v[i + 1] + 2.0 * A_BRAKE * ds[i]))
    # Constant acceleration between samples: dt = 2 ds / (v_i + v_{i+1}); never 0/0 because a
    # stop is a single sample and its neighbours move at ≥ sqrt(2 a ds).
    dt = 2.0 * ds / np.maximum(v[:-1] + v[1:], 1e-6)
    dwell = np.zeros(len(s))
    for (_, seconds), i in zip(stops, stop_idx):
        dwell[i] += seconds
    arrive = np.concatenate([[0.0], np.cumsum(dt + dwell[:-1])])
    return v, arrive, arrive + dwell


def _arc_length_at(times: np.ndarray, s: np.ndarray, v: np.ndarray, arrive: np.ndarray, depart: np.ndarray):
    """Where the car is at ``times``: waiting at a sample, or between two samples under the
    constant acceleration that takes it from v_i to v_{i+1} (so speeds change smoothly)."""
    i = np.clip(np.searchsorted(arrive, times, side="right") - 1, 0, len(s) - 2)
    tau = np.maximum(times - depart[i], 0.0)
    ds = s[i + 1] - s[i]
    a = (v[i + 1] ** 2 - v[i] ** 2) / (2.0 * ds)
    return np.minimum(s[i] + v[i] * tau + 0.5 * a * tau**2, s[i + 1])


def _body_sway(rng: np.random.Generator, times: np.ndarray, speed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(pitch, roll) of the car body on its suspension, rad: a stationary Gauss–Markov process
    (σ SWAY_STD, correlation time SWAY_TIME) per angle, scaled by speed (a stopped car is still).

    Why: without it the body follows the smooth ground exactly, every scan sees the ground rings
    at the same ranges, and KISS-ICP, matching those rings, measured only half of the car's motion
    over the first six scans of the default town (~7 m for 10.15 m driven over the first ten
    steps). Real drives show nothing like it: on KITTI raw 0013 KISS-ICP reads 1.20 m per step
    against the GPS/INS's 1.18 m from the first scan.

    σ and the correlation time are read off that drive's GPS/INS poses: pitch and roll minus
    their 2 s moving average have a std of 0.13–0.14°, and change by 0.08–0.10° (std) from scan
    to scan. This process changes by 0.09°. With it, KISS-ICP's first ten steps on the default
    town sum to 10.14 m for 10.15 m driven.
    """
    n = len(times)
    dt = np.diff(times, prepend=times[0])
    a = np.exp(-dt / SWAY_TIME)
    eps = rng.standard_normal((n, 2))
    angles = np.empty((n, 2))
    angles[0] = SWAY_STD * eps[0]
    for k in range(1, n):
        angles[k] = a[k] * angles[k - 1] + math.sqrt(1.0 - a[k] ** 2) * SWAY_STD * eps[k]
    scale = np.clip(speed / SWAY_FULL_SPEED, 0.0, 1.0)
    return angles[:, 0] * scale, angles[:, 1] * scale


def _vehicle_poses(x, y, yaw, ground: HeightField) -> np.ndarray:
    """LiDAR poses of a car at (x, y) heading ``yaw``: its body follows the ground plane under
    the wheels (pitch and roll from the slope), the sensor SENSOR_HEIGHT above the ground."""
    half_wheelbase, half_track = 1.35, 0.8
    f = np.stack([np.cos(yaw), np.sin(yaw)], axis=1)
    l = _left(f)
    slope_f = (ground(*(np.stack([x, y], 1) + half_wheelbase * f).T)
               - ground(*(np.stack([x, y], 1) - half_wheelbase * f).T)) / (2 * half_wheelbase)
    slope_l = (ground(*(np.stack([x, y], 1) + half_track * l).T)
               - ground(*(np.stack([x, y], 1) - half_track * l).T)) / (2 * half_track)
    x_axis = np.concatenate([f, slope_f[:, None]], axis=1)
    x_axis /= np.linalg.norm(x_axis, axis=1, keepdims=True)
    normal = np.concatenate([-slope_f[:, None] * f - slope_l[:, None] * l, np.ones((len(x), 1))], axis=1)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    y_axis = np.cross(normal, x_axis)
    T = np.tile(np.eye(4), (len(x), 1, 1))
    T[:, :3, 0] = x_axis
    T[:, :3, 1] = y_axis
    T[:, :3, 2] = normal
    T[:, :3, 3] = np.stack([x, y, ground(x, y)], axis=1) + SENSOR_HEIGHT * normal
    return T


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
class _Grid:
    xs: np.ndarray            # x of the N–S streets (index a)
    ys: np.ndarray            # y of the E–W streets (index b)
    hw_x: np.ndarray
    hw_y: np.ndarray
    sw_x: np.ndarray
    sw_y: np.ndarray
    speed_x: np.ndarray       # m/s, speed limit
    speed_y: np.ndarray
    park_x: np.ndarray
    park_y: np.ndarray
    h_edge: np.ndarray        # (na-1, nb): (a, b)–(a+1, b) present, along E–W street b
    v_edge: np.ndarray        # (na, nb-1): (a, b)–(a, b+1) present, along N–S street a
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


def _plan_grid(rng: np.random.Generator, size: float, loop_distance: float) -> _Grid:
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
    grid = _Grid(xs, ys, hw_x, hw_y, sw_x, sw_y, speed_x, speed_y, park_x, park_y, h_edge, v_edge, best)

    # Drop some street segments (merging blocks) while every intersection keeps ≥ 2 streets
    # (no dead ends for the drive) and the network stays connected.
    edges = [("h", a, b) for a in range(na - 1) for b in range(nb)] + [("v", a, b) for a in range(na) for b in range(nb - 1)]
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


def _connected(grid: _Grid) -> bool:
    seen = {(0, 0)}
    todo = [(0, 0)]
    while todo:
        for m in grid.neighbours(todo.pop()):
            if m not in seen:
                seen.add(m)
                todo.append(m)
    return len(seen) == grid.na * grid.nb


def _grid_streets(grid: _Grid, size: float) -> tuple[list[Street], np.ndarray]:
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


def _grid_route(rng: np.random.Generator, grid: _Grid, length_needed: float):
    """Nodes of the drive: half an edge, a full loop around the chosen rectangle (back past the
    start), then a random walk that prefers going straight and never U-turns."""
    a0, a1, b0, b1 = grid.loop
    cycle = ([(a, b0) for a in range(a0, a1)] + [(a1, b) for b in range(b0, b1)]
             + [(a, b1) for a in range(a1, a0, -1)] + [(a0, b) for b in range(b1, b0, -1)])
    if rng.random() < 0.5:
        cycle = cycle[::-1]
    n = len(cycle)
    lengths = [np.linalg.norm(grid.node_xy(cycle[(k + 1) % n]) - grid.node_xy(cycle[k])) for k in range(n)]
    k0 = int(rng.choice(np.flatnonzero(np.asarray(lengths) >= 40.0))) if max(lengths) >= 40.0 else int(np.argmax(lengths))
    start_xy = 0.5 * (grid.node_xy(cycle[k0]) + grid.node_xy(cycle[(k0 + 1) % n]))
    nodes = [cycle[(k0 + 1 + k) % n] for k in range(n + 1)]  # ends one node past the start point
    length = sum(lengths)
    prev = cycle[k0]
    while length < length_needed:
        here = nodes[-1]
        prev = nodes[-2] if len(nodes) >= 2 else prev
        options = [m for m in grid.neighbours(here) if m != prev] or [prev]
        heading_in = grid.node_xy(here) - grid.node_xy(prev)
        weights = np.array([3.0 if float((grid.node_xy(m) - grid.node_xy(here)) @ heading_in) > 0 else 1.0
                            for m in options])  # straight on (the grid is axis-aligned) or a turn
        nxt = options[int(rng.choice(len(options), p=weights / weights.sum()))]
        length += float(np.linalg.norm(grid.node_xy(nxt) - grid.node_xy(here)))
        nodes.append(nxt)
    return start_xy, cycle[k0], nodes


def _grid_drive(rng, grid: _Grid, n_scans: int, rate_hz: float):
    """The drive through the grid town: (times, x, y, yaw, driven dense path xy, stop count)."""
    duration = (n_scans - 1) / rate_hz
    length_needed = duration * max(grid.speed_x.max(), grid.speed_y.max()) + 200.0
    start_xy, before_start, nodes = _grid_route(rng, grid, length_needed)
    route = np.vstack([start_xy] + [grid.node_xy(m) for m in nodes])
    path = _lane_path(route)

    # Per-edge cruising speed: the street's limit, driven at 90–100 %.
    chain = [before_start] + nodes  # chain[k] → chain[k+1] is route edge k (edge 0 starts mid-block)
    edge_speed = np.array([grid.edge_street(chain[k], chain[k + 1])[1] * rng.uniform(0.9, 1.0)
                           for k in range(len(nodes))])
    stops = []
    for k in range(1, len(nodes)):
        node, prev, nxt = nodes[k - 1], chain[k - 1], nodes[k]
        turning = (node[0] - prev[0], node[1] - prev[1]) != (nxt[0] - node[0], nxt[1] - node[1])
        is_junction = len(grid.neighbours(node)) >= 3 or turning
        forced = k == 2 and not stops  # make sure the drive has a stop early on
        if is_junction and (forced or rng.random() < STOP_PROB):
            back = max(0.0, grid.crossing_half_width(prev, node) + 1.5 + path.stop_back[k])
            stops.append((path.vertex_s[k] - back, float(rng.uniform(1.5, 6.0))))
    slow_zones = []
    s_total = path.s[-1]
    for s0 in np.arange(rng.uniform(150, 400), s_total, rng.uniform(400, 700)):
        slow_zones.append((s0, s0 + rng.uniform(30, 70), float(rng.uniform(0.4, 0.7))))  # traffic ahead
    v, arrive, depart = _speed_profile(path, edge_speed, stops, slow_zones)

    times = np.arange(n_scans) / rate_hz
    if times[-1] > arrive[-1]:
        raise DataError("town: the planned route is shorter than the drive (increase the town size)")
    s_scan = _arc_length_at(times, path.s, v, arrive, depart)
    x = np.interp(s_scan, path.s, path.xy[:, 0])
    y = np.interp(s_scan, path.s, path.xy[:, 1])
    yaw = np.interp(s_scan, path.s, path.heading)
    driven = path.xy[path.s <= s_scan[-1] + 10.0]
    return times, x, y, yaw, driven, len([st for st in stops if st[0] <= s_scan[-1]])


# --------------------------------------------------------------------------------- trajectory layout
def _trajectory_streets(rng, ego_xy: np.ndarray):
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
    centre = path + LANE_OFFSET * _left(tangent)

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
                ang = math.atan2(*(side * _left(t))[::-1]) + rng.uniform(-0.25, 0.25)
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
                    streets.append(Street(np.array(pts), hw, float(rng.uniform(SIDEWALK_MIN, 3.5)), bool(rng.random() < 0.5)))
                    junctions.append(p)
            s_branch += rng.uniform(50.0, 120.0)
    return streets, np.asarray(junctions, float).reshape(-1, 2), path


def _heights_from_track(raster: Raster, ground_points: np.ndarray) -> np.ndarray:
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
class _Plan:
    raster: Raster
    ground: HeightField
    streets: list
    junctions: np.ndarray
    build_area: np.ndarray    # bool, where buildings may stand
    road: np.ndarray          # bool
    dist_road: np.ndarray     # m, from each cell to the road (0 on road)
    road_dir: np.ndarray      # (nx, ny, 2), unit vector from a cell to its nearest road cell
    dist_ego: np.ndarray      # m, from each cell to the driven path
    occupied: np.ndarray      # bool, taken by something solid
    density: np.ndarray       # [0, 1], urban density (tall, dense, close to the street when high)
    park: np.ndarray          # bool


def _road_mask(raster: Raster, streets: list[Street]) -> np.ndarray:
    """Cells within each street's half width of its centre line, with curb corners rounded."""
    road = np.zeros(raster.shape, bool)
    by_width = defaultdict(list)
    for st in streets:
        by_width[round(st.half_width / CELL) * CELL].append(st)
    for hw, group in by_width.items():
        centre = np.zeros(raster.shape, bool)
        for st in group:
            p = _densify(st.points, CELL / 2)
            raster.paint(centre, p[:, 0], p[:, 1])
        road |= ndimage.distance_transform_edt(~centre, sampling=CELL) <= hw
    # Round the curbs: a closing with a 4 m disc fills inside corners (and slivers between roads).
    r = 4.0
    dilated = ndimage.distance_transform_edt(~road, sampling=CELL) <= r
    return road | (ndimage.distance_transform_edt(dilated, sampling=CELL) > r)


def _make_plan(rng, raster, ground, streets, junctions, build_area, driven_xy, downtown=None) -> _Plan:
    road = _road_mask(raster, streets)
    dist_road, (ii, jj) = ndimage.distance_transform_edt(~road, sampling=CELL, return_indices=True)
    xs, ys = raster.centres()
    vec = np.stack([xs[ii] - xs[:, None], ys[jj] - ys[None, :]], axis=-1)
    road_dir = vec / np.maximum(np.linalg.norm(vec, axis=-1, keepdims=True), 1e-9)
    ego = np.zeros(raster.shape, bool)
    dense = _densify(driven_xy, CELL / 2)
    raster.paint(ego, dense[:, 0], dense[:, 1])
    dist_ego = ndimage.distance_transform_edt(~ego, sampling=CELL)
    density = _smooth_noise(rng, raster, 140.0)
    if downtown is not None:  # grid towns have a centre where it is densest
        cx, cy, spread = downtown
        X, Y = np.meshgrid(xs, ys, indexing="ij")
        density = np.clip(0.55 * density + 0.65 * np.exp(-((X - cx) ** 2 + (Y - cy) ** 2) / (2 * spread**2)) - 0.1, 0, 1)
    park = (_smooth_noise(rng, raster, 90.0) > 0.8) & ~road
    return _Plan(raster, ground, streets, junctions, build_area & ~road, road, dist_road, road_dir, dist_ego,
                 np.zeros(raster.shape, bool), density, park)


# --------------------------------------------------------------------------------- objects
class _Solids:
    """Collects object parameters per material; meshes are made in bulk at the end."""

    def __init__(self):
        self.boxes = defaultdict(list)     # material → (cx, cy, yaw, length, width, z0, z1, refl)
        self.prisms = defaultdict(list)    # gable roofs: (cx, cy, yaw, length, width, z0, rise, refl)
        self.cylinders = defaultdict(list)  # (cx, cy, r, z0, z1, refl)
        self.blobs = defaultdict(list)     # (cx, cy, cz, rx, ry, rz, yaw, n, leaf, shape, refl)
        self.decals = defaultdict(list)    # flat quads on the ground: (cx, cy, yaw, length, width, refl)
        self.counts = defaultdict(int)


def _rect_points(cx, cy, yaw, length, width, step=CELL):
    nu = max(2, int(math.ceil(length / step)) + 1)
    nv = max(2, int(math.ceil(width / step)) + 1)
    U, V = np.meshgrid(np.linspace(-length / 2, length / 2, nu), np.linspace(-width / 2, width / 2, nv))
    c, s = math.cos(yaw), math.sin(yaw)
    return cx + U.ravel() * c - V.ravel() * s, cy + U.ravel() * s + V.ravel() * c


def _rect_free(plan: _Plan, cx, cy, yaw, length, width, clearance=0.0):
    """A footprint can be built: inside the build area, off the road and its sidewalks, away
    from the drive and from everything already placed (``clearance`` keeps a gap)."""
    x, y = _rect_points(cx, cy, yaw, length + 2 * clearance, width + 2 * clearance)
    i, j, ok = plan.raster.ij(x, y)
    return bool(np.all(ok & plan.build_area[i, j] & ~plan.occupied[i, j]
                       & (plan.dist_road[i, j] >= SIDEWALK_MIN) & (plan.dist_ego[i, j] >= 5.0)))


def _mark_rect(plan: _Plan, cx, cy, yaw, length, width):
    x, y = _rect_points(cx, cy, yaw, length, width, step=CELL / 2)
    plan.raster.paint(plan.occupied, x, y)


def _point_free(plan: _Plan, x, y, radius, min_road=0.6):
    ang = np.linspace(0, 2 * np.pi, 8, endpoint=False)
    px = np.concatenate([[x], x + radius * np.cos(ang)])
    py = np.concatenate([[y], y + radius * np.sin(ang)])
    i, j, ok = plan.raster.ij(px, py)
    return bool(np.all(ok & ~plan.occupied[i, j] & (plan.dist_road[i, j] >= min_road)
                       & (plan.dist_ego[i, j] >= EGO_CLEARANCE_STATIC)))


def _mark_point(plan: _Plan, x, y, radius):
    x2, y2 = _rect_points(x, y, 0.0, 2 * radius, 2 * radius, step=CELL / 2)
    plan.raster.paint(plan.occupied, x2, y2)


def _building(plan: _Plan, solids: _Solids, rng, cx, cy, yaw, length, width, density):
    """A building: main block, maybe an annex of another height, a gable roof on low houses or
    roof plant on tall ones. Its base is buried below the lowest ground under it."""
    ground = plan.ground
    fx, fy = _rect_points(cx, cy, yaw, length, width, step=max(length, width) / 2)
    gz = ground(fx, fy)
    base = float(gz.min()) - 0.5
    top_ground = float(gz.max()) + CURB
    storeys = 1 + int(rng.gamma(1.0 + 5.0 * density**1.5, 1.0 + 1.2 * density))
    height = min(storeys * rng.uniform(2.9, 3.4) + rng.uniform(0.2, 1.0), 45.0)
    refl = float(rng.uniform(0.2, 0.65))
    solids.boxes["building"].append((cx, cy, yaw, length, width, base, top_ground + height, refl))
    c, s = math.cos(yaw), math.sin(yaw)
    if height < 10.0 and rng.random() < 0.6:
        along = length >= width
        solids.prisms["roof"].append((cx, cy, yaw if along else yaw + np.pi / 2, max(length, width), min(length, width),
                                      top_ground + height, rng.uniform(1.2, 3.0), float(rng.uniform(0.1, 0.4))))
    elif height > 12.0 and rng.random() < 0.5:
        ux, uy = rng.uniform(-0.3, 0.3) * length, rng.uniform(-0.3, 0.3) * width
        solids.boxes["building"].append((cx + ux * c - uy * s, cy + ux * s + uy * c, yaw, rng.uniform(2.5, 5.0),
                                         rng.uniform(2.5, 5.0), top_ground + height - 0.5,
                                         top_ground + height + rng.uniform(2.0, 3.5), refl))
    solids.counts["buildings"] += 1
    if rng.random() < 0.35:
        # Annex behind or beside the main block: L- and T-shaped footprints.
        al = rng.uniform(0.35, 0.8) * length
        aw = rng.uniform(4.0, 10.0)
        ux = rng.uniform(-0.5, 0.5) * (length - al)
        uy = width / 2 + aw / 2 - 0.3  # behind: local +v points away from the street (see _populate)
        ax, ay = cx + ux * c - uy * s, cy + ux * s + uy * c
        if _rect_free(plan, ax, ay, yaw, al, aw - 0.6):
            solids.boxes["building"].append((ax, ay, yaw, al, aw, base,
                                             top_ground + max(3.0, height * rng.uniform(0.3, 1.3)), refl))
            _mark_rect(plan, ax, ay, yaw, al, aw)
    _mark_rect(plan, cx, cy, yaw, length, width)


def _fence_line(plan: _Plan, solids: _Solids, rng, p0, p1, kind):
    """A wall, fence or hedge from p0 to p1 on the ground, split where its cells are not free."""
    length = float(np.linalg.norm(p1 - p0))
    if length < 2.0:
        return
    u = np.arange(0.0, length, CELL) + CELL / 2
    pts = p0 + (p1 - p0) / length * u[:, None]
    i, j, ok = plan.raster.ij(pts[:, 0], pts[:, 1])
    free = ok & ~plan.occupied[i, j] & ~plan.road[i, j] & (plan.dist_ego[i, j] >= EGO_CLEARANCE_STATIC)
    runs = np.flatnonzero(np.diff(np.concatenate([[0], free.astype(np.int8), [0]])))
    yaw = math.atan2(*(p1 - p0)[::-1])
    ground = plan.ground
    for r0, r1 in zip(runs[::2], runs[1::2]):
        if (r1 - r0) * CELL < 2.0:
            continue
        a, b = pts[r0] - (pts[1] - pts[0]) * 0.5, pts[r1 - 1] + (pts[1] - pts[0]) * 0.5
        seg = float(np.linalg.norm(b - a))
        mid = 0.5 * (a + b)
        gz = ground(np.array([a[0], mid[0], b[0]]), np.array([a[1], mid[1], b[1]]))
        if kind == "wall":
            h = rng.uniform(0.8, 2.2)
            solids.boxes["wall"].append((mid[0], mid[1], yaw, seg, 0.25, gz.min() - 0.3, gz.max() + CURB + h,
                                         float(rng.uniform(0.3, 0.55))))
        elif kind == "hedge":
            h = rng.uniform(1.0, 2.0)
            n = int(seg * h * 14)
            solids.blobs["hedge"].append((mid[0], mid[1], gz.mean() + CURB + h / 2, seg / 2, 0.45, h / 2, yaw,
                                          n, 0.3, 2, 0.5))
        else:  # fence: posts every 2.5 m and two rails; rays pass between them
            h = rng.uniform(1.0, 1.8)
            n_posts = int(seg / 2.5) + 1
            for k in range(n_posts):
                q = a + (b - a) * (k / max(n_posts - 1, 1))
                z = float(ground(q[0:1], q[1:2])[0])
                solids.boxes["fence"].append((q[0], q[1], yaw, 0.08, 0.08, z - 0.2, z + CURB + h, 0.45))
            for frac in (0.45, 0.9):
                z = float(gz.mean()) + CURB + h * frac
                solids.boxes["fence"].append((mid[0], mid[1], yaw, seg, 0.04, z - 0.05, z + 0.05, 0.45))
        _mark_rect(plan, mid[0], mid[1], yaw, seg, 0.5)
        solids.counts[kind + "s"] += 1


def _tree(plan: _Plan, solids: _Solids, rng, x, y, scale=1.0):
    ground_z = float(plan.ground(np.array([x]), np.array([y]))[0]) + CURB
    conifer = rng.random() < 0.25
    trunk_r = rng.uniform(0.12, 0.3) * scale
    if conifer:
        crown_h = rng.uniform(5.0, 12.0) * scale
        crown_r = crown_h * rng.uniform(0.25, 0.35)
        crown_base = ground_z + rng.uniform(0.8, 2.0)
        trunk_top = crown_base + crown_h * 0.6
        n = int(np.clip(crown_r * crown_h * 12, 80, 450))
        solids.blobs["crown"].append((x, y, crown_base, crown_r, crown_r, crown_h, 0.0, n, 0.4, 1,
                                      float(rng.uniform(0.4, 0.6))))
    else:
        crown_r = rng.uniform(1.5, 4.0) * scale
        crown_v = crown_r * rng.uniform(0.7, 1.2)
        trunk_top = ground_z + rng.uniform(2.2, 4.0) * scale
        n = int(np.clip(crown_r * crown_v * 22, 80, 450))
        solids.blobs["crown"].append((x, y, trunk_top + crown_v * 0.7, crown_r, crown_r * rng.uniform(0.8, 1.2), crown_v,
                                      rng.uniform(0, np.pi), n, 0.45, 0, float(rng.uniform(0.45, 0.7))))
    solids.cylinders["trunk"].append((x, y, trunk_r, ground_z - 0.3, trunk_top, float(rng.uniform(0.25, 0.4))))
    _mark_point(plan, x, y, max(trunk_r, 0.6))
    solids.counts["trees"] += 1


def _pole(plan: _Plan, solids: _Solids, rng, x, y, toward_road, kind):
    z = float(plan.ground(np.array([x]), np.array([y]))[0]) + CURB
    yaw = math.atan2(toward_road[1], toward_road[0])
    if kind == "light":
        h = rng.uniform(7.0, 9.0)
        solids.cylinders["pole"].append((x, y, 0.1, z - 0.3, z + h, 0.5))
        arm = 1.8
        solids.boxes["pole"].append((x + toward_road[0] * arm / 2, y + toward_road[1] * arm / 2, yaw, arm, 0.15,
                                     z + h - 0.25, z + h, 0.5))
        solids.boxes["pole"].append((x + toward_road[0] * arm, y + toward_road[1] * arm, yaw, 0.7, 0.3,
                                     z + h - 0.4, z + h - 0.1, 0.6))
    elif kind == "utility":
        h = rng.uniform(9.0, 11.0)
        solids.cylinders["pole"].append((x, y, 0.14, z - 0.3, z + h, 0.35))
        solids.boxes["pole"].append((x, y, yaw + np.pi / 2, 1.8, 0.12, z + h - 0.8, z + h - 0.65, 0.35))
    elif kind == "traffic_light":
        h = rng.uniform(5.0, 6.0)
        solids.cylinders["pole"].append((x, y, 0.12, z - 0.3, z + h, 0.5))
        arm = rng.uniform(3.0, 5.0)
        solids.boxes["pole"].append((x + toward_road[0] * arm / 2, y + toward_road[1] * arm / 2, yaw, arm, 0.15,
                                     z + h - 0.2, z + h, 0.5))
        solids.boxes["sign"].append((x + toward_road[0] * arm, y + toward_road[1] * arm, yaw, 0.35, 0.35,
                                     z + h - 1.1, z + h, 0.3))
    else:  # sign: thin post with a retro-reflective plate facing the road
        h = rng.uniform(2.2, 3.0)
        solids.cylinders["pole"].append((x, y, 0.04, z - 0.3, z + h, 0.5))
        solids.boxes["sign"].append((x, y, yaw, 0.03, 0.65, z + h - 0.7, z + h, 0.95))
    _mark_point(plan, x, y, 0.5)
    solids.counts["poles"] += 1


def _parked_car(plan: _Plan, solids: _Solids, rng, x, y, yaw):
    kind = rng.choice(3, p=[0.6, 0.3, 0.1])  # car, SUV, van
    length = [rng.uniform(3.9, 4.7), rng.uniform(4.4, 4.9), rng.uniform(4.8, 5.4)][kind]
    width = [rng.uniform(1.7, 1.85), rng.uniform(1.8, 1.95), rng.uniform(1.9, 2.05)][kind]
    body_h = [rng.uniform(0.65, 0.8), rng.uniform(0.8, 1.0), rng.uniform(1.5, 1.9)][kind]
    cabin_h = [rng.uniform(0.45, 0.55), rng.uniform(0.55, 0.7), 0.0][kind]
    fx, fy = _rect_points(x, y, yaw, length, width, step=length)
    z = float(plan.ground(fx, fy).min())
    c, s = math.cos(yaw), math.sin(yaw)
    refl = float(rng.uniform(0.1, 0.75))
    solids.boxes["car"].append((x, y, yaw, length, width, z + 0.3, z + 0.3 + body_h, refl))
    if cabin_h > 0:
        back = -0.15 * length
        solids.boxes["glass"].append((x + back * c, y + back * s, yaw, 0.55 * length, width - 0.15,
                                      z + 0.3 + body_h, z + 0.3 + body_h + cabin_h, 0.08))
    for u in (-1, 1):
        for v in (-1, 1):
            ux, uy = u * (length / 2 - 0.85), v * (width / 2 - 0.12)
            solids.boxes["wheel"].append((x + ux * c - uy * s, y + ux * s + uy * c, yaw, 0.62, 0.22, z, z + 0.62, 0.05))
    solids.counts["parked_cars"] += 1


def _populate(plan: _Plan, rng) -> _Solids:
    """Place everything beside the streets: buildings, walls/fences/hedges, trees, poles, cars,
    centre-line dashes; then back buildings and parks in the remaining space."""
    solids = _Solids()
    raster = plan.raster
    junction_tree = cKDTree(plan.junctions) if len(plan.junctions) else None

    def near_junction(p, dist):
        return junction_tree is not None and junction_tree.query(p)[0] < dist

    for st in plan.streets:
        for side in (-1.0, 1.0):
            # Per street side: its own building line and planting style.
            setback_style = rng.uniform(0.0, 1.0)
            has_trees = rng.random() < 0.55
            fence_kind = rng.choice(["wall", "fence", "hedge"])
            prop = st.half_width + st.sidewalk
            s = rng.uniform(0.0, 8.0)
            while s < st.length - 4.0:
                p, t = st.at(s)
                d = float(raster.lookup(plan.density, p[0], p[1]))
                if raster.lookup(plan.park, *(p + side * _left(t) * (prop + 6.0))):
                    s += 8.0
                    continue
                width = rng.uniform(8.0, 14.0 + 30.0 * d)
                depth = rng.uniform(8.0, 12.0 + 18.0 * d)
                setback = (rng.uniform(0.0, 1.5) if d > 0.5 else rng.uniform(1.0, 6.0)) * (0.4 + setback_style)
                pm, tm = st.at(s + width / 2)
                normal = side * _left(tm)
                centre = pm + normal * (prop + setback + depth / 2)
                yaw = math.atan2(tm[1], tm[0])
                if rng.random() < 0.05 + 0.2 * (1 - d):
                    gap = rng.uniform(8.0, 25.0)  # an empty lot: maybe walled or fenced off
                    if rng.random() < 0.5:
                        a = st.at(s)[0] + side * _left(st.at(s)[1]) * (prop + 0.3)
                        b = st.at(s + gap)[0] + side * _left(st.at(s + gap)[1]) * (prop + 0.3)
                        _fence_line(plan, solids, rng, a, b, fence_kind)
                    s += gap
                    continue
                # In a footprint's own frame (_rect_points) +v is to the left of its yaw; turning
                # right-side buildings by π makes +v point away from the street on both sides.
                b_yaw = yaw if side > 0 else yaw + np.pi
                if _rect_free(plan, centre[0], centre[1], b_yaw, width - 0.6, depth - 0.6):
                    _building(plan, solids, rng, centre[0], centre[1], b_yaw, width, depth, d)
                    if setback > 2.5 and rng.random() < 0.45:
                        a = st.at(s)[0] + normal * (prop + 0.3)
                        b = st.at(s + width)[0] + normal * (prop + 0.3)
                        _fence_line(plan, solids, rng, a, b, fence_kind)
                    s += width + (0.0 if (d > 0.55 and rng.random() < 0.6) else rng.uniform(1.5, 8.0))
                else:
                    s += 2.0

            # Street trees on the sidewalk, near the curb.
            curb_off = st.half_width + min(max(st.sidewalk * 0.45, 0.8), 1.5)
            if has_trees:
                for u in np.arange(rng.uniform(2, 8), st.length, rng.uniform(7.0, 11.0)):
                    p, t = st.at(u + rng.uniform(-0.8, 0.8))
                    q = p + side * _left(t) * curb_off
                    if not near_junction(q, st.half_width + 6.0) and _point_free(plan, q[0], q[1], 0.6):
                        _tree(plan, solids, rng, q[0], q[1], scale=rng.uniform(0.7, 1.0))
        # Street lights (or utility poles) at the curb, on one side or alternating.
        light_kind = "light" if rng.random() < 0.7 else "utility"
        alternate = rng.random() < 0.5
        for k, u in enumerate(np.arange(rng.uniform(5, 20), st.length, rng.uniform(25.0, 40.0))):
            side = (1.0 if k % 2 else -1.0) if alternate else 1.0
            p, t = st.at(u)
            q = p + side * _left(t) * (st.half_width + 0.7)
            if _point_free(plan, q[0], q[1], 0.3, min_road=0.1):
                _pole(plan, solids, rng, q[0], q[1], -side * _left(t), light_kind)

    # Signs and traffic lights at junction corners.
    for jp in plan.junctions:
        lights = rng.random() < 0.3
        for ang in rng.uniform(0, 2 * np.pi) + np.arange(4) * np.pi / 2:
            if rng.random() < (0.6 if lights else 0.35):
                for dist in (8.5, 9.5, 10.5, 7.5):
                    q = jp + dist * np.array([math.cos(ang), math.sin(ang)])
                    i, j, ok = raster.ij(q[0], q[1])
                    if ok and 0.2 <= plan.dist_road[i, j] <= 2.0 and _point_free(plan, q[0], q[1], 0.3, min_road=0.1):
                        _pole(plan, solids, rng, q[0], q[1], plan.road_dir[i, j],
                              "traffic_light" if lights else "sign")
                        break

    # Parked cars in the parking lanes; right curb faces the street's direction, left curb against.
    for st in plan.streets:
        if not st.parking:
            continue
        for side in (-1.0, 1.0):
            fill = rng.uniform(0.25, 0.85)
            u = rng.uniform(2.0, 6.0)
            while u < st.length - 3.0:
                p, t = st.at(u)
                q = p + side * _left(t) * (st.half_width - 1.15)
                yaw = math.atan2(t[1], t[0]) + (0.0 if side < 0 else np.pi) + rng.uniform(-0.03, 0.03)
                if rng.random() < fill and not near_junction(q, JUNCTION_CLEAR):
                    x, y = _rect_points(q[0], q[1], yaw, 5.0, 2.0)
                    i, j, ok = raster.ij(x, y)
                    if np.all(ok & plan.road[i, j] & ~plan.occupied[i, j] & (plan.dist_ego[i, j] >= EGO_CLEARANCE)):
                        _parked_car(plan, solids, rng, q[0], q[1], yaw)
                        _mark_rect(plan, q[0], q[1], yaw, 4.8, 1.9)
                u += rng.uniform(5.6, 7.0)

    # Dashed centre lines, not across junctions.
    for st in plan.streets:
        for u in np.arange(rng.uniform(0, 9), st.length - 3.0, 9.0):
            p, t = st.at(u + 1.5)
            if not near_junction(p, JUNCTION_CLEAR) and raster.lookup(plan.road, p[0], p[1]):
                solids.decals["marking"].append((p[0], p[1], math.atan2(t[1], t[0]), 3.0, 0.15, 0.85))

    # Back buildings inside big blocks, then trees and bushes in yards and parks.
    free_cells = np.flatnonzero((plan.build_area & ~plan.occupied & ~plan.park & (plan.dist_road >= 12.0)).ravel())
    if len(free_cells):
        for cell in rng.choice(free_cells, size=min(len(free_cells), 400), replace=False):
            i, j = np.unravel_index(cell, raster.shape)
            if plan.occupied[i, j]:
                continue
            d = float(plan.density[i, j])
            x, y = raster.x0 + (i + 0.5) * CELL, raster.y0 + (j + 0.5) * CELL
            rd = plan.road_dir[i, j]
            yaw = math.atan2(rd[1], rd[0]) + np.pi / 2 + rng.choice([0.0, np.pi / 2]) + rng.normal(0, 0.05)
            length, width = rng.uniform(8.0, 14.0 + 20.0 * d), rng.uniform(7.0, 10.0 + 14.0 * d)
            if _rect_free(plan, x, y, yaw, length, width, clearance=2.5):
                _building(plan, solids, rng, x, y, yaw, length, width, d)
    green = ~plan.road & ~plan.occupied & (plan.dist_road >= 1.5) & (plan.dist_ego >= 3.0)
    cells = np.flatnonzero(green.ravel())
    if len(cells):
        tries = rng.choice(cells, size=min(len(cells), int(len(cells) * CELL * CELL / 90.0)), replace=False)
        for cell in tries:
            i, j = np.unravel_index(cell, raster.shape)
            in_park = plan.park[i, j]
            if rng.random() > (0.9 if in_park else 0.25 * (1.0 - plan.density[i, j]) ** 2):
                continue
            x = raster.x0 + (i + rng.random()) * CELL
            y = raster.y0 + (j + rng.random()) * CELL
            if rng.random() < 0.3:  # a bush
                if _point_free(plan, x, y, 0.8, min_road=1.5):
                    gz = float(plan.ground(np.array([x]), np.array([y]))[0]) + CURB
                    r = rng.uniform(0.5, 1.3)
                    solids.blobs["bush"].append((x, y, gz + r * 0.6, r, r, r * 0.7, 0.0, int(40 * r * r + 20), 0.3, 0,
                                                 float(rng.uniform(0.4, 0.6))))
                    _mark_point(plan, x, y, r * 0.8)
                    solids.counts["bushes"] += 1
            elif _point_free(plan, x, y, 1.2, min_road=1.5):
                _tree(plan, solids, rng, x, y)
    return solids


# --------------------------------------------------------------------------------- meshes
_BOX_FACES = np.array([  # bottom 0-3, top 4-7; no bottom face (it sits on or in the ground)
    [4, 5, 6], [4, 6, 7],
    [0, 1, 5], [0, 5, 4], [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7],
])


def _boxes_mesh(rows):
    a = np.asarray(rows, float).reshape(-1, 8)
    cx, cy, yaw, L, W, z0, z1, refl = a.T
    u = np.array([-0.5, 0.5, 0.5, -0.5])[None] * L[:, None]
    v = np.array([-0.5, -0.5, 0.5, 0.5])[None] * W[:, None]
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    x = cx[:, None] + u * c - v * s
    y = cy[:, None] + u * s + v * c
    V = np.empty((len(a), 8, 3))
    V[:, :4, 0] = V[:, 4:, 0] = x
    V[:, :4, 1] = V[:, 4:, 1] = y
    V[:, :4, 2] = z0[:, None]
    V[:, 4:, 2] = z1[:, None]
    T = _BOX_FACES[None] + 8 * np.arange(len(a))[:, None, None]
    return V.reshape(-1, 3), T.reshape(-1, 3), np.repeat(refl, len(_BOX_FACES))


def _prisms_mesh(rows):
    a = np.asarray(rows, float).reshape(-1, 8)
    cx, cy, yaw, L, W, z0, rise, refl = a.T
    u = np.array([-0.5, 0.5, 0.5, -0.5, -0.5, 0.5])[None] * L[:, None]
    v = np.array([-0.5, -0.5, 0.5, 0.5, 0.0, 0.0])[None] * W[:, None]
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    V = np.empty((len(a), 6, 3))
    V[..., 0] = cx[:, None] + u * c - v * s
    V[..., 1] = cy[:, None] + u * s + v * c
    V[..., 2] = z0[:, None] + np.array([0, 0, 0, 0, 1, 1])[None] * rise[:, None]
    faces = np.array([[0, 1, 5], [0, 5, 4], [2, 3, 4], [2, 4, 5], [0, 4, 3], [1, 2, 5]])
    T = faces[None] + 6 * np.arange(len(a))[:, None, None]
    return V.reshape(-1, 3), T.reshape(-1, 3), np.repeat(refl, len(faces))


def _cylinders_mesh(rows, sides=8):
    a = np.asarray(rows, float).reshape(-1, 6)
    cx, cy, r, z0, z1, refl = a.T
    ang = np.arange(sides) * 2 * np.pi / sides
    V = np.empty((len(a), 2 * sides, 3))
    V[:, :, 0] = cx[:, None] + r[:, None] * np.tile(np.cos(ang), 2)[None]
    V[:, :, 1] = cy[:, None] + r[:, None] * np.tile(np.sin(ang), 2)[None]
    V[:, :sides, 2] = z0[:, None]
    V[:, sides:, 2] = z1[:, None]
    k = np.arange(sides)
    k1 = (k + 1) % sides
    faces = np.concatenate([
        np.stack([k, k1, k1 + sides], 1), np.stack([k, k1 + sides, k + sides], 1),
        np.stack([np.full(sides - 2, sides), np.arange(1, sides - 1) + sides, np.arange(2, sides) + sides], 1),
    ])
    T = faces[None] + 2 * sides * np.arange(len(a))[:, None, None]
    return V.reshape(-1, 3), T.reshape(-1, 3), np.repeat(refl, len(faces))


def _blobs_mesh(rows, rng):
    """Clouds of small randomly oriented triangles filling an ellipsoid (shape 0, denser towards
    its surface like foliage), a cone (1, conifers) or a box (2, hedges)."""
    a = np.asarray(rows, float).reshape(-1, 11)
    n = a[:, 7].astype(np.int64)
    rep = np.repeat(np.arange(len(a)), n)
    cx, cy, cz, rx, ry, rz, yaw, _, leaf, shape, refl = (col[rep] for col in a.T)
    m = len(rep)
    dirs = rng.standard_normal((m, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    radial = rng.random(m) ** 0.25
    ell = dirs * radial[:, None]
    f = rng.random(m)  # cone: fraction of the height; radius shrinks linearly to the tip
    disc = np.sqrt(rng.random(m))
    phi = rng.random(m) * 2 * np.pi
    cone = np.stack([(1 - f) * disc * np.cos(phi), (1 - f) * disc * np.sin(phi), f], axis=1)
    box = rng.uniform(-1.0, 1.0, (m, 3))
    local = np.where((shape == 0)[:, None], ell, np.where((shape == 1)[:, None], cone, box))
    local *= np.stack([rx, ry, rz], axis=1)
    c, s = np.cos(yaw), np.sin(yaw)
    centre = np.stack([cx + local[:, 0] * c - local[:, 1] * s, cy + local[:, 0] * s + local[:, 1] * c, cz + local[:, 2]], 1)
    V = centre[:, None, :] + rng.standard_normal((m, 3, 3)) * (0.6 * leaf)[:, None, None]
    T = np.arange(3 * m).reshape(-1, 3)
    return V.reshape(-1, 3), T, refl * rng.uniform(0.8, 1.2, m)


def _decals_mesh(rows, ground: HeightField):
    a = np.asarray(rows, float).reshape(-1, 6)
    cx, cy, yaw, L, W, refl = a.T
    u = np.array([-0.5, 0.5, 0.5, -0.5])[None] * L[:, None]
    v = np.array([-0.5, -0.5, 0.5, 0.5])[None] * W[:, None]
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    x = cx[:, None] + u * c - v * s
    y = cy[:, None] + u * s + v * c
    V = np.stack([x, y, ground(x, y) + 0.01], axis=-1)
    T = np.array([[0, 1, 2], [0, 2, 3]])[None] + 4 * np.arange(len(a))[:, None, None]
    return V.reshape(-1, 3), T.reshape(-1, 3), np.repeat(refl, 2)


def _quads(corner_index_grid_shape, i0, j0, di, dj):
    """Two triangles per quad of a vertex grid (row-major (nx+1, ny+1) indices), quads with lower
    corners (i0, j0) and extents (di, dj) in grid steps."""
    ny1 = corner_index_grid_shape[1]
    a = i0 * ny1 + j0
    b = (i0 + di) * ny1 + j0
    c = (i0 + di) * ny1 + j0 + dj
    d = i0 * ny1 + j0 + dj
    return np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])


def _compact(vertices: np.ndarray, triangles: np.ndarray):
    """Drop the vertices no triangle uses (the ground is cut from full vertex grids)."""
    used, remap = np.unique(triangles, return_inverse=True)
    return vertices[used], remap.reshape(triangles.shape)


def _ground_parts(plan: _Plan, rng) -> list[MeshPart]:
    """Road-level ground (2 m quads wherever there is road), the raised level of sidewalks and
    lots (4 m quads where a block is all raised, 0.5 m quads along curbs) and vertical curbs."""
    raster, ground = plan.raster, plan.ground
    nx, ny = raster.shape
    raised = ~plan.road
    parts = []

    # Road level on the height-field nodes.
    X, Y = HeightField.node_coordinates(raster)
    node_vertices = np.stack([X.ravel(), Y.ravel(), ground.z.ravel()], axis=1)
    nb = NODE_CELLS
    any_road = plan.road.reshape(nx // nb, nb, ny // nb, nb).any(axis=(1, 3))
    qi, qj = np.nonzero(any_road)
    tris = _quads(X.shape, qi, qj, 1, 1)
    parts.append(MeshPart("road", *_compact(node_vertices, tris), rng.uniform(0.12, 0.2, len(tris)).astype(np.float32)))

    # Raised level on the cell-corner grid.
    xc = raster.x0 + np.arange(nx + 1) * CELL
    yc = raster.y0 + np.arange(ny + 1) * CELL
    XC, YC = np.meshgrid(xc, yc, indexing="ij")
    ZC = ground(XC, YC) + CURB
    corner_vertices = np.stack([XC.ravel(), YC.ravel(), ZC.ravel()], axis=1)
    bb = BLOCK_CELLS
    full = raised.reshape(nx // bb, bb, ny // bb, bb).all(axis=(1, 3))
    fi, fj = np.nonzero(full)
    in_full = np.repeat(np.repeat(full, bb, axis=0), bb, axis=1)
    ci, cj = np.nonzero(raised & ~in_full)
    tris = np.concatenate([_quads(XC.shape, fi * bb, fj * bb, bb, bb), _quads(XC.shape, ci, cj, 1, 1)])
    # Sidewalk near the road, grass and soil behind: material by the quad's first cell.
    first_i = np.concatenate([fi * bb, fi * bb, ci, ci])  # _quads gives all first halves, then all second
    first_j = np.concatenate([fj * bb, fj * bb, cj, cj])
    near = plan.dist_road[first_i, first_j] <= 3.0
    refl = np.where(near, rng.uniform(0.25, 0.32, len(tris)), rng.uniform(0.3, 0.5, len(tris))).astype(np.float32)
    parts.append(MeshPart("sidewalk_lot", *_compact(corner_vertices, tris), refl))

    # Curbs: a vertical quad on every cell edge between road and raised ground.
    quads = []
    ex_i, ex_j = np.nonzero(raised[1:, :] != raised[:-1, :])  # edge x = xc[i+1], y from yc[j] to yc[j+1]
    quads.append(np.stack([np.stack([xc[ex_i + 1], yc[ex_j]], 1), np.stack([xc[ex_i + 1], yc[ex_j + 1]], 1)], 1))
    ey_i, ey_j = np.nonzero(raised[:, 1:] != raised[:, :-1])
    quads.append(np.stack([np.stack([xc[ey_i], yc[ey_j + 1]], 1), np.stack([xc[ey_i + 1], yc[ey_j + 1]], 1)], 1))
    ends = np.concatenate(quads)  # (Q, 2 ends, 2)
    top = ground(ends[..., 0], ends[..., 1]) + CURB
    V = np.empty((len(ends), 4, 3))
    V[:, 0, :2], V[:, 1, :2], V[:, 2, :2], V[:, 3, :2] = ends[:, 0], ends[:, 1], ends[:, 1], ends[:, 0]
    V[:, 0, 2], V[:, 1, 2] = top[:, 0] - CURB - 0.02, top[:, 1] - CURB - 0.02
    V[:, 2, 2], V[:, 3, 2] = top[:, 1], top[:, 0]
    T = np.array([[0, 1, 2], [0, 2, 3]])[None] + 4 * np.arange(len(ends))[:, None, None]
    parts.append(MeshPart("curb", V.reshape(-1, 3), T.reshape(-1, 3), 0.35))
    return parts


# Intensity of each object material is set per object above; these only name the mesh parts.
_PART_ORDER = ("building", "roof", "wall", "fence", "hedge", "trunk", "crown", "bush", "pole", "sign",
               "car", "glass", "wheel", "marking")


def _object_parts(solids: _Solids, ground: HeightField, rng) -> list[MeshPart]:
    meshes = defaultdict(list)
    for name, rows in solids.boxes.items():
        meshes[name].append(_boxes_mesh(rows))
    for name, rows in solids.prisms.items():
        meshes[name].append(_prisms_mesh(rows))
    for name, rows in solids.cylinders.items():
        meshes[name].append(_cylinders_mesh(rows))
    for name, rows in solids.blobs.items():
        meshes[name].append(_blobs_mesh(rows, rng))
    for name, rows in solids.decals.items():
        meshes[name].append(_decals_mesh(rows, ground))
    parts = []
    for name in _PART_ORDER + tuple(sorted(set(meshes) - set(_PART_ORDER))):
        if name not in meshes:
            continue
        vs, ts, rs, offset = [], [], [], 0
        for V, T, R in meshes[name]:
            vs.append(V)
            ts.append(T + offset)
            rs.append(R)
            offset += len(V)
        parts.append(MeshPart(name, np.concatenate(vs), np.concatenate(ts), np.concatenate(rs).astype(np.float32)))
    return parts


# --------------------------------------------------------------------------------- the sequence
def _file_digest(path: Path) -> str:
    return hashlib.sha1(path.read_bytes()).hexdigest()[:12]


class TownSequence(Sequence):
    """A generated town and a drive through it, scanned on demand by a simulated HDL-64E.

    ``TownSequence(seed)`` lays out a ``size`` × ``size`` m grid town and drives ``n_scans`` scans
    at ``rate_hz``; with ``trajectory`` (a KITTI odometry poses file of cam0 poses) and ``calib``
    (its calib with the ``Tr:`` line), the drive is that trajectory and the town is grown around
    it (one scan per pose; ``size`` and ``n_scans`` are then ignored).
    """

    def __init__(self, seed: int = 0, size: float = 400.0, n_scans: int = 1200, rate_hz: float = 10.0,
                 trajectory: str | Path | None = None, calib: str | Path | None = None,
                 lidar: LidarModel | None = None):
        t_start = time.perf_counter()
        self.seed = int(seed)
        self.size = float(size)
        self.rate_hz = float(rate_hz)
        self.trajectory = Path(trajectory) if trajectory is not None else None
        self.calib = Path(calib) if calib is not None else None
        if (self.trajectory is None) != (self.calib is None):
            raise DataError("town: a trajectory needs its calib (the Tr line converts cam0 poses to LiDAR poses)")
        if self.size < 100.0:
            raise DataError(f"town: size must be ≥ 100 m, got {self.size:g}")
        if n_scans < 1:
            raise DataError(f"town: n_scans must be ≥ 1, got {n_scans}")
        if not self.rate_hz > 0:
            raise DataError(f"town: rate_hz must be > 0, got {self.rate_hz:g}")
        rng = np.random.default_rng([self.seed, *TOWN_STREAM])
        self.stats: dict = {}

        if self.trajectory is None:
            self.name = f"town-seed{self.seed}"
            poses_town, times, plan = self._build_grid(rng, int(n_scans))
        else:
            self.name = f"town-seed{self.seed}-{self.trajectory.stem}"
            poses_town, times, plan = self._build_along_trajectory(rng)
        self.n_scans = len(poses_town)
        self.poses_town = poses_town
        self._times = times - times[0]
        self.town_to_world = inv_pose(poses_town[0])
        self._poses = rebase_poses(poses_town)

        solids = _populate(plan, rng)
        parts = _ground_parts(plan, rng) + _object_parts(solids, plan.ground, rng)
        self.ground = plan.ground
        self.raster = plan.raster
        self.road = plan.road
        self.streets = plan.streets
        self.lidar = RaycastLidar(parts, lidar)
        self.lidar.build()
        self.stats.update(dict(solids.counts), triangles=self.lidar.n_triangles, streets=len(plan.streets),
                              build_seconds=time.perf_counter() - t_start)

    # -------------------------------------------------------------- construction
    def _build_grid(self, rng, n_scans):
        size = self.size
        grid = _plan_grid(rng, size, loop_distance=6.5 * n_scans / self.rate_hz)
        streets, junctions = _grid_streets(grid, size)
        times, x, y, yaw, driven, n_stops = _grid_drive(rng, grid, n_scans, self.rate_hz)
        raster = Raster.covering(-GROUND_MARGIN, -GROUND_MARGIN, size + GROUND_MARGIN, size + GROUND_MARGIN)

        # Rolling hills: a few long plane waves, scaled to 3–6 m from lowest to highest point.
        X, Y = HeightField.node_coordinates(raster)
        z = np.zeros(X.shape)
        for _ in range(4):
            wavelength = rng.uniform(0.9, 2.2) * size
            ang, phase = rng.uniform(0, 2 * np.pi, 2)
            z += rng.uniform(0.4, 1.0) * np.sin(2 * np.pi * (X * np.cos(ang) + Y * np.sin(ang)) / wavelength + phase)
        in_town = (X >= 0) & (X <= size) & (Y >= 0) & (Y <= size)
        z *= rng.uniform(3.0, 6.0) / max(np.ptp(z[in_town]), 1e-9)
        ground = HeightField(raster, z)

        xs, ys = raster.centres()
        build_area = ((xs >= 0) & (xs <= size))[:, None] & ((ys >= 0) & (ys <= size))[None, :]
        downtown = (rng.uniform(0.3, 0.7) * size, rng.uniform(0.3, 0.7) * size, 0.28 * size)
        plan = _make_plan(rng, raster, ground, streets, junctions, build_area, driven, downtown)
        poses = _vehicle_poses(x, y, yaw, ground)
        speed = np.hypot(np.gradient(x, times), np.gradient(y, times)) if len(times) > 1 else np.zeros(1)
        pitch, roll = _body_sway(np.random.default_rng([self.seed, *SWAY_STREAM]), times, speed)
        poses[:, :3, :3] = poses[:, :3, :3] @ rotation_zyx(0.0, pitch, roll)   # about the sensor
        self.stats.update(stops=n_stops, route_loop=grid.loop)
        return poses, times, plan

    def _build_along_trajectory(self, rng):
        cam0 = read_pose_lines(self.trajectory)
        Tr = read_tr(self.calib)
        poses = rebase_poses(cam0_to_lidar_poses(cam0, Tr))
        poses = check_poses(poses, len(cam0), str(self.trajectory))
        if len(poses) < 2:
            raise DataError(f"{self.trajectory}: a trajectory needs at least 2 poses")
        times = self._trajectory_times(len(poses))
        xy = poses[:, :2, 3]
        streets, junctions, path = _trajectory_streets(rng, xy)
        lo = xy.min(axis=0) - BUILD_REACH - GROUND_MARGIN
        hi = xy.max(axis=0) + BUILD_REACH + GROUND_MARGIN
        raster = Raster.covering(lo[0], lo[1], hi[0], hi[1])
        # The ground passes SENSOR_HEIGHT below each LiDAR pose, along the car's own up axis.
        under = poses[:, :3, 3] - SENSOR_HEIGHT * poses[:, :3, 2]
        step = np.linalg.norm(np.diff(under[:, :2], axis=0), axis=1)
        cum = np.concatenate([[0.0], np.cumsum(step)])
        s = np.arange(0.0, cum[-1] + 1e-9, 1.0)
        moving = np.concatenate([[True], step > 1e-3])
        samples = np.stack([np.interp(s, cum[moving], under[moving, k]) for k in range(3)], axis=1)
        ground = HeightField(raster, _heights_from_track(raster, samples))
        centre = np.zeros(raster.shape, bool)
        for st in streets:
            p = _densify(st.points, CELL / 2)
            raster.paint(centre, p[:, 0], p[:, 1])
        centre_dist = ndimage.distance_transform_edt(~centre, sampling=CELL)
        build_area = centre_dist <= BUILD_REACH
        plan = _make_plan(rng, raster, ground, streets, junctions, build_area, path)
        # Sensor height above the ground minus SENSOR_HEIGHT: ≈ 0, > 0 where the drive's own
        # heights disagree between passes (see _heights_from_track), < 0 would be a sunken car.
        residual = samples[:, 2] - ground(samples[:, 0], samples[:, 1])
        self.stats.update(ground_residual_median=float(np.median(np.abs(residual))),
                          ground_residual_min=float(residual.min()), ground_residual_max=float(residual.max()))
        return poses, times, plan

    def _trajectory_times(self, n):
        """Timestamps from the times file beside the poses (``…/times/SS.txt`` as in
        kitti_odometry_poses, or ``sequences/SS/times.txt``), else ``rate_hz``."""
        candidates = [self.trajectory.parent.parent / "times" / self.trajectory.name,
                      self.trajectory.parent.parent / "sequences" / self.trajectory.stem / "times.txt"]
        for path in candidates:
            if path.is_file():
                try:
                    times = np.loadtxt(path, dtype=np.float64, ndmin=1)
                except ValueError:
                    raise DataError(f"{path}: not a column of numbers") from None
                if len(times) != n:
                    raise DataError(f"{path}: {len(times)} timestamps for {n} poses in {self.trajectory}")
                self._times_source = str(path)
                return times
        self._times_source = f"{self.rate_hz:g} Hz"
        return np.arange(n) / self.rate_hz

    @classmethod
    def from_config(cls, cfg: TownConfig, seed: int | None = None, trajectory: Path | None = None,
                    calib: Path | None = None) -> "TownSequence":
        """The town of ``cfg`` (``seed`` overrides ``cfg.seed``), optionally along a trajectory."""
        return cls(seed=cfg.seed if seed is None else seed, size=cfg.size, n_scans=cfg.n_scans,
                   rate_hz=cfg.rate_hz, trajectory=trajectory, calib=calib)

    # -------------------------------------------------------------- Sequence interface
    def __len__(self) -> int:
        return self.n_scans

    def _read_scan(self, i: int) -> np.ndarray:
        rng = np.random.default_rng([self.seed, int(i)])
        return self.lidar.scan(self.poses_town[i], rng)

    def _describe_scan(self, i: int) -> str:
        return f"town seed {self.seed} scan {i}"

    @property
    def timestamps(self) -> np.ndarray:
        return self._times

    @property
    def poses(self) -> np.ndarray:
        return self._poses

    def identity(self) -> str:
        parts = [f"town|v{TOWN_VERSION}", f"seed={self.seed}", f"size={self.size:g}", f"n_scans={self.n_scans}",
                 f"rate={self.rate_hz:g}", f"lidar={self.lidar.model}"]
        if self.trajectory is not None:
            parts += [f"trajectory={self.trajectory.resolve()}#{_file_digest(self.trajectory)}",
                      f"calib={self.calib.resolve()}#{_file_digest(self.calib)}", f"times={self._times_source}"]
        return "|".join(parts)

    # -------------------------------------------------------------- extras for display and tests
    @property
    def speeds(self) -> np.ndarray:
        """(len,) m/s, ground-truth speed between consecutive scans (last one repeated)."""
        d = np.linalg.norm(np.diff(self._poses[:, :3, 3], axis=0), axis=1)
        dt = np.diff(self._times)
        v = d / np.maximum(dt, 1e-9)
        return np.concatenate([v, v[-1:]]) if len(v) else np.zeros(1)

    def world_mesh(self) -> list[tuple[str, np.ndarray, np.ndarray]]:
        """The town's triangles in the world frame: [(material, vertices (V, 3) float32, triangles
        (T, 3) uint32)], for display."""
        R, t = self.town_to_world[:3, :3], self.town_to_world[:3, 3]
        return [(p.name, (p.vertices.astype(np.float64) @ R.T + t).astype(np.float32), p.triangles)
                for p in self.lidar.parts]

    @functools.cached_property
    def extent(self) -> np.ndarray:
        """(2, 3) world-frame bounding box [min, max] of everything the sensor can hit."""
        lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
        for _, vertices, triangles in self.world_mesh():
            used = vertices[np.unique(triangles)]
            lo, hi = np.minimum(lo, used.min(axis=0)), np.maximum(hi, used.max(axis=0))
        return np.stack([lo, hi]).astype(np.float64)

    def ground_height_world(self, xy: np.ndarray) -> np.ndarray:
        """Approximate world-frame z of the road surface under world-frame points (N, 2); exact
        when the first pose is level, off by the first pose's tilt times the distance otherwise."""
        xy = np.atleast_2d(np.asarray(xy, float))
        world_to_town = inv_pose(self.town_to_world)
        p = np.concatenate([xy, np.zeros((len(xy), 1))], axis=1) @ world_to_town[:3, :3].T + world_to_town[:3, 3]
        ground_town = np.stack([p[:, 0], p[:, 1], self.ground(p[:, 0], p[:, 1])], axis=1)
        return (ground_town @ self.town_to_world[:3, :3].T + self.town_to_world[:3, 3])[:, 2]

"""The drive: the car's path in its lane, its speed along it, where it is at each scan time, and
the LiDAR poses of a car body that follows the ground and sways on its suspension.

In a grid town the route is planned here too (``grid_drive``): a loop around a group of blocks
and then a random walk, with stops at some intersections and slow traffic now and then.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ...errors import DataError
from .constants import (
    A_ACCEL,
    A_BRAKE,
    A_LATERAL,
    DS,
    LANE_OFFSET,
    R_LEFT,
    R_RIGHT,
    SENSOR_HEIGHT,
    SWAY_FULL_SPEED,
    SWAY_STD,
    SWAY_TIME,
)
from .layout import Grid
from .raster import HeightField, left_normal


@dataclass
class _LanePath:
    """The car's path in its lane, sampled every DS metres of arc length."""

    s: np.ndarray
    xy: np.ndarray
    heading: np.ndarray  # unwrapped, rad
    curvature: np.ndarray  # 1/m, signed (left positive)
    edge: np.ndarray  # route edge each sample lies on (arcs: the incoming edge)
    on_arc: np.ndarray  # bool
    vertex_s: np.ndarray  # per route vertex: s where its turn starts (or where it is passed)
    stop_back: np.ndarray  # per route vertex: (lane corner − node)·heading in, minus the turn's tangent length


def _lane_path(route: np.ndarray) -> _LanePath:
    """Offset a route through intersection centres into the right lane and round the turns."""
    P = np.asarray(route, float)
    d = np.diff(P, axis=0)
    seg_len = np.linalg.norm(d, axis=1)
    d /= seg_len[:, None]
    right = -left_normal(d)
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
            centre = b + sigma * R * left_normal(d[k])
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
        s=np.concatenate(s_list),
        xy=np.concatenate(xs),
        heading=heading,
        curvature=np.concatenate(ks),
        edge=np.concatenate(es).astype(np.int64),
        on_arc=np.concatenate(arcs),
        vertex_s=vertex_s,
        stop_back=stop_back,
    )


def _speed_profile(
    path: _LanePath,
    edge_speed: np.ndarray,
    stops: list[tuple[float, float]],
    slow_zones: list[tuple[float, float, float]],
):
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


def body_sway(rng: np.random.Generator, times: np.ndarray, speed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
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


def vehicle_poses(x, y, yaw, ground: HeightField) -> np.ndarray:
    """LiDAR poses of a car at (x, y) heading ``yaw``: its body follows the ground plane under
    the wheels (pitch and roll from the slope), the sensor SENSOR_HEIGHT above the ground."""
    half_wheelbase, half_track = 1.35, 0.8
    f = np.stack([np.cos(yaw), np.sin(yaw)], axis=1)
    l = left_normal(f)
    slope_f = (
        ground(*(np.stack([x, y], 1) + half_wheelbase * f).T) - ground(*(np.stack([x, y], 1) - half_wheelbase * f).T)
    ) / (2 * half_wheelbase)
    slope_l = (
        ground(*(np.stack([x, y], 1) + half_track * l).T) - ground(*(np.stack([x, y], 1) - half_track * l).T)
    ) / (2 * half_track)
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


# --------------------------------------------------------------------------------- grid route
def choose_next_node(rng: np.random.Generator, grid: Grid, prev, here, options: list):
    """The next grid node of a drive arriving at ``here`` from ``prev``: straight on three times
    as likely as a turn (the grid is axis-aligned)."""
    heading_in = grid.node_xy(here) - grid.node_xy(prev)
    weights = np.array(
        [3.0 if float((grid.node_xy(m) - grid.node_xy(here)) @ heading_in) > 0 else 1.0 for m in options]
    )
    return options[int(rng.choice(len(options), p=weights / weights.sum()))]


def _grid_route(rng: np.random.Generator, grid: Grid, length_needed: float):
    """Nodes of the drive: half an edge, a full loop around the chosen rectangle (back past the
    start), then a random walk that prefers going straight and never U-turns."""
    a0, a1, b0, b1 = grid.loop
    cycle = (
        [(a, b0) for a in range(a0, a1)]
        + [(a1, b) for b in range(b0, b1)]
        + [(a, b1) for a in range(a1, a0, -1)]
        + [(a0, b) for b in range(b1, b0, -1)]
    )
    if rng.random() < 0.5:
        cycle = cycle[::-1]
    n = len(cycle)
    lengths = [np.linalg.norm(grid.node_xy(cycle[(k + 1) % n]) - grid.node_xy(cycle[k])) for k in range(n)]
    k0 = (
        int(rng.choice(np.flatnonzero(np.asarray(lengths) >= 40.0)))
        if max(lengths) >= 40.0
        else int(np.argmax(lengths))
    )
    start_xy = 0.5 * (grid.node_xy(cycle[k0]) + grid.node_xy(cycle[(k0 + 1) % n]))
    nodes = [cycle[(k0 + 1 + k) % n] for k in range(n + 1)]  # ends one node past the start point
    length = sum(lengths)
    prev = cycle[k0]
    while length < length_needed:
        here = nodes[-1]
        prev = nodes[-2] if len(nodes) >= 2 else prev
        options = [m for m in grid.neighbours(here) if m != prev] or [prev]
        nxt = choose_next_node(rng, grid, prev, here, options)
        length += float(np.linalg.norm(grid.node_xy(nxt) - grid.node_xy(here)))
        nodes.append(nxt)
    return start_xy, cycle[k0], nodes


@dataclass
class GridDrive:
    """A drive through the grid: the car at each scan time and what it drove."""

    times: np.ndarray
    x: np.ndarray
    y: np.ndarray
    yaw: np.ndarray
    driven: np.ndarray  # (K, 2) dense path actually driven (plus 10 m)
    n_stops: int
    edges: list  # grid edges driven, in order: ((a, b), (a', b')) node pairs


def grid_drive(rng, grid: Grid, n_scans: int, rate_hz: float, plan_route=None) -> GridDrive:
    """The drive through the grid town. ``plan_route(rng, grid, length_needed)`` gives the route
    as (start point, node before the start, nodes); the default is :func:`_grid_route`."""
    duration = (n_scans - 1) / rate_hz
    length_needed = duration * max(grid.speed_x.max(), grid.speed_y.max()) + 200.0
    start_xy, before_start, nodes = (plan_route or _grid_route)(rng, grid, length_needed)
    route = np.vstack([start_xy] + [grid.node_xy(m) for m in nodes])
    path = _lane_path(route)

    # Per-edge cruising speed: the street's limit, driven at 90–100 %.
    chain = [before_start] + nodes  # chain[k] → chain[k+1] is route edge k (edge 0 starts mid-block)
    edge_speed = np.array(
        [grid.edge_street(chain[k], chain[k + 1])[1] * rng.uniform(0.9, 1.0) for k in range(len(nodes))]
    )
    stops = []
    for k in range(1, len(nodes)):
        node, prev, nxt = nodes[k - 1], chain[k - 1], nodes[k]
        turning = (node[0] - prev[0], node[1] - prev[1]) != (nxt[0] - node[0], nxt[1] - node[1])
        is_junction = len(grid.neighbours(node)) >= 3 or turning
        forced = k == 2 and not stops  # make sure the drive has a stop early on
        if is_junction and (forced or rng.random() < grid.stop_probability(prev, node, nxt)):
            back = max(0.0, grid.crossing_half_width(prev, node) + 1.5 + path.stop_back[k])
            stops.append((path.vertex_s[k] - back, float(rng.uniform(1.5, 6.0))))
    slow_zones = []
    s_total = path.s[-1]
    for s0 in np.arange(rng.uniform(150, 400), s_total, rng.uniform(400, 700)):
        slow_zones.append((s0, s0 + rng.uniform(30, 70), float(rng.uniform(0.4, 0.7))))  # traffic ahead
    v, arrive, depart = _speed_profile(path, edge_speed, stops, slow_zones)

    times = np.arange(n_scans) / rate_hz
    if times[-1] > arrive[-1]:
        raise DataError("town: the planned route is shorter than the drive (increase town.extent_m)")
    s_scan = _arc_length_at(times, path.s, v, arrive, depart)
    x = np.interp(s_scan, path.s, path.xy[:, 0])
    y = np.interp(s_scan, path.s, path.xy[:, 1])
    yaw = np.interp(s_scan, path.s, path.heading)
    driven = path.xy[path.s <= s_scan[-1] + 10.0]
    edges = [(chain[k], chain[k + 1]) for k in range(len(nodes)) if path.vertex_s[k] <= s_scan[-1]]
    return GridDrive(times, x, y, yaw, driven, len([st for st in stops if st[0] <= s_scan[-1]]), edges)


def interpolate_poses(times: np.ndarray, poses: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Poses (m, 4, 4) at times ``t`` (m,) between the poses (n, 4, 4) known at ``times`` (n,):
    translation linear, rotation by Slerp between the two neighbouring poses, extrapolated at
    constant velocity beyond the first and the last."""
    from scipy.spatial.transform import Rotation

    t = np.asarray(t, np.float64)
    if len(times) < 2:
        return np.broadcast_to(poses[0], (len(t), 4, 4)).copy()
    i = np.clip(np.searchsorted(times, t, side="right") - 1, 0, len(times) - 2)
    f = (t - times[i]) / np.maximum(times[i + 1] - times[i], 1e-12)
    # A sweep's times fall into one or two intervals: one rotation step per interval.
    intervals, which = np.unique(i, return_inverse=True)
    step = Rotation.from_matrix(np.swapaxes(poses[intervals, :3, :3], 1, 2) @ poses[intervals + 1, :3, :3]).as_rotvec()
    out = np.tile(np.eye(4), (len(t), 1, 1))
    out[:, :3, :3] = poses[i, :3, :3] @ Rotation.from_rotvec(step[which] * f[:, None]).as_matrix()
    out[:, :3, 3] = poses[i, :3, 3] + f[:, None] * (poses[i + 1, :3, 3] - poses[i, :3, 3])
    return out

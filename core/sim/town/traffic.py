"""Traffic (``town.traffic``): cars, cyclists and pedestrians moving through the town while a
drive scans it. Never in the mapping drive's scans, so never in the map.

Who goes where (all drawn from the town seed's traffic stream):

- **cars** in the lanes of every street, right-hand traffic, LANE_OFFSET right of the centre
  line (less on narrow streets with parking, so they pass the parked cars), one speed per lane
  (29–47 km/h) and 20–150 m between cars. The drive's own lanes (wherever it drives in their
  direction) carry no such cars: nothing steers them around the drive's car;
- a **leading car** in the drive's own lane, now and then for 15–45 s: it is where the drive
  will be 1.5 s later, 8 m further on (so it brakes and stops as the drive does, and keeps a
  gap of at least 8 m centre to centre); it joins and leaves near a junction where there is one;
- **cyclists** at the road's right edge (left of the parking lane), 3.5–6 m/s, where the street
  leaves them room beside a car in the lane;
- **pedestrians** on both sidewalks, both ways, 70 % of the sidewalk's width from the curb,
  1.0–1.6 m/s.

Each mover runs along its path at a constant speed and starts over when it reaches the path's
end (after an unseen stretch), so the traffic at any time is a closed-form function of that
time. Simplifications: nobody turns at a junction (a car reaching the end of a street that ends
at a T-junction leaves the scene there), movers on one path may pass through each other when
their speeds differ (pedestrians, cyclists), nothing is drawn within 5 m (cars) or 2 m (others)
of the drive's sensor, and with motion skew the traffic stands still during each sweep.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from ..lidar_sim import Movers
from .constants import CURB, LANE_OFFSET, TRAFFIC_STREAM
from .meshes import boxes_part
from .raster import left_normal
from .world import Town

CAR, CYCLIST, PEDESTRIAN, LEADER = 0, 1, 2, 3
KIND_NAMES = ("car", "cyclist", "pedestrian", "leader")
_KEEP_OUT = np.array([5.0, 2.0, 2.0, 0.0])  # m from the drive's sensor, per kind
LEADER_HEADWAY = 1.5  # s
LEADER_GAP = 8.0  # m, centre to centre


def _offset_polyline(points: np.ndarray, offset: float) -> np.ndarray:
    """The polyline ``offset`` m to the right of ``points`` (per-vertex normals)."""
    tangent = np.gradient(points, axis=0)
    tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-9)
    return points - offset * left_normal(tangent)


class _Paths:
    """Polylines laid end to end on one arc-length axis (1 m apart), so that the positions of
    all movers are one vectorised interpolation."""

    def __init__(self, polylines: list[np.ndarray]):
        starts, cums, pts = [], [], []
        at = 0.0
        for p in polylines:
            cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
            starts.append(at)
            cums.append(at + cum)
            pts.append(p)
            at += cum[-1] + 1.0
        self.start = np.asarray(starts)
        self.length = np.array([c[-1] - s for c, s in zip(cums, starts)])
        self.cum = np.concatenate(cums) if cums else np.zeros(0)
        self.xy = np.concatenate(pts) if pts else np.zeros((0, 2))

    def at(self, path: np.ndarray, s: np.ndarray):
        """Positions (m, 2) and headings (m,) at arc lengths s (m,) along paths (m,)."""
        g = self.start[path] + np.clip(s, 0.0, self.length[path] - 1e-6)
        i = np.clip(np.searchsorted(self.cum, g, side="right") - 1, 0, len(self.cum) - 2)
        d = self.xy[i + 1] - self.xy[i]
        seg = np.maximum(self.cum[i + 1] - self.cum[i], 1e-9)
        xy = self.xy[i] + d * ((g - self.cum[i]) / seg)[:, None]
        return xy, np.arctan2(d[:, 1], d[:, 0])


class Traffic:
    """The movers of one drive through ``town`` (the drive's town-frame ``poses`` at ``times``
    decide which lanes are its own and where the leading car goes); ``seed`` draws which traffic
    (0: the town's own, the same for every drive of the town at the same moments)."""

    def __init__(self, town: Town, poses: np.ndarray, times: np.ndarray, seed: int = 0):
        # seed 0: the town's own traffic; another: another day's on the same streets
        rng = np.random.default_rng([town.seed, *TRAFFIC_STREAM, *([seed] if seed else [])])
        self.ground = town.ground
        self.raster, self.road = town.raster, town.road
        ego_xy = poses[:, :2, 3]
        ego_yaw = np.arctan2(poses[:, 1, 0], poses[:, 0, 0])
        ego_tree = cKDTree(ego_xy)

        polylines, kind, path, s0, speed, period = [], [], [], [], [], []

        def add_path(points, k, spacing, speeds, per_path_speed):
            cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
            if cum[-1] < 20.0:
                return
            p = len(polylines)
            polylines.append(points)
            P = cum[-1] + rng.uniform(30.0, 80.0)  # the unseen stretch before it starts over
            u = rng.uniform(0.0, spacing[1])
            v_path = rng.uniform(*speeds)
            while u < P:
                kind.append(k)
                path.append(p)
                s0.append(u)
                speed.append(v_path if per_path_speed else rng.uniform(*speeds))
                period.append(P)
                u += rng.uniform(*spacing)

        def drives_it(points):
            """The drive uses this lane in its direction (for 3 or more 4-m samples)."""
            cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
            s = np.arange(0.0, cum[-1], 4.0)
            q = np.stack([np.interp(s, cum, points[:, 0]), np.interp(s, cum, points[:, 1])], axis=1)
            heading = np.arctan2(*np.gradient(q, axis=0).T[::-1]) if len(q) > 1 else np.zeros(len(q))
            d, j = ego_tree.query(q)
            same = (d < 1.5) & (np.cos(heading - ego_yaw[j]) > 0.7)
            return int(same.sum()) >= 3

        for st in town.streets:
            hw, parking = st.half_width, st.parking
            lane = min(LANE_OFFSET, hw - (2.1 if parking else 0.3) - 0.95)
            bike = hw - (2.4 if parking else 0.7)
            walk = hw + 0.7 * st.sidewalk
            for points in (st.points, st.points[::-1]):
                points = np.asarray(points, float)
                if len(points) < 2:
                    continue
                lane_pts = _offset_polyline(points, lane)
                if not drives_it(lane_pts):
                    add_path(lane_pts, CAR, (20.0, 150.0), (8.0, 13.0), True)
                if bike - 0.3 >= lane + 0.95 + 0.4:  # room beside a car in the lane
                    add_path(_offset_polyline(points, bike), CYCLIST, (150.0, 400.0), (3.5, 6.0), True)
                add_path(_offset_polyline(points, walk), PEDESTRIAN, (60.0, 150.0), (1.0, 1.6), False)

        self.paths = _Paths(polylines)
        self.kind = np.asarray(kind, np.int64)
        self.path = np.asarray(path, np.int64)
        self.s0 = np.asarray(s0, float)
        self.speed = np.asarray(speed, float)
        self.period = np.asarray(period, float)
        m = len(self.kind)
        # Sizes: cars 3.9–4.8 × 1.7–1.9 m, people 0.9–1.1 times a 1.72 m adult.
        self.length = rng.uniform(3.9, 4.8, m)
        self.width = rng.uniform(1.7, 1.9, m)
        self.body_h = rng.uniform(0.65, 0.85, m)
        self.cabin_h = rng.uniform(0.45, 0.6, m)
        self.scale = rng.uniform(0.9, 1.1, m)
        self.refl = rng.uniform(0.1, 0.75, m)

        # The leading car: the drive's own path, LEADER_HEADWAY s later and LEADER_GAP m ahead.
        step = np.linalg.norm(np.diff(ego_xy, axis=0), axis=1)
        self.ego_s = np.concatenate([[0.0], np.cumsum(step)])
        keep = np.concatenate([[True], step > 1e-3])
        self.ego_path_s, self.ego_path_xy = self.ego_s[keep], ego_xy[keep]
        self.ego_times = np.asarray(times, float)
        self.leader_windows = self._leader_windows(
            rng, town.plan.junctions if town.plan is not None else np.zeros((0, 2))
        )
        self.leader_size = (
            rng.uniform(4.2, 4.8),
            rng.uniform(1.75, 1.9),
            rng.uniform(0.7, 0.85),
            0.55,
            rng.uniform(0.1, 0.75),
        )

    # ----------------------------------------------------------------------------- the leader
    def _leader_s(self, t):
        s = np.interp(np.asarray(t, float) + LEADER_HEADWAY, self.ego_times, self.ego_s) + LEADER_GAP
        return s, s <= self.ego_path_s[-1]

    def _leader_windows(self, rng, junctions) -> list[tuple[float, float]]:
        t_end = float(self.ego_times[-1])
        times = self.ego_times
        s, valid = self._leader_s(times)
        xy = np.stack([np.interp(s, self.ego_path_s, self.ego_path_xy[:, k]) for k in range(2)], axis=1)
        near = (cKDTree(junctions).query(xy)[0] < 12.0) & valid if len(junctions) else np.zeros(len(times), bool)

        def snap(t):
            """The time nearest ``t`` (within 10 s) at which the leader is near a junction."""
            close = np.flatnonzero(near & (np.abs(times - t) <= 10.0))
            return float(times[close[np.argmin(np.abs(times[close] - t))]]) if len(close) else t

        windows = []
        t = rng.uniform(5.0, 30.0)
        while t < t_end:
            duration = rng.uniform(15.0, 45.0)
            a, b = snap(t), snap(t + duration)
            if b > a:
                windows.append((a, b))
            t = max(b, t + duration) + rng.uniform(20.0, 60.0)
        return windows

    def _leader_at(self, t: float):
        if not any(a <= t <= b for a, b in self.leader_windows):
            return None
        s, valid = self._leader_s(t)
        if not valid:
            return None
        xy = np.array([np.interp(s, self.ego_path_s, self.ego_path_xy[:, k]) for k in range(2)])
        ahead = np.array([np.interp(s + 1.0, self.ego_path_s, self.ego_path_xy[:, k]) for k in range(2)])
        behind = np.array([np.interp(s - 1.0, self.ego_path_s, self.ego_path_xy[:, k]) for k in range(2)])
        d = ahead - behind
        return xy, math.atan2(d[1], d[0])

    # ----------------------------------------------------------------------------- at a time
    def agents_at(self, t: float, sensor_xy=None, reach: float = np.inf) -> dict:
        """The movers present at time ``t`` (s from the first scan), within ``reach`` m of
        ``sensor_xy`` and not within the keep-out distance of it: kind (m,), xy (m, 2),
        yaw (m,) and their row index ``index`` (m,) (−1 for the leader)."""
        s = np.mod(self.s0 + self.speed * t, self.period)
        present = s <= self.paths.length[self.path]
        idx = np.flatnonzero(present)
        xy, yaw = self.paths.at(self.path[idx], s[idx])
        kind = self.kind[idx]
        leader = self._leader_at(t)
        if leader is not None:
            xy = np.concatenate([xy, leader[0][None]])
            yaw = np.concatenate([yaw, [leader[1]]])
            kind = np.concatenate([kind, [LEADER]])
            idx = np.concatenate([idx, [-1]])
        if sensor_xy is not None:
            d = np.hypot(*(xy - np.asarray(sensor_xy, float)[:2]).T)
            keep = (d <= reach) & (d >= _KEEP_OUT[kind])
            xy, yaw, kind, idx = xy[keep], yaw[keep], kind[keep], idx[keep]
        return dict(kind=kind, xy=xy, yaw=yaw, index=idx)

    def boxes_at(self, t: float, sensor_xy=None, reach: float = np.inf) -> np.ndarray:
        """Upright boxes (k, 8) (cx, cy, yaw, length, width, z0, z1, reflectivity), town frame,
        of the movers present at ``t`` (see :meth:`agents_at`)."""
        a = self.agents_at(t, sensor_xy, reach)
        kind, xy, yaw, idx = a["kind"], a["xy"], a["yaw"], a["index"]
        if len(kind) == 0:
            return np.zeros((0, 8))
        z = self.ground(xy[:, 0], xy[:, 1])
        on_walk = ~self.raster.lookup(self.road, xy[:, 0], xy[:, 1], outside=1).astype(bool)
        z = z + CURB * (on_walk & (kind == PEDESTRIAN))
        lead = np.asarray(self.leader_size)
        j = np.maximum(idx, 0)
        is_leader = kind == LEADER
        L = np.where(is_leader, lead[0], self.length[j])
        W = np.where(is_leader, lead[1], self.width[j])
        bh = np.where(is_leader, lead[2], self.body_h[j])
        ch = np.where(is_leader, lead[3], self.cabin_h[j])
        refl = np.where(is_leader, lead[4], self.refl[j])
        h = np.where(is_leader, 1.0, self.scale[j])
        c, s = np.cos(yaw), np.sin(yaw)
        rows = []

        def box(mask, du, dv, length, width, z0, z1, r):
            if not np.any(mask):
                return
            x = xy[mask, 0] + du * c[mask] - dv * s[mask]
            y = xy[mask, 1] + du * s[mask] + dv * c[mask]
            n = int(mask.sum())
            rows.append(
                np.stack(
                    [
                        x,
                        y,
                        yaw[mask],
                        np.broadcast_to(length, n),
                        np.broadcast_to(width, n),
                        z0,
                        z1,
                        np.broadcast_to(r, n),
                    ],
                    axis=1,
                )
            )

        car = (kind == CAR) | is_leader
        if np.any(car):
            zc, Lc, Wc, bc, cc = z[car], L[car], W[car], bh[car], ch[car]
            box(car, 0.0, 0.0, Lc, Wc, zc + 0.3, zc + 0.3 + bc, refl[car])  # body
            box(car, -0.15 * Lc, 0.0, 0.55 * Lc, Wc - 0.15, zc + 0.3 + bc, zc + 0.3 + bc + cc, 0.08)  # cabin
            for u in (-1, 1):
                for v in (-1, 1):
                    box(car, u * (Lc / 2 - 0.85), v * (Wc / 2 - 0.12), 0.62, 0.22, zc, zc + 0.62, 0.05)
        bike = kind == CYCLIST
        if np.any(bike):
            zb, hb = z[bike], h[bike]
            box(bike, 0.0, 0.0, 1.7, 0.12, zb + 0.05, zb + 1.0, 0.35)  # bicycle
            box(bike, -0.1, 0.0, 0.55, 0.45, zb + 1.0, zb + 1.75 * hb, refl[bike])  # rider
        walker = kind == PEDESTRIAN
        if np.any(walker):
            zp, hp, rp = z[walker], h[walker], refl[walker]
            box(walker, 0.0, 0.0, 0.3, 0.4, zp, zp + 0.85 * hp, rp)  # legs
            box(walker, 0.0, 0.0, 0.3, 0.5, zp + 0.85 * hp, zp + 1.45 * hp, rp)  # torso
            box(walker, 0.0, 0.0, 0.22, 0.2, zp + 1.45 * hp, zp + 1.72 * hp, 0.3)  # head
        return np.concatenate(rows) if rows else np.zeros((0, 8))

    def movers_at(self, t: float, sensor_xy, reach: float) -> Movers | None:
        """The traffic at ``t`` within ``reach`` m of the sensor, for one scan (None if none)."""
        rows = self.boxes_at(t, sensor_xy, reach)
        if not len(rows):
            return None
        return Movers(
            [boxes_part("traffic", rows)], rows[:, :2], 0.5 * np.hypot(rows[:, 3], rows[:, 4]), rows[:, 5], rows[:, 6]
        )

"""The live browser viewer (viser): the prior map, the particle filter's state after every scan,
the last scan-to-map match, and the controls to drive and perturb the localizer.

Threads. A :class:`~lidarloc.app.player.Player` thread calls ``localizer.step()``; each snapshot
it returns is recorded in a :class:`History` (cheap appends) and left in a one-slot mailbox. A
display thread wakes up, takes the newest snapshot (skipping any it had no time for) and updates
the scene and panels. GUI callbacks run on viser's worker threads; they only flip player flags or
call the localizer's thread-safe setters. Nothing here holds a lock the localizer waits on, so the
display never slows the filter down.

Scene state is shared by all browser tabs (one scene, sent once to each client: the map is static
and never re-sent per scan); the camera and its controls are per tab.
"""

from __future__ import annotations

import copy
import inspect
import math
import sys
import threading
import time
import traceback
import webbrowser
from dataclasses import dataclass, field

import numpy as np
import viser
import viser.uplot as uplot

from lidarloc.core.config import ANGULAR_STATE, DEG, STATE_NAMES
from lidarloc.core.errors import LidarlocError
from lidarloc.core.mapping import VoxelAccumulator
from lidarloc.core.snapshot import Event, Snapshot

from .player import Player

# ------------------------------------------------------------------------------------------ look
# Dark background: the paper's colour code (green scan, red particles) reads best on it, and the
# height ramp of the map avoids pure green and red so neither gets lost in the map.
SCAN_COLOR = (40, 255, 40)
S2M_ACCEPTED_COLOR = (255, 60, 255)
S2M_REJECTED_COLOR = (150, 150, 150)     # grey: discarded (and unlike the BEV yellow)
BEST_COLOR = (0, 230, 255)
ELLIPSE_COLOR = (255, 70, 70)
GT_COLOR = (235, 235, 235)
EST_COLOR = (255, 150, 30)
PARTICLE_LOW = np.array([110, 30, 40], np.float32)     # weight ≈ 0
PARTICLE_HIGH = np.array([255, 70, 50], np.float32)    # the highest weight
BEV_COLOR = (255, 225, 90)
RESET_COLOR = (255, 255, 255)

DISPLAY_VOXEL = 0.5          # m, first try for the displayed map's voxel size …
DISPLAY_MAX_POINTS = 1_500_000   # … grown until the map fits in this many points
MIN_DRAW_INTERVAL = 1 / 30   # s, the display refreshes at most this often
PLOT_INTERVAL = 0.5          # s, the plots at most this often (they resend whole series)
PLOT_MAX_POINTS = 1500       # longer series are decimated for the plots
TRAJ_CHUNK = 256             # points per trajectory chunk (finished chunks are never re-sent)
EVENTS_SHOWN = 6

SPEEDS = ("1", "2", "5", "10", "20", "50", "max")        # scans per second in replay
SHIFT = "shift"


def _height_lut() -> np.ndarray:
    """256-entry RGB ramp for map heights: slate blue (low) → light blue → warm white (high)."""
    stops = np.array([[62, 80, 135], [80, 120, 190], [145, 180, 228], [245, 235, 215]], np.float32)
    t = np.linspace(0, 1, 256)
    pos = t * (len(stops) - 1)
    i = np.minimum(pos.astype(int), len(stops) - 2)
    f = (pos - i)[:, None]
    return ((1 - f) * stops[i] + f * stops[i + 1]).astype(np.uint8)


HEIGHT_LUT = _height_lut()


def height_colors(z: np.ndarray) -> np.ndarray:
    """(N,) heights → (N, 3) uint8, the 2nd–98th percentile spread over the ramp."""
    if len(z) == 0:
        return np.zeros((0, 3), np.uint8)
    lo, hi = np.percentile(z, [2, 98])
    t = np.clip((z - lo) / max(hi - lo, 1e-6), 0, 1)
    return HEIGHT_LUT[(t * 255).astype(np.intp)]


def downsample_for_display(points: np.ndarray, voxel: float = DISPLAY_VOXEL,
                           max_points: int = DISPLAY_MAX_POINTS) -> tuple[np.ndarray, float]:
    """One centroid per voxel, the voxel grown by 1.5× until at most ``max_points`` remain.
    Returns (points float32, voxel used)."""
    if len(points) == 0:
        return np.zeros((0, 3), np.float32), voxel
    while True:
        acc = VoxelAccumulator(voxel, capacity=1 << max(10, int(np.ceil(np.log2(2 * len(points) + 1)))))
        acc.add(points)
        out = acc.points()
        if len(out) <= max_points:
            return out, voxel
        voxel *= 1.5


def shorten(text: str, limit: int = 70) -> str:
    """One line of at most ``limit`` characters (the panel and labels are narrow; the localizer's
    event log keeps the full text)."""
    text = " ".join(str(text).split())
    return text if len(text) <= limit else text[: limit - 1].rstrip() + "…"


def quat_wxyz_from_matrix(R: np.ndarray) -> np.ndarray:
    return viser.transforms.SO3.from_matrix(np.asarray(R, float)).wxyz


# ------------------------------------------------------------------------------------ geometry
class GroundHeight:
    """Lowest map height per 2D cell, so a click on the screen lands on the road, not on a roof."""

    def __init__(self, points: np.ndarray, cell: float = 2.0, max_cells: int = 4_000_000):
        self.z_default = float(np.percentile(points[:, 2], 5)) if len(points) else 0.0
        lo = points[:, :2].min(axis=0) if len(points) else np.zeros(2)
        hi = points[:, :2].max(axis=0) if len(points) else np.ones(2)
        while np.prod(np.ceil((hi - lo) / cell) + 1) > max_cells:
            cell *= 2
        self.cell, self.origin = cell, lo
        shape = (np.ceil((hi - lo) / cell) + 1).astype(int)
        self.grid = np.full(shape, np.inf, np.float32)
        if len(points):
            idx = ((points[:, :2] - lo) / cell).astype(int)
            np.minimum.at(self.grid, (idx[:, 0], idx[:, 1]), points[:, 2])

    def at(self, x: float, y: float) -> float:
        i = int((x - self.origin[0]) // self.cell)
        j = int((y - self.origin[1]) // self.cell)
        if 0 <= i < self.grid.shape[0] and 0 <= j < self.grid.shape[1] and np.isfinite(self.grid[i, j]):
            return float(self.grid[i, j])
        return self.z_default

    def hit(self, origin, direction) -> np.ndarray | None:
        """Where a ray meets the ground (two passes: a flat ground, then the local height there)."""
        o, d = np.asarray(origin, float), np.asarray(direction, float)
        if abs(d[2]) < 1e-9:
            return None
        z = self.z_default
        p = None
        for _ in range(2):
            s = (z - o[2]) / d[2]
            if s <= 0:
                return None
            p = o + s * d
            z = self.at(p[0], p[1])
        return p


def screen_ray(camera, u: float, v: float) -> tuple[np.ndarray, np.ndarray]:
    """World ray through the normalised screen point (u, v) ∈ [0, 1]², (0, 0) top left, of a
    viser camera (OpenCV convention: x right, y down, z forward; fov is vertical)."""
    R = viser.transforms.SO3(np.asarray(camera.wxyz)).as_matrix()
    t = math.tan(camera.fov / 2.0)
    d_cam = np.array([(2 * u - 1) * t * camera.aspect, (2 * v - 1) * t, 1.0])
    d = R @ d_cam
    return np.asarray(camera.position, float), d / np.linalg.norm(d)


# ------------------------------------------------------------------------------------- history
class History:
    """Per-scan values of the current run (cleared on restart), written by the player thread and
    read by the display thread; appends and whole-array reads happen under one short lock."""

    def __init__(self, capacity: int = 1024):
        self._lock = threading.Lock()
        self.epoch = 0
        self._cap = capacity
        self._alloc(capacity)
        self.events: list[Event] = []
        self.version = 0

    def _alloc(self, cap: int) -> None:
        self.n = 0
        self.scan = np.zeros(cap, np.int64)
        self.std = np.zeros(cap)            # max(std_x, std_y), m
        self.error = np.full(cap, np.nan)   # m, NaN without ground truth
        self.pf_ms = np.zeros(cap)
        self.s2m_ms = np.zeros(cap)         # wall time of the last landed match (held between landings)
        self.est = np.zeros((cap, 3), np.float32)
        self.gt = np.full((cap, 3), np.nan, np.float32)
        self._last_s2m = None

    def _grow(self) -> None:
        cap = 2 * len(self.scan)
        for name in ("scan", "std", "error", "pf_ms", "s2m_ms", "est", "gt"):
            old = getattr(self, name)
            new = np.full((cap,) + old.shape[1:], np.nan if name in ("error", "gt") else 0, old.dtype)
            new[: self.n] = old[: self.n]
            setattr(self, name, new)

    def clear(self) -> None:
        with self._lock:
            self.epoch += 1
            self._alloc(self._cap)
            self.events = []
            self.version += 1

    def record(self, snap: Snapshot) -> None:
        with self._lock:
            k = snap.scan_index
            if self.n and (k < self.scan[self.n - 1] or k < 0):
                # the scan index went back: a restart; the old run's curves end here
                self.epoch += 1
                self._alloc(self._cap)
                self.events = []
            self._merge_events(snap.events)
            if k >= 0:
                if self.n and self.scan[self.n - 1] == k:
                    i = self.n - 1          # same scan again (e.g. the snapshot after a reset)
                else:
                    if self.n == len(self.scan):
                        self._grow()
                    i = self.n
                    self.n += 1
                self.scan[i] = k
                std = np.asarray(snap.std_xyz, float)
                self.std[i] = float(max(std[0], std[1]))
                self.error[i] = np.nan if snap.error_m is None else float(snap.error_m)
                self.pf_ms[i] = float(snap.pf_ms)
                if snap.s2m is not None:
                    self._last_s2m = snap.s2m
                self.s2m_ms[i] = 0.0 if self._last_s2m is None else float(self._last_s2m.ms)
                self.est[i] = np.asarray(snap.mean_pose)[:3, 3]
                if snap.gt_pose is not None:
                    self.gt[i] = np.asarray(snap.gt_pose)[:3, 3]
            self.version += 1

    def _merge_events(self, events: tuple) -> None:
        """Snapshots carry a rolling window of recent events; append only the ones not seen yet
        (the longest prefix of the window that equals the tail of what we have is old)."""
        events = tuple(events)
        if not events:
            return
        mine = self.events[-len(events):]
        for overlap in range(min(len(mine), len(events)), -1, -1):
            if overlap == 0 or tuple(mine[-overlap:]) == events[:overlap]:
                break
        self.events.extend(events[overlap:])
        del self.events[:-200]

    def arrays(self) -> dict:
        with self._lock:
            n = self.n
            return {"epoch": self.epoch, "version": self.version, "scan": self.scan[:n].copy(),
                    "std": self.std[:n].copy(), "error": self.error[:n].copy(), "pf_ms": self.pf_ms[:n].copy(),
                    "s2m_ms": self.s2m_ms[:n].copy(), "events": list(self.events[-EVENTS_SHOWN:])}

    def trajectories(self) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
        with self._lock:
            n = self.n
            return self.epoch, self.scan[:n].copy(), self.est[:n].copy(), self.gt[:n].copy()


class ChunkedPolyline:
    """A growing polyline sent in chunks: a finished chunk is sent once and left alone, only the
    last one is updated, so the per-scan cost does not grow with the length of the drive."""

    def __init__(self, scene, name: str, color, thickness: float = 2.0):
        self.scene, self.name, self.color, self.thickness = scene, name, color, thickness
        self.epoch = None
        self.handles: list = []
        self.visible = True

    def _clear(self) -> None:
        for h in self.handles:
            h.remove()
        self.handles = []

    def set_visible(self, visible: bool) -> None:
        self.visible = visible
        for h in self.handles:
            h.visible = visible

    def sync(self, epoch: int, pts: np.ndarray, connected: np.ndarray) -> None:
        """``pts`` (n, 3) so far; ``connected[i]`` says whether point i joins point i − 1.
        Chunk c holds the segments between points c·C … (c+1)·C (consecutive chunks share a point)."""
        if epoch != self.epoch:
            self._clear()
            self.epoch = epoch
        n = len(pts)
        if n < 2:
            return
        last = (n - 2) // TRAJ_CHUNK                  # chunk of the newest segment
        first = max(len(self.handles) - 1, 0)         # the open chunk: finished ones stay as sent
        for c in range(first, last + 1):
            lo, hi = c * TRAJ_CHUNK, min((c + 1) * TRAJ_CHUNK, n - 1)
            segs = self._segments(pts, connected, lo, hi)
            if segs is None:   # nothing connected here (e.g. no ground truth): a zero-length stand-in
                segs = np.repeat(np.nan_to_num(pts[lo:lo + 1]).astype(np.float32)[:, None], 2, axis=1)
            if c < len(self.handles):
                self.handles[c].points = segs
            else:
                self.handles.append(self.scene.add_line_segments(
                    f"{self.name}/c{c}", segs, self.color, thickness=self.thickness, thickness_units="screen",
                    visible=self.visible))

    @staticmethod
    def _segments(pts, connected, lo, hi):
        """Segments between points lo…hi (inclusive) that are connected and finite, or None."""
        if hi <= lo:
            return None
        a, b = pts[lo:hi], pts[lo + 1: hi + 1]
        keep = connected[lo + 1: hi + 1] & np.isfinite(a).all(axis=1) & np.isfinite(b).all(axis=1)
        if not keep.any():
            return None
        return np.stack([a[keep], b[keep]], axis=1).astype(np.float32)


# --------------------------------------------------------------------------------------- scene
@dataclass
class Layers:
    map: bool = True
    map_bev: bool = False
    bev_level: bool = False
    particles: bool = True
    scan: bool = True
    s2m: bool = True
    trajectories: bool = True
    ellipse: bool = True


class SceneView:
    """Every 3D node the viewer shows, on the server-wide scene (shared by all tabs).

    The display thread draws while GUI callbacks (layer toggles, BEV level) run on viser's
    worker threads: one lock keeps a node from being replaced by one while the other updates it.
    """

    def __init__(self, scene):
        self.scene = scene
        self._lock = threading.RLock()
        self.layers = Layers()
        self.ground: GroundHeight | None = None
        self.map_center = np.zeros(3)
        self.map_extent = 100.0
        self._map = self._map_bev = self._bev_image = None
        self._pyramid = None
        self._bev_level_shown = None
        self._particles = self._particle_dots = self._best = self._ellipse = self._scan = None
        self._s2m_scan = self._s2m_box = self._s2m_label = None
        self._s2m_shown = None
        self._est_frame = None
        self._reset_hint = None
        self._reset_hint_scan: int | None = None
        self.gt_line = ChunkedPolyline(scene, "/trajectory/ground_truth", GT_COLOR, 2.0)
        self.est_line = ChunkedPolyline(scene, "/trajectory/estimate", EST_COLOR, 2.0)
        self.display_voxel = DISPLAY_VOXEL

    # -------------------------------------------------------------------- static content
    def set_map(self, prior_map, voxel: float = DISPLAY_VOXEL, max_points: int = DISPLAY_MAX_POINTS) -> None:
        """The map, down-sampled for display and coloured by height; sent once (static scene state).
        float32 positions: viser's default float16 is off by ~0.25 m a few hundred metres out."""
        with self._lock:
            self._set_map(prior_map, voxel, max_points)

    def _set_map(self, prior_map, voxel: float, max_points: int) -> None:
        pts, self.display_voxel = downsample_for_display(prior_map.points, max(voxel, prior_map.voxel_size), max_points)
        self._map = self.scene.add_point_cloud(
            "/map/full", pts, height_colors(pts[:, 2]), point_size=self.display_voxel * 0.8, precision="float32",
            point_shape="square", point_shading="flat", visible=self.layers.map)
        bev, _ = downsample_for_display(prior_map.points_bev, self.display_voxel, max_points)
        self._map_bev = self.scene.add_point_cloud(
            "/map/road_removed", bev, height_colors(bev[:, 2]), point_size=self.display_voxel * 0.8,
            precision="float32", point_shape="square", point_shading="flat", visible=self.layers.map_bev)
        self.ground = GroundHeight(pts)
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        self.map_center = (lo + hi) / 2.0
        self.map_center[2] = self.ground.z_default
        self.map_extent = float(max(hi[0] - lo[0], hi[1] - lo[1], 20.0))

    def set_pyramid(self, pyramid, level: int) -> None:
        """Show one BEV pyramid level as a flat image on the ground (cells with map points in
        yellow, the paper's colour, brighter for larger values; empty cells transparent)."""
        if pyramid is None:
            return
        with self._lock:
            self._set_pyramid(pyramid, level)

    def _set_pyramid(self, pyramid, level: int) -> None:
        level = int(np.clip(level, 0, len(pyramid.levels) - 1))
        if pyramid is self._pyramid and level == self._bev_level_shown:
            return
        grid = np.asarray(pyramid.levels[level], np.float32)        # [ix, iy]
        cell = pyramid.resolution * 2 ** level
        vmax = float(grid.max()) if grid.size and grid.max() > 0 else 1.0
        value = np.clip(grid / vmax, 0, 1)
        # image rows run top (max y) to bottom, columns along +x
        value = value.T[::-1]
        rgba = np.zeros(value.shape + (4,), np.uint8)
        rgba[..., :3] = BEV_COLOR
        rgba[..., 3] = np.where(value > 0, (90 + 140 * np.sqrt(value)).astype(np.uint8), 0)
        nx, ny = grid.shape
        x0, y0 = (float(v) for v in pyramid.origin)
        w, h = nx * cell, ny * cell
        z = (self.ground.z_default if self.ground is not None else 0.0) - 0.3
        if self._bev_image is not None:
            self._bev_image.remove()
        # Nearest-neighbour look: upsample small levels so the image filter keeps the cells crisp.
        rep = max(1, int(np.ceil(256 / max(value.shape))))
        if rep > 1:
            rgba = np.repeat(np.repeat(rgba, rep, axis=0), rep, axis=1)
        self._bev_image = self.scene.add_image(
            "/map/bev_level", rgba, w, h, format="png", position=(x0 + w / 2, y0 + h / 2, z),
            cast_shadow=False, receive_shadow=False, visible=self.layers.bev_level)
        self._pyramid, self._bev_level_shown = pyramid, level

    def set_layer(self, name: str, visible: bool) -> None:
        with self._lock:
            self._set_layer(name, visible)

    def _set_layer(self, name: str, visible: bool) -> None:
        setattr(self.layers, name, visible)
        nodes = {"map": [self._map], "map_bev": [self._map_bev], "bev_level": [self._bev_image],
                 "particles": [self._particles, self._particle_dots, self._best],
                 "scan": [self._scan, self._est_frame], "s2m": [self._s2m_scan, self._s2m_box, self._s2m_label],
                 "ellipse": [self._ellipse]}.get(name, [])
        for node in nodes:
            if node is not None:
                node.visible = visible
        if name == "trajectories":
            self.gt_line.set_visible(visible)
            self.est_line.set_visible(visible)

    # -------------------------------------------------------------------- per snapshot
    def draw(self, snap: Snapshot, history: History) -> None:
        with self._lock:
            self._draw(snap, history)

    def show_reset_area(self, scan_index: int, center=None, region=None, radius: float = 6.0) -> None:
        """Outline where particles were just re-drawn (a circle round a point, or a rectangle),
        until a scan after ``scan_index`` shows the particles themselves."""
        with self._lock:
            z = self.ground.z_default if self.ground is not None else 0.0
            if region is not None:
                x0, y0, x1, y1 = region
                c = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], np.float32)
            else:
                th = np.linspace(0, 2 * np.pi, 49)[:-1]
                c = np.stack([center[0] + radius * np.cos(th), center[1] + radius * np.sin(th),
                              np.full_like(th, center[2] if len(center) > 2 else z)], axis=1).astype(np.float32)
            segs = np.stack([c, np.roll(c, -1, axis=0)], axis=1)
            if self._reset_hint is None:
                self._reset_hint = self.scene.add_line_segments("/reset_area", segs, RESET_COLOR, thickness=3.0,
                                                                thickness_units="screen")
            else:
                self._reset_hint.points = segs
                self._reset_hint.visible = True
            self._reset_hint_scan = scan_index

    def _draw(self, snap: Snapshot, history: History) -> None:
        if self._reset_hint_scan is not None and snap.scan_index > self._reset_hint_scan:
            self._reset_hint.visible = False
            self._reset_hint_scan = None
        self._draw_particles(snap)
        self._draw_ellipse(snap)
        self._draw_scan(snap)
        self._draw_s2m(snap)
        self._draw_trajectories(history)

    def _node(self, attr: str, make, update, visible: bool):
        h = getattr(self, attr)
        if h is None:
            setattr(self, attr, make(visible))
        else:
            update(h)

    def _draw_particles(self, snap: Snapshot) -> None:
        P = np.asarray(snap.particles)
        w = np.asarray(snap.weights, np.float64)
        if len(P) == 0:
            return
        w_rel = (w / w.max()) if w.max() > 0 else np.ones_like(w)
        xyz = P[:, :3].astype(np.float32)
        yaw = P[:, 3]
        head = np.stack([np.cos(yaw), np.sin(yaw), np.zeros_like(yaw)], axis=1).astype(np.float32)
        length = (1.5 + 3.0 * w_rel).astype(np.float32)[:, None]           # longer = heavier
        tip = xyz + head * length
        segs = np.stack([xyz, tip], axis=1)
        c = (PARTICLE_LOW + (PARTICLE_HIGH - PARTICLE_LOW) * w_rel[:, None].astype(np.float32)).astype(np.uint8)
        colors = np.repeat(c[:, None, :], 2, axis=1)
        vis = self.layers.particles
        self._node("_particles",
                   lambda v: self.scene.add_line_segments("/particles/headings", segs, colors, thickness=2.0,
                                                          thickness_units="screen", visible=v),
                   lambda h: self._set(h, points=segs, colors=colors), vis)
        dots_c = c
        self._node("_particle_dots",
                   lambda v: self.scene.add_point_cloud("/particles/positions", xyz, dots_c, point_size=0.6,
                                                        precision="float32", point_shape="circle",
                                                        point_shading="flat", visible=v),
                   lambda h: self._set(h, points=xyz, colors=dots_c), vis)
        # the highest-weight particle: a big cyan arrow (shaft and two barbs)
        b = int(snap.best_index) if 0 <= snap.best_index < len(P) else int(np.argmax(w))
        p, hd = xyz[b], head[b]
        side = np.array([-hd[1], hd[0], 0], np.float32)
        L = 8.0
        t = p + hd * L
        best = np.array([[p, t], [t, t - hd * 2.5 + side * 1.5], [t, t - hd * 2.5 - side * 1.5]], np.float32)
        self._node("_best",
                   lambda v: self.scene.add_line_segments("/particles/best", best, BEST_COLOR, thickness=4.0,
                                                          thickness_units="screen", visible=v),
                   lambda h: self._set(h, points=best), vis)

    def _draw_ellipse(self, snap: Snapshot) -> None:
        a, bb, ang = (float(v) for v in snap.ellipse_xy)
        center = np.asarray(snap.mean_pose)[:3, 3]
        if not all(math.isfinite(v) for v in (a, bb, ang)) or not np.isfinite(center).all():
            return
        n = 72
        th = np.linspace(0, 2 * np.pi, n + 1)
        ca, sa = math.cos(ang), math.sin(ang)
        ex, ey = a * np.cos(th), bb * np.sin(th)
        pts = np.stack([center[0] + ca * ex - sa * ey, center[1] + sa * ex + ca * ey,
                        np.full_like(th, center[2])], axis=1).astype(np.float32)
        segs = np.stack([pts[:-1], pts[1:]], axis=1)[::2]     # every other piece: the paper's dotted circle
        self._node("_ellipse",
                   lambda v: self.scene.add_line_segments("/estimate/ellipse_2sigma", segs, ELLIPSE_COLOR,
                                                          thickness=2.5, thickness_units="screen", visible=v),
                   lambda h: self._set(h, points=segs), self.layers.ellipse)

    def _draw_scan(self, snap: Snapshot) -> None:
        pts = np.asarray(snap.scan_world, np.float32).reshape(-1, 3)
        T = np.asarray(snap.mean_pose, float)
        if len(pts) == 0:
            if self._scan is not None:
                self._scan.visible = False
        else:
            self._node("_scan",
                       lambda v: self.scene.add_point_cloud("/estimate/scan", pts, SCAN_COLOR, point_size=0.25,
                                                            precision="float32", point_shading="flat", visible=v),
                       lambda h: self._set(h, points=pts, visible=self.layers.scan), self.layers.scan)
        if np.isfinite(T).all():
            wxyz, pos = quat_wxyz_from_matrix(T[:3, :3]), T[:3, 3]
            if self._est_frame is None:
                self._est_frame = self.scene.add_frame("/estimate/pose", wxyz=wxyz, position=pos, axes_length=3.0,
                                                       axes_radius=0.15, visible=self.layers.scan)
            else:
                self._est_frame.wxyz, self._est_frame.position = wxyz, pos

    def _draw_s2m(self, snap: Snapshot) -> None:
        s = snap.s2m
        if s is None or s is self._s2m_shown:
            return
        self._s2m_shown = s
        color = S2M_ACCEPTED_COLOR if s.accepted else S2M_REJECTED_COLOR
        vis = self.layers.s2m
        pts = np.asarray(s.scan_world, np.float32).reshape(-1, 3)
        if len(pts):
            if self._s2m_scan is not None:
                self._s2m_scan.remove()
            self._s2m_scan = self.scene.add_point_cloud("/s2m/scan", pts, color, point_size=0.3,
                                                        precision="float32", point_shading="flat", visible=vis)
        x0, y0, x1, y1 = (float(v) for v in s.region)
        z = float(np.asarray(s.pose)[2, 3])
        c = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], np.float32)
        box = np.stack([c, np.roll(c, -1, axis=0)], axis=1)
        if self._s2m_box is None:
            self._s2m_box = self.scene.add_line_segments("/s2m/region", box, color, thickness=2.0,
                                                         thickness_units="screen", visible=vis)
        else:
            self._set(self._s2m_box, points=box, colors=np.asarray(color, np.uint8))
        verdict = "accepted" if s.accepted else "rejected" + (f" ({shorten(s.reason, 60)})" if s.reason else "")
        text = (f"S2M: started at scan {s.started_at}, landed at {s.landed_at}\n{verdict}, "
                f"score {s.score:.0f} (start {s.start_score:.0f}), {s.ms:.0f} ms")
        if self._s2m_label is None:
            self._s2m_label = self.scene.add_label("/s2m/label", text, position=(x0, y1, z + 2.0),
                                                   anchor="bottom-left", visible=vis)
        else:
            self._s2m_label.text = text
            self._s2m_label.position = (x0, y1, z + 2.0)

    def _draw_trajectories(self, history: History) -> None:
        epoch, scans, est, gt = history.trajectories()
        # Ground truth jumps where the vehicle was kidnapped (scan index skips): no line there.
        connected = np.ones(len(scans), bool)
        if len(scans):
            connected[1:] = np.diff(scans) == 1
            connected[0] = False
        self.gt_line.sync(epoch, gt, connected)
        est_connected = np.ones(len(scans), bool)
        if len(scans):
            est_connected[0] = False
        self.est_line.sync(epoch, est, est_connected)

    @staticmethod
    def _set(handle, **props) -> None:
        for k, v in props.items():
            setattr(handle, k, v)


# ---------------------------------------------------------------------------------- parameters
@dataclass(frozen=True)
class Param:
    key: str            # Localizer.set_params keyword
    label: str
    section: str        # Config section …
    attr: str           # … and attribute holding the current value
    scale: float = 1.0  # GUI value = SI value / scale (DEG shows radians as degrees)
    step: float = 0.01
    integer: bool = False
    hint: str = ""


NUMERIC_PARAMS = (
    Param("d_max", "d_max (m)", "pf", "d_max", hint="Distance cap of the likelihood (a larger one than the built table rebuilds it in the background)"),
    Param("sigma", "σ (m)", "pf", "sigma", hint="Likelihood scale"),
    Param("n_particles", "N particles", "pf", "n_particles", step=1, integer=True),
    Param("scan_voxel", "scan voxel (m)", "pf", "scan_voxel", hint="Random point per voxel of each scan"),
    Param("region_x", "L_x (m)", "s2m", "region_x", step=0.5, hint="S2M local search half-width in x"),
    Param("region_y", "L_y (m)", "s2m", "region_y", step=0.5, hint="S2M local search half-width in y"),
    Param("match_resolution", "d_m (m)", "s2m", "match_resolution", step=0.1, hint="S2M match resolution (rebuilds the BEV pyramid)"),
    Param("angle_step", "d_θ (deg)", "s2m", "angle_step", scale=DEG, step=0.1, hint="S2M angular resolution"),
)


def q_units() -> tuple[str, ...]:
    """Display units of the 11 process-noise standard deviations (the paper's units)."""
    units = []
    for name, angular in zip(STATE_NAMES, ANGULAR_STATE):
        rate = name.endswith("_rate") or name == "v"
        if name == "a":
            units.append("m/s²")
        elif angular:
            units.append("deg/s" if rate else "deg")
        else:
            units.append("m/s" if rate else "m")
    return tuple(units)


def q_to_gui(q_std) -> list[float]:
    return [float(q) / DEG if ang else float(q) for q, ang in zip(q_std, ANGULAR_STATE)]


def q_from_gui(values) -> tuple[float, ...]:
    return tuple(float(v) * DEG if ang else float(v) for v, ang in zip(values, ANGULAR_STATE))


def validate_changes(cfg, changes: dict) -> None:
    """Refuse values the localizer cannot use, before calling it: the same rules as the config
    file (Config.validate) applied to a copy with the changes in."""
    section_of = {p.key: (p.section, p.attr) for p in NUMERIC_PARAMS}
    section_of.update({"q_std": ("pf", "q_std"), "s2m_enabled": ("s2m", "enabled"), "clock": ("localize", "clock")})
    for key, value in changes.items():
        if key == "q_std":
            bad = [f"{n}" for n, q in zip(STATE_NAMES, value) if not (math.isfinite(q) and q >= 0)]
            if bad:
                raise LidarlocError(f"Q std of {', '.join(bad)} must be finite and ≥ 0")
        elif isinstance(value, float) and not math.isfinite(value):
            raise LidarlocError(f"{key} must be a finite number")
    trial = copy.deepcopy(cfg)
    for key, value in changes.items():
        section, attr = section_of[key]
        setattr(getattr(trial, section), attr, value)
    trial.validate()


# -------------------------------------------------------------------------------------- viewer
@dataclass
class _ClientState:
    follow: object = None          # per-tab "follow the vehicle" checkbox
    top_down: object = None
    fit: object = None


@dataclass
class Controls:
    """Handles of every control, for the callbacks and for tests that drive them."""

    play: object = None
    step: object = None
    speed: object = None
    clock: object = None
    seed: object = None
    restart: object = None
    reset: object = None
    kidnap_skip: object = None
    kidnap: object = None
    params: dict = field(default_factory=dict)      # set_params key → number handle
    q: list = field(default_factory=list)           # 11 number handles, paper units
    s2m_enabled: object = None
    apply: object = None
    layers: dict = field(default_factory=dict)
    bev_level: object = None


class Viewer:
    """GUI, scene and threads around one Localizer. Use :func:`serve` to start one."""

    def __init__(self, server: viser.ViserServer, *, autoplay: bool = True, speed: str = "10",
                 display_thread: bool = True):
        self.server = server
        self.localizer = None
        self.player: Player | None = None
        self.history = History()
        self.scene = SceneView(server.scene)
        self.controls = Controls()
        self.owns_localizer = False
        self._autoplay = autoplay
        self._initial_speed = speed
        self._latest: Snapshot | None = None
        self._drawn: Snapshot | None = None
        self._wake = threading.Event()
        self._stopping = threading.Event()
        self._ready = threading.Event()
        self._clients: dict[int, _ClientState] = {}
        self._clients_lock = threading.Lock()
        self._build_stage: str | None = "starting"     # Localizer construction stage, None once attached
        self._build_frac: float | None = None
        self._startup_error: str | None = None
        self._message = ""
        self._status_text = ""
        self._plot_version = None
        self._last_plot = 0.0
        self._last_draw = 0.0
        self._applied: dict = {}
        self._syncing = False           # set while the viewer itself writes GUI values
        self._build_gui()
        server.on_client_connect(self._on_connect)
        server.on_client_disconnect(self._on_disconnect)
        server.scene.on_click(modifier=SHIFT)(self._on_shift_click)
        server.scene.on_rect_select(modifier=SHIFT)(self._on_shift_rect)
        # Without the display thread (benchmarks) the owner calls update_display() itself.
        self._display = threading.Thread(target=self._display_loop, name="lidarloc-display", daemon=True)
        if display_thread:
            self._display.start()

    # ============================================================== GUI construction
    def _build_gui(self) -> None:
        gui, c = self.server.gui, self.controls
        gui.configure_theme(dark_mode=True, control_width="medium", show_share_button=False)
        gui.set_panel_label("lidarloc")
        self._progress = gui.add_progress_bar(0.0, animated=True, visible=True)
        self._progress_text = gui.add_markdown("Starting the localizer…")
        self._status = gui.add_markdown("")
        self._message_md = gui.add_markdown("", visible=False)

        with gui.add_folder("Playback"):
            c.play = gui.add_button("Pause", icon=viser.Icon.PLAYER_PAUSE, disabled=True)
            c.step = gui.add_button("Step", icon=viser.Icon.PLAYER_TRACK_NEXT, disabled=True,
                                    hint="Pause and process exactly one scan")
            c.speed = gui.add_dropdown("Speed (scans/s)", SPEEDS, initial_value=self._initial_speed,
                                       hint="Replay clock: at most this many scans per second")
            c.clock = gui.add_dropdown("Clock", ("replay", "realtime"), initial_value="replay",
                                       hint="replay: deterministic; realtime: S2M lands when it finishes, playback at the sequence's timestamps")
            c.seed = gui.add_number("Seed", 0, step=1)
            c.restart = gui.add_button("Restart from scan 0", icon=viser.Icon.REFRESH, disabled=True)
        self._particles_folder = gui.add_folder("Particles")
        with self._particles_folder:
            c.reset = gui.add_button("Reset globally", disabled=True, hint="Re-initialise the particles over the whole map")
            gui.add_markdown("**Shift+click** the ground: reset around that point.  \n"
                             "**Shift+drag** a rectangle: reset inside it.")
            c.kidnap_skip = gui.add_number("Kidnap skip (scans)", 100, step=1)
            c.kidnap = gui.add_button("Kidnap", disabled=True, hint="Jump the vehicle ahead without telling the filter")
        with gui.add_folder("Parameters", expand_by_default=False):
            for p in NUMERIC_PARAMS:
                c.params[p.key] = gui.add_number(p.label, 1 if p.integer else 1.0, step=p.step, hint=p.hint or None)
            c.s2m_enabled = gui.add_checkbox("S2M enabled", True, hint="Scan-to-map matching on/off (applies at once)")
            with gui.add_folder("Process noise Q (std)", expand_by_default=False):
                for name, unit in zip(STATE_NAMES, q_units()):
                    c.q.append(gui.add_number(f"{name} ({unit})", 0.0, step=0.001))
            c.apply = gui.add_button("Apply", disabled=True, hint="Numbers take effect from the next scan")
        with gui.add_folder("Layers", expand_by_default=False):
            for name, label in (("map", "Map"), ("map_bev", "Map, road removed"), ("particles", "Particles"),
                                ("scan", "Current scan (green)"), ("s2m", "Last S2M match"),
                                ("trajectories", "Trajectories (white: truth, orange: estimate)"),
                                ("ellipse", "2σ ellipse"), ("bev_level", "BEV pyramid level")):
                c.layers[name] = gui.add_checkbox(label, getattr(self.scene.layers, name),
                                                  visible=name != "bev_level")
            c.bev_level = gui.add_slider("BEV level", 0, 8, 1, 0, visible=False)
        with gui.add_folder("Plots"):
            x = np.zeros(1)
            self._plot_std = gui.add_uplot(
                (x, x, x), (uplot.Series(label="scan"),
                            uplot.Series(label="std (m)", stroke="#ff5a5a", width=2),
                            uplot.Series(label="error (m)", stroke="#e6e6e6", width=2)),
                title="Position std (max of x, y) and error", scales={"x": uplot.Scale(time=False, auto=True),
                                                                       "y": uplot.Scale(distr=3, auto=True)},
                aspect=1.6)
            self._plot_ms = gui.add_uplot(
                (x, x, x), (uplot.Series(label="scan"),
                            uplot.Series(label="PF (ms)", stroke="#ff9620", width=2),
                            uplot.Series(label="S2M (ms)", stroke="#ff3cff", width=2)),
                title="Latency per scan", scales={"x": uplot.Scale(time=False, auto=True),
                                                  "y": uplot.Scale(auto=True)}, aspect=1.6)

        c.play.on_click(lambda e: self._guard(e, self._toggle_play))
        c.step.on_click(lambda e: self._guard(e, self.step_once))
        c.speed.on_update(lambda e: self._guard(e, self._apply_speed))
        c.clock.on_update(lambda e: self._guard(e, self._apply_clock))
        c.restart.on_click(lambda e: self._guard(e, self._restart))
        c.reset.on_click(lambda e: self._guard(e, lambda: self.reset()))
        c.kidnap.on_click(lambda e: self._guard(e, self._kidnap))
        c.apply.on_click(lambda e: self._guard(e, self.apply_params))
        c.s2m_enabled.on_update(lambda e: self._guard(e, self._apply_s2m_enabled))
        for h in list(c.params.values()) + c.q:
            h.on_update(lambda e: self._guard(e, self._mark_pending))
        for name, h in c.layers.items():
            h.on_update(lambda e, name=name: self._guard(e, lambda: self._toggle_layer(name, e.target.value),
                                                         needs_localizer=False))
        c.bev_level.on_update(lambda e: self._guard(e, self._show_bev_level))

    def _guard(self, event, action, needs_localizer: bool = True) -> None:
        """Run a GUI action; a refused value or any failure becomes a visible message, never a
        dead callback thread or a crashed server."""
        if self._syncing:
            return
        client = getattr(event, "client", None)
        try:
            if needs_localizer and not self._ready.is_set():
                raise LidarlocError("the localizer is still starting (map and tables are being built)")
            action()
        except LidarlocError as exc:
            self.show_message(f"refused: {exc}", error=True, client=client)
        except Exception as exc:  # keep the server alive and say what went wrong
            traceback.print_exc(file=sys.stderr)
            self.show_message(f"internal error: {type(exc).__name__}: {exc}", error=True, client=client)

    def show_message(self, text: str, error: bool = False, client=None) -> None:
        self._message = text
        self._message_md.content = (f"<span style='color:#ff6b6b'>**{text}**</span>" if error else text)
        self._message_md.visible = bool(text)
        if client is not None and text:
            try:
                client.add_notification("lidarloc", text, color="red" if error else "blue", auto_close_seconds=6.0)
            except Exception:  # the tab may have closed meanwhile; the panel message stays
                pass

    @property
    def message(self) -> str:
        return self._message

    # ============================================================== localizer lifecycle
    def build_progress(self, stage, frac=None) -> None:
        """Progress callback for the Localizer constructor: (stage, fraction)."""
        self._build_stage = str(stage)
        self._build_frac = None if frac is None else float(frac)
        self._wake.set()

    def startup_failed(self, message: str) -> None:
        self._startup_error = message
        self._build_stage = None
        self._progress_text.content = f"<span style='color:#ff6b6b'>**could not start: {message}**</span>"
        self._progress.visible = False
        self.show_message(f"could not start: {message}", error=True)

    def attach(self, localizer) -> None:
        """Show a ready Localizer: its map (once), its parameters, and start playing it."""
        self.localizer = localizer
        self.scene.set_map(localizer.prior_map)
        self._sync_params_from_localizer()
        pyr = self._pyramid()
        if pyr is not None:
            c = self.controls
            c.layers["bev_level"].visible = True
            self._syncing = True
            try:
                c.bev_level.max = max(len(pyr.levels) - 1, 0)
                c.bev_level.value = min(2, len(pyr.levels) - 1)
            finally:
                self._syncing = False
            c.bev_level.visible = True
        if not getattr(localizer.seq, "has_poses", True):
            self._plot_std.series = (uplot.Series(label="scan"),
                                     uplot.Series(label="std (m)", stroke="#ff5a5a", width=2),
                                     uplot.Series(label="error: no ground truth", show=False))
        self._set_initial_camera()
        speed = self.controls.speed.value
        self.player = Player(localizer, self._on_step, self._on_player_error,
                             speed=None if speed == "max" else float(speed), clock=localizer.cfg.localize.clock)
        self.player.start()
        for h in (self.controls.play, self.controls.step, self.controls.restart, self.controls.reset,
                  self.controls.kidnap):
            h.disabled = False
        self._build_stage = None
        self.publish(localizer.snapshot())
        self._ready.set()
        if self._autoplay:
            self.play()
        self._wake.set()

    def _pyramid(self):
        """The localizer's BEV pyramid, if it has one (the layer is hidden otherwise)."""
        pyr = getattr(self.localizer, "pyramid", None)
        if isinstance(pyr, tuple) and pyr:      # load_or_build_pyramid's (pyramid, was_cached)
            pyr = pyr[0]
        return pyr if hasattr(pyr, "levels") and hasattr(pyr, "resolution") and hasattr(pyr, "origin") else None

    def _sync_params_from_localizer(self) -> None:
        cfg = self.localizer.cfg
        c = self.controls
        self._syncing = True
        try:
            applied = {}
            for p in NUMERIC_PARAMS:
                v = getattr(getattr(cfg, p.section), p.attr)
                gui_v = int(v) if p.integer else float(v) / p.scale
                c.params[p.key].value = gui_v
                applied[p.key] = gui_v
            q = q_to_gui(cfg.pf.q_std)
            for h, v in zip(c.q, q):
                h.value = v
            applied["q_std"] = q
            c.s2m_enabled.value = bool(cfg.s2m.enabled)
            c.clock.value = cfg.localize.clock
            c.seed.value = int(cfg.seed)
            self._applied = applied
        finally:
            self._syncing = False
        self._mark_pending()

    def _overview(self) -> tuple[np.ndarray, np.ndarray]:
        """(camera position, look-at) of an oblique view of the whole map."""
        center, ext = self.scene.map_center, self.scene.map_extent
        return center + np.array([0.0, -0.42 * ext, 0.6 * ext]), center

    def _set_initial_camera(self) -> None:
        position, look_at = self._overview()
        self.server.initial_camera.look_at = tuple(look_at)
        self.server.initial_camera.position = tuple(position)
        self.server.initial_camera.up = (0.0, 0.0, 1.0)
        # tabs opened while the map was being built still look at the default origin
        for client in self.server.get_clients().values():
            with client.atomic():
                client.camera.position = position
                client.camera.look_at = look_at

    # ============================================================== snapshots
    def publish(self, snap: Snapshot) -> None:
        """Hand a snapshot to the display (any thread; never blocks on the display)."""
        self.history.record(snap)
        self._latest = snap
        self._wake.set()

    def _on_step(self, snap: Snapshot) -> None:
        """A snapshot from the player thread. A restart that landed between the step returning
        and this call has replaced the localizer's snapshot: this one is from the old run, drop it."""
        if snap is self.localizer.snapshot():
            self.publish(snap)

    def _on_player_error(self, message: str) -> None:
        self.show_message(message, error=True)
        self._wake.set()

    def _display_loop(self) -> None:
        while not self._stopping.is_set():
            self._wake.wait(timeout=0.1)
            self._wake.clear()
            if self._stopping.is_set():
                return
            wait = self._last_draw + MIN_DRAW_INTERVAL - time.perf_counter()
            if wait > 0:
                self._stopping.wait(wait)
            try:
                self.update_display()
            except Exception:  # one bad frame must not end the display thread
                traceback.print_exc(file=sys.stderr)

    def update_display(self, force_plots: bool = False) -> float:
        """One display update: progress, scene, status and (rate-limited) plots. Returns ms spent
        on the scene and status (the per-scan cost)."""
        self._update_progress()
        snap = self._latest
        ms = 0.0
        if snap is not None and snap is not self._drawn:
            t0 = time.perf_counter()
            with self.server.atomic():
                self.scene.draw(snap, self.history)
            self._drawn = snap
            self._update_status(snap)
            self._follow_cameras(snap)
            ms = (time.perf_counter() - t0) * 1000.0
            self._last_draw = time.perf_counter()
        elif snap is not None:
            self._update_status(snap)      # play/pause state may have changed
        self._update_plots(force_plots)
        self._sync_play_button()
        if self.localizer is not None and self.controls.layers["bev_level"].value:
            self._show_bev_level()
        return ms

    def _update_progress(self) -> None:
        if self._startup_error is not None:
            return
        if self._build_stage is not None:
            frac = self._build_frac
            label = {"starting": "Starting the localizer", "map": "Building the prior map", "lookup": "Building the distance lookup table",
                     "pyramid": "Building the BEV pyramid", "ready": "Ready"}.get(self._build_stage, self._build_stage)
            self._progress.visible = True
            self._progress.animated = frac is None
            self._progress.value = 100.0 * (frac if frac is not None else 1.0)
            pct = f" {100 * frac:.0f}%" if frac is not None else ""
            self._progress_text.content = f"{label}…{pct}"
            self._progress_text.visible = True
            return
        rebuild = getattr(self.localizer, "rebuild_progress", None) if self.localizer is not None else None
        if rebuild is not None:
            self._progress.visible = True
            self._progress.animated = False
            self._progress.value = float(np.clip(100.0 * rebuild, 0, 100))
            self._progress_text.content = f"Rebuilding a table in the background… {100 * rebuild:.0f}% (the old one is used meanwhile)"
            self._progress_text.visible = True
        else:
            self._progress.visible = False
            self._progress_text.visible = False

    def _play_state(self) -> str:
        p = self.player
        if p is None:
            return "starting"
        if self.localizer is not None and self.localizer.done and p.idle:
            return "finished"
        if p.playing:
            return "playing"
        return "paused" if p.idle else "stepping"

    def status_markdown(self, snap: Snapshot) -> str:
        state = self._play_state()
        clock = self.player.clock if self.player else "replay"
        speed = "" if clock == "realtime" else f", {self.controls.speed.value} scans/s"
        k = "–" if snap.scan_index < 0 else str(snap.scan_index)
        lines = [f"**Scan {k} of {snap.n_scans}** · {state} ({clock}{speed})"]
        if snap.localized:
            since = "" if snap.localized_since is None else f" since scan {snap.localized_since}"
            lines.append(f"<span style='color:#5be35b'>**localized**{since}</span>")
        else:
            lines.append("<span style='color:#ffb347'>**not localized**</span>")
        std = np.asarray(snap.std_xyz, float)
        err = "–" if snap.error_m is None else f"{snap.error_m:.2f} m"
        n = len(snap.weights)
        s2m_ms = "–" if snap.s2m is None else f"{snap.s2m.ms:.0f} ms"
        running = " · running" if snap.s2m_running else ""
        lines += [
            "",
            "| | |",
            "|---|---|",
            f"| position std x/y/z | {std[0]:.2f} / {std[1]:.2f} / {std[2]:.2f} m |",
            f"| error to truth | {err} |",
            f"| N_eff | {snap.n_eff:.0f} of {n} |",
            f"| PF | {snap.pf_ms:.1f} ms/scan |",
            f"| S2M | {s2m_ms} · {100 * snap.s2m_acceptance:.0f}% accepted{running} |",
        ]
        events = self.history.arrays()["events"]
        if events:
            lines += ["", "**Recent events**"]
            lines += [f"- {e.scan}: {e.kind.replace('_', ' ')}" + (f" — {shorten(e.detail, 60)}" if e.detail else "")
                      for e in reversed(events)]
        return "\n".join(lines)

    def _update_status(self, snap: Snapshot) -> None:
        text = self.status_markdown(snap)
        if text != self._status_text:
            self._status_text = text
            self._status.content = text

    def _update_plots(self, force: bool) -> None:
        now = time.perf_counter()
        if not force and now - self._last_plot < PLOT_INTERVAL:
            return
        h = self.history.arrays()
        if h["version"] == self._plot_version:
            return
        self._plot_version, self._last_plot = h["version"], now
        x = h["scan"].astype(np.float64)
        if len(x) == 0:
            return
        stride = int(np.ceil(len(x) / PLOT_MAX_POINTS))
        sl = slice(None, None, stride)
        # a log scale needs positive finite values; without ground truth the error series is hidden
        std = np.maximum(h["std"], 1e-3)
        err = h["error"]
        err = np.where(np.isfinite(err), np.maximum(err, 1e-3), std)
        self._plot_std.data = (x[sl], std[sl], err[sl])
        self._plot_ms.data = (x[sl], h["pf_ms"][sl], h["s2m_ms"][sl])

    def _sync_play_button(self) -> None:
        p = self.player
        if p is None:
            return
        label = "Pause" if p.playing else "Play"
        if self.controls.play.label != label:
            self.controls.play.label = label
            self.controls.play.icon = viser.Icon.PLAYER_PAUSE if p.playing else viser.Icon.PLAYER_PLAY
        finished = self.localizer.done
        if self.controls.play.disabled != finished:
            self.controls.play.disabled = finished
            self.controls.step.disabled = finished

    # ============================================================== playback controls
    def play(self) -> None:
        self.player.play()
        self._wake.set()

    def pause(self) -> None:
        self.player.pause()
        self._wake.set()

    def _toggle_play(self) -> None:
        if self.player.playing:
            self.pause()
        else:
            if self.localizer.done:
                raise LidarlocError("end of the sequence: restart to play again")
            self.play()

    def step_once(self) -> None:
        if self.localizer.done:
            raise LidarlocError("end of the sequence: restart to play again")
        self.player.step_once()
        self._wake.set()

    def _apply_speed(self) -> None:
        v = self.controls.speed.value
        self.player.set_speed(None if v == "max" else float(v))
        self._wake.set()

    def _apply_clock(self) -> None:
        clock = self.controls.clock.value
        self.localizer.set_params(clock=clock)
        self.player.set_clock(clock)
        self.controls.speed.disabled = clock == "realtime"
        self.show_message(f"clock: {clock}")

    def _int_field(self, handle, what: str, minimum: int) -> int:
        v = handle.value
        if not (isinstance(v, (int, float)) and math.isfinite(v) and float(v).is_integer() and v >= minimum):
            raise LidarlocError(f"{what} must be a whole number ≥ {minimum}, got {v}")
        return int(v)

    def _restart(self) -> None:
        seed = self._int_field(self.controls.seed, "seed", 0)
        self.localizer.restart(seed=seed)
        self.history.clear()
        self.player.rebase()
        self.publish(self.localizer.snapshot())
        self.show_message(f"restarted from scan 0 with seed {seed}")

    def reset(self, pose: np.ndarray | None = None, region: tuple | None = None) -> None:
        self.localizer.reset(pose=pose, region=region)
        if pose is not None or region is not None:
            last = self._latest.scan_index if self._latest is not None else -1
            self.scene.show_reset_area(last, center=None if pose is None else pose[:3, 3], region=region)
        self.publish(self.localizer.snapshot())
        where = ("globally" if pose is None and region is None else
                 f"around ({pose[0, 3]:.1f}, {pose[1, 3]:.1f})" if pose is not None else
                 "in x {:.0f}…{:.0f}, y {:.0f}…{:.0f} m".format(region[0], region[2], region[1], region[3]))
        self.show_message(f"particles reset {where}")

    def _kidnap(self) -> None:
        skip = self._int_field(self.controls.kidnap_skip, "kidnap skip", 1)
        before = self.localizer.k
        target = self.localizer.kidnap(skip)
        self.player.rebase()
        if target is None:
            target = self.localizer.k
        self.show_message(f"kidnapped: the vehicle jumped from scan {before} to {target}; the filter was not told")
        self._wake.set()

    # ============================================================== parameters
    def _gui_values(self) -> dict:
        c = self.controls
        values = {p.key: c.params[p.key].value for p in NUMERIC_PARAMS}
        values["q_std"] = [h.value for h in c.q]
        return values

    def _changed(self) -> dict:
        """GUI values that differ from what the localizer was last given (GUI units)."""
        out = {}
        for key, v in self._gui_values().items():
            old = self._applied.get(key)
            if key == "q_std":
                if old is None or any(not math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-12) for a, b in zip(v, old)):
                    out[key] = v
            elif old is None or not math.isclose(float(v), float(old), rel_tol=1e-9, abs_tol=1e-12):
                out[key] = v
        return out

    def _mark_pending(self) -> None:
        n = len(self._changed())
        apply = self.controls.apply
        label = f"Apply {n} change{'s' if n != 1 else ''}" if n else "Apply"
        # one message to the clients: with three, "Apply 1 change" could show while the button
        # was still disabled, and a quick click on it was lost (seen once in the browser test)
        with self.server.atomic():
            if apply.label != label:
                apply.label = label
            apply.disabled = n == 0
            apply.color = "orange" if n else None

    def apply_params(self) -> dict:
        """Send the changed numbers to the localizer (effective from the next scan). All or nothing:
        an invalid value refuses the whole change with a message. Returns what was sent (SI)."""
        changed = self._changed()
        if not changed:
            return {}
        by_key = {p.key: p for p in NUMERIC_PARAMS}
        si: dict = {}
        for key, v in changed.items():
            if key == "q_std":
                si[key] = q_from_gui(v)
                continue
            p = by_key[key]
            if p.integer:
                if not (math.isfinite(v) and float(v).is_integer()):
                    raise LidarlocError(f"{p.label} must be a whole number, got {v}")
                si[key] = int(v)
            else:
                si[key] = float(v) * p.scale
        validate_changes(self.localizer.cfg, si)
        self.localizer.set_params(**si)
        for key, v in changed.items():
            self._applied[key] = list(v) if key == "q_std" else v
        self._mark_pending()
        names = ", ".join("Q" if k == "q_std" else by_key[k].label for k in changed)
        self.show_message(f"applied from the next scan: {names}")
        self._wake.set()
        return si

    def _apply_s2m_enabled(self) -> None:
        on = bool(self.controls.s2m_enabled.value)
        self.localizer.set_params(s2m_enabled=on)
        self.show_message(f"scan-to-map matching {'on' if on else 'off'} from the next scan")

    # ============================================================== layers
    def _toggle_layer(self, name: str, visible: bool) -> None:
        if name == "bev_level" and visible:
            self._show_bev_level()
        self.scene.set_layer(name, bool(visible))

    def _show_bev_level(self) -> None:
        pyr = self._pyramid()
        if pyr is None or not self.controls.layers["bev_level"].value:
            return
        top = max(len(pyr.levels) - 1, 0)
        if self.controls.bev_level.max != top:      # a rebuilt pyramid (new d_m) has other levels
            self._syncing = True
            try:
                self.controls.bev_level.max = top
                self.controls.bev_level.value = min(self.controls.bev_level.value, top)
            finally:
                self._syncing = False
        self.scene.set_pyramid(pyr, int(self.controls.bev_level.value))

    # ============================================================== clients and camera
    def _on_connect(self, client: viser.ClientHandle) -> None:
        state = _ClientState()
        with client.gui.add_folder("Camera (this tab)", order=self._particles_folder.order + 0.5):
            state.follow = client.gui.add_checkbox("Follow the vehicle", False,
                                                   hint="Keep the camera on the estimate")
            state.top_down = client.gui.add_button("Top-down view", icon=viser.Icon.ARROW_DOWN)
            state.fit = client.gui.add_button("Whole map")
        state.follow.on_update(lambda e: self._guard(e, lambda: self._follow_toggled(client, state), False))
        state.top_down.on_click(lambda e: self._guard(e, lambda: self.top_down(client), False))
        state.fit.on_click(lambda e: self._guard(e, lambda: self.whole_map(client), False))
        with self._clients_lock:
            self._clients[client.client_id] = state

    def _on_disconnect(self, client: viser.ClientHandle) -> None:
        with self._clients_lock:
            self._clients.pop(client.client_id, None)

    def _estimate_xyz(self) -> np.ndarray | None:
        snap = self._latest
        if snap is None:
            return None
        p = np.asarray(snap.mean_pose, float)[:3, 3]
        return p if np.isfinite(p).all() else None

    def _follow_toggled(self, client, state: _ClientState) -> None:
        if not state.follow.value:
            return
        snap, p = self._latest, self._estimate_xyz()
        if p is None:
            return
        yaw = float(np.arctan2(snap.mean_pose[1][0], snap.mean_pose[0][0]))
        back = np.array([-math.cos(yaw), -math.sin(yaw), 0.0])
        with client.atomic():
            client.camera.position = p + 35.0 * back + np.array([0, 0, 25.0])
            client.camera.look_at = p

    def _follow_cameras(self, snap: Snapshot) -> None:
        p = self._estimate_xyz()
        if p is None:
            return
        with self._clients_lock:
            following = [cid for cid, s in self._clients.items() if s.follow is not None and s.follow.value]
        if not following:
            return
        clients = self.server.get_clients()
        for cid in following:
            client = clients.get(cid)
            if client is None:
                continue
            try:
                cam = client.camera
                shift = p - np.asarray(cam.look_at)
                if np.linalg.norm(shift) > 1e-3:
                    cam.position = np.asarray(cam.position) + shift   # moves look_at along
            except (AssertionError, ValueError):  # camera state not reported yet
                continue

    def top_down(self, client) -> None:
        """Look straight down: on the vehicle if following it, else on the whole map."""
        with self._clients_lock:
            state = self._clients.get(client.client_id)
        following = state is not None and state.follow.value
        p = self._estimate_xyz()
        if following and p is not None:
            self._look_down(client, p, 120.0)
        else:
            self.whole_map(client)

    def whole_map(self, client) -> None:
        fov = client.camera.fov if client.camera.fov else 1.3
        h = 0.55 * self.scene.map_extent / math.tan(fov / 2.0)
        self._look_down(client, self.scene.map_center, h)

    @staticmethod
    def _look_down(client, target, height: float) -> None:
        target = np.asarray(target, float)
        with client.atomic():
            # a hair off vertical keeps the orbit controls' up vector defined; +y stays up on screen
            client.camera.position = target + np.array([0.0, -1e-3 * height, height])
            client.camera.look_at = target

    # ============================================================== scene pointer → reset
    def _on_shift_click(self, event) -> None:
        def act():
            if self.scene.ground is None:
                raise LidarlocError("the map is not loaded yet")
            hit = self.scene.ground.hit(event.ray_origin, event.ray_direction)
            if hit is None:
                raise LidarlocError("that click does not meet the ground")
            self.reset(pose=self.pose_at(hit[0], hit[1]))
        self._guard(event, act)

    def _on_shift_rect(self, event) -> None:
        def act():
            if self.scene.ground is None:
                raise LidarlocError("the map is not loaded yet")
            cam = event.client.camera
            (u0, v0), (u1, v1) = event.screen_min, event.screen_max
            corners = []
            for u, v in ((u0, v0), (u1, v0), (u1, v1), (u0, v1)):
                o, d = screen_ray(cam, u, v)
                hit = self.scene.ground.hit(o, d)
                if hit is None:
                    raise LidarlocError("the rectangle reaches above the horizon: drag it on the ground")
                corners.append(hit)
            c = np.array(corners)
            self.reset(region=self.region_from_corners(c[:, :2]))
        self._guard(event, act)

    def pose_at(self, x: float, y: float) -> np.ndarray:
        """A sensor pose standing on the ground at (x, y); heading unknown (identity)."""
        T = np.eye(4)
        z = self.scene.ground.at(x, y) if self.scene.ground is not None else 0.0
        T[:3, 3] = (x, y, z + float(self.localizer.cfg.pf.sensor_height))
        return T

    @staticmethod
    def region_from_corners(xy: np.ndarray) -> tuple[float, float, float, float]:
        lo, hi = xy.min(axis=0), xy.max(axis=0)
        return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])

    # ============================================================== shutdown
    def stop(self) -> None:
        self._stopping.set()
        self._wake.set()
        if self.player is not None:
            self.player.stop(timeout=0.5)
        if self._display.is_alive():
            self._display.join(timeout=0.3)


class ViewerHandle:
    """What :func:`serve` returns: where the viewer is, and how to stop it."""

    def __init__(self, viewer: Viewer, server: viser.ViserServer, host: str):
        self.viewer = viewer
        self.server = server
        self.port = int(server.get_port())
        shown = "localhost" if host in ("0.0.0.0", "::") else host
        self.url = f"http://{shown}:{self.port}"
        self._stopped = threading.Event()

    @property
    def localizer(self):
        return self.viewer.localizer

    def wait_ready(self, timeout: float | None = None) -> bool:
        """Block until the localizer is built and shown (False on timeout or failed start)."""
        return self.viewer._ready.wait(timeout)

    def wait(self) -> None:
        """Block until :meth:`stop` (in short waits, so Ctrl-C gets through at once)."""
        while not self._stopped.wait(0.25):
            pass

    def stop(self) -> None:
        """Stop playback, the display and the server; close the localizer if the viewer built it.
        Bounded: returns within ~1.2 s. A scan of the viewer's own localizer that is waiting for
        a block gives up at once (``Localizer.interrupt``); one still computing finishes on its
        daemon thread, and the localizer's worker pools are joined by Python at exit."""
        if self._stopped.is_set():
            return
        loc = self.viewer.localizer
        owned = loc is not None and self.viewer.owns_localizer
        if owned:
            loc.interrupt()
        self.viewer.stop()
        self.server.stop()
        if owned:
            closer = threading.Thread(target=loc.close, name="lidarloc-close", daemon=True)
            closer.start()
            closer.join(timeout=0.3)
        self._stopped.set()


def _call_factory(factory, progress):
    """Build the localizer, handing it the progress callback if it takes one."""
    try:
        params = inspect.signature(factory).parameters
    except (TypeError, ValueError):
        params = {}
    if "progress" in params or any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values()):
        return factory(progress=progress)
    return factory()


def serve(localizer_factory_or_localizer, host: str = "127.0.0.1", port: int = 8080, open_browser: bool = False,
          *, autoplay: bool = True, speed: str = "10") -> ViewerHandle:
    """Start the viewer and return at once.

    ``localizer_factory_or_localizer``: a ready Localizer (the caller keeps ownership and closes
    it), or a callable returning one — called on a background thread, with ``progress=`` if it
    accepts it (the Localizer's ``(stage, fraction)`` callback), while the page shows a progress
    bar; the viewer then owns it and closes it on :meth:`ViewerHandle.stop`.
    ``port``: the first port tried (viser moves up if it is taken; the handle has the real one).
    """
    if speed not in SPEEDS:
        raise LidarlocError(f"speed must be one of {', '.join(SPEEDS)}, got {speed!r}")
    server = viser.ViserServer(host=host, port=port, label="lidarloc", verbose=False)
    try:
        viewer = Viewer(server, autoplay=autoplay, speed=speed)
    except BaseException:
        server.stop()
        raise
    target = localizer_factory_or_localizer
    if hasattr(target, "step") and hasattr(target, "snapshot"):
        try:
            viewer.attach(target)
        except BaseException:
            viewer.stop()
            server.stop()
            raise
    elif callable(target):
        def build():
            loc = None
            try:
                loc = _call_factory(target, viewer.build_progress)
                viewer.owns_localizer = True
                if viewer._stopping.is_set():      # stopped while building: nobody will show it
                    loc.close()
                    return
                viewer.attach(loc)
            except LidarlocError as exc:
                viewer.startup_failed(str(exc))
            except Exception as exc:
                traceback.print_exc(file=sys.stderr)
                viewer.startup_failed(f"{type(exc).__name__}: {exc}")
        threading.Thread(target=build, name="lidarloc-build", daemon=True).start()
    else:
        viewer.stop()
        server.stop()
        raise LidarlocError("serve() needs a Localizer or a callable that returns one")
    handle = ViewerHandle(viewer, server, host)
    if open_browser:
        threading.Thread(target=webbrowser.open, args=(handle.url,), daemon=True).start()
    return handle

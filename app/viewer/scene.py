"""The 3D scene: the prior map, the particles, the 2σ ellipse, the current scan, the last
scan-to-map match, the trajectories and the BEV pyramid level, on the server-wide scene that
every browser tab shares."""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass

import numpy as np

from ...core.snapshot import Snapshot
from .ground import GroundHeight
from .history import History
from .map_tiles import TileSettings
from .minimap import Footprint
from .scene_map import MapLayers
from .shapes import (
    ChunkedPolyline,
    log_weight_rank,
    quat_wxyz_from_matrix,
    snapshot_log_weights,
    vehicle_outline,
)
from .style import (
    BEST_COLOR,
    DISPLAY_MAX_POINTS,
    DISPLAY_VOXEL,
    ELLIPSE_COLOR,
    EST_COLOR,
    GT_COLOR,
    PARTICLE_ARROW_MAX,
    PARTICLE_ARROW_MIN,
    PARTICLE_HIGH,
    PARTICLE_LOW,
    RESET_COLOR,
    S2M_ACCEPTED_COLOR,
    S2M_REJECTED_COLOR,
    SCAN_COLOR,
    shorten,
)


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
    vehicles: bool = True
    ellipse: bool = True
    staleness: bool = True


class SceneView(MapLayers):
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
        self._gt_shown = False
        self._est_frame = None
        self._est_vehicle = self._gt_vehicle = None
        self._reset_hint = None
        self._reset_hint_scan: int | None = None
        self.gt_line = ChunkedPolyline(scene, "/trajectory/ground_truth", GT_COLOR, 2.0)
        self.est_line = ChunkedPolyline(scene, "/trajectory/estimate", EST_COLOR, 2.0)
        self.display_voxel = DISPLAY_VOXEL
        self._source_voxel = DISPLAY_VOXEL
        # a map sent in tiles (scene_map): the tiles, their nodes, and the points sent
        self._tiled = self._near = None
        self._near_nodes: dict = {}
        self._coarse_nodes: dict = {}
        self._map_points = self._map_bev_points = 0
        self._max_points = DISPLAY_MAX_POINTS
        self._tile_settings = TileSettings()
        self.footprint: Footprint | None = None  # the map from above, for the panel's overview
        self.on_map_tiles = None  # called (any thread) when tiles were read and wait to be shown

    #: the names :meth:`node` answers to, and the attribute holding each node
    _NODES = {
        "map": "_map",
        "map_bev": "_map_bev",
        "bev_level": "_bev_image",
        "particles": "_particles",
        "particle_dots": "_particle_dots",
        "best": "_best",
        "ellipse": "_ellipse",
        "scan": "_scan",
        "pose": "_est_frame",
        "est_vehicle": "_est_vehicle",
        "gt_vehicle": "_gt_vehicle",
        "s2m_scan": "_s2m_scan",
        "s2m_region": "_s2m_box",
        "s2m_label": "_s2m_label",
        "reset_area": "_reset_hint",
    }

    def node(self, name: str):
        """The viser handle of one drawn node (``"map"``, ``"particles"``, ``"scan"``, ``"s2m_label"``,
        ``"reset_area"``, … see ``_NODES``), or None until it is first drawn."""
        return getattr(self, self._NODES[name])

    @property
    def bev_shown(self) -> tuple:
        """(pyramid, level) of the BEV level image on the ground; (None, None) before one is shown."""
        return self._pyramid, self._bev_level_shown

    def set_layer(self, name: str, visible: bool) -> None:
        with self._lock:
            self._set_layer(name, visible)

    def _set_layer(self, name: str, visible: bool) -> None:
        setattr(self.layers, name, visible)
        nodes = {
            "map": [self._map],
            "map_bev": [self._map_bev],
            "bev_level": [self._bev_image],
            "particles": [self._particles, self._particle_dots, self._best],
            "scan": [self._scan, self._est_frame],
            "s2m": [self._s2m_scan, self._s2m_box, self._s2m_label],
            "vehicles": [self._est_vehicle, self._gt_vehicle],
            "ellipse": [self._ellipse],
        }.get(name, [])
        for node in nodes:
            if node is not None:
                # a node with nothing to show (no match yet in this run, no truth) stays hidden
                node.visible = visible and self._has_content(node)
        if name == "trajectories":
            self.gt_line.set_visible(visible)
            self.est_line.set_visible(visible)

    def _has_content(self, node) -> bool:
        # by identity: a handle's == compares its props, numpy arrays among them, which raises
        if any(node is n for n in (self._s2m_scan, self._s2m_box, self._s2m_label)):
            return self._s2m_shown is not None
        if node is self._gt_vehicle:
            return self._gt_shown
        return True

    # -------------------------------------------------------------------- per snapshot
    def clear(self) -> None:
        """The run restarted: nothing of the old run stays (its S2M match, reset area, truth)."""
        with self._lock:
            self._hide_s2m()
            if self._reset_hint is not None:
                self._reset_hint.visible = False
            self._reset_hint_scan = None
            if self._gt_vehicle is not None:
                self._gt_vehicle.visible = False
            self._gt_shown = False

    def draw(self, snap: Snapshot, history: History, cut: int | None = None) -> None:
        """Draw ``snap``; the trajectories end at the ``cut``-th recorded step (the scan the
        timeline shows) or, with None, at the newest."""
        with self._lock:
            self._draw(snap, history, cut)

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
                c = np.stack(
                    [
                        center[0] + radius * np.cos(th),
                        center[1] + radius * np.sin(th),
                        np.full_like(th, center[2] if len(center) > 2 else z),
                    ],
                    axis=1,
                ).astype(np.float32)
            segs = np.stack([c, np.roll(c, -1, axis=0)], axis=1)
            if self._reset_hint is None:
                self._reset_hint = self.scene.add_line_segments(
                    "/reset_area", segs, RESET_COLOR, thickness=3.0, thickness_units="screen"
                )
            else:
                self._reset_hint.points = segs
                self._reset_hint.visible = True
            self._reset_hint_scan = scan_index

    def _draw(self, snap: Snapshot, history: History, cut: int | None = None) -> None:
        if self._reset_hint_scan is not None and snap.scan_index > self._reset_hint_scan:
            self._reset_hint.visible = False
            self._reset_hint_scan = None
        self._draw_particles(snap)
        self._draw_ellipse(snap)
        self._draw_scan(snap)
        self._draw_s2m(snap)
        self._draw_vehicles(snap)
        self._draw_trajectories(history, cut)

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
        # as RViz draws a weighted pose array: longer = heavier; the colour orders them by log-weight
        length = (PARTICLE_ARROW_MIN + (PARTICLE_ARROW_MAX - PARTICLE_ARROW_MIN) * w_rel).astype(np.float32)[:, None]
        tip = xyz + head * length
        segs = np.stack([xyz, tip], axis=1)
        rank = log_weight_rank(snapshot_log_weights(snap)).astype(np.float32)[:, None]
        c = (PARTICLE_LOW + (PARTICLE_HIGH - PARTICLE_LOW) * rank).astype(np.uint8)
        colors = np.repeat(c[:, None, :], 2, axis=1)
        vis = self.layers.particles
        self._node(
            "_particles",
            lambda v: self.scene.add_line_segments(
                "/particles/headings", segs, colors, thickness=2.0, thickness_units="screen", visible=v
            ),
            lambda h: self._set(h, points=segs, colors=colors),
            vis,
        )
        dots_c = c
        self._node(
            "_particle_dots",
            lambda v: self.scene.add_point_cloud(
                "/particles/positions",
                xyz,
                dots_c,
                point_size=0.6,
                precision="float32",
                point_shape="circle",
                point_shading="flat",
                visible=v,
            ),
            lambda h: self._set(h, points=xyz, colors=dots_c),
            vis,
        )
        # the highest-weight particle: a big cyan arrow (shaft and two barbs)
        b = int(snap.best_index) if 0 <= snap.best_index < len(P) else int(np.argmax(w))
        p, hd = xyz[b], head[b]
        side = np.array([-hd[1], hd[0], 0], np.float32)
        L = 8.0
        t = p + hd * L
        best = np.array([[p, t], [t, t - hd * 2.5 + side * 1.5], [t, t - hd * 2.5 - side * 1.5]], np.float32)
        self._node(
            "_best",
            lambda v: self.scene.add_line_segments(
                "/particles/best", best, BEST_COLOR, thickness=4.0, thickness_units="screen", visible=v
            ),
            lambda h: self._set(h, points=best),
            vis,
        )

    def _draw_ellipse(self, snap: Snapshot) -> None:
        a, bb, ang = (float(v) for v in snap.ellipse_xy)
        center = np.asarray(snap.mean_pose)[:3, 3]
        if not all(math.isfinite(v) for v in (a, bb, ang)) or not np.isfinite(center).all():
            return
        n = 72
        th = np.linspace(0, 2 * np.pi, n + 1)
        ca, sa = math.cos(ang), math.sin(ang)
        ex, ey = a * np.cos(th), bb * np.sin(th)
        pts = np.stack(
            [center[0] + ca * ex - sa * ey, center[1] + sa * ex + ca * ey, np.full_like(th, center[2])], axis=1
        ).astype(np.float32)
        segs = np.stack([pts[:-1], pts[1:]], axis=1)[::2]  # every other piece: the paper's dotted circle
        self._node(
            "_ellipse",
            lambda v: self.scene.add_line_segments(
                "/estimate/ellipse_2sigma", segs, ELLIPSE_COLOR, thickness=2.5, thickness_units="screen", visible=v
            ),
            lambda h: self._set(h, points=segs),
            self.layers.ellipse,
        )

    def _draw_scan(self, snap: Snapshot) -> None:
        pts = np.asarray(snap.scan_world, np.float32).reshape(-1, 3)
        T = np.asarray(snap.mean_pose, float)
        if len(pts) == 0:
            if self._scan is not None:
                self._scan.visible = False
        else:
            self._node(
                "_scan",
                lambda v: self.scene.add_point_cloud(
                    "/estimate/scan",
                    pts,
                    SCAN_COLOR,
                    point_size=0.25,
                    precision="float32",
                    point_shading="flat",
                    visible=v,
                ),
                lambda h: self._set(h, points=pts, visible=self.layers.scan),
                self.layers.scan,
            )
        if np.isfinite(T).all():
            wxyz, pos = quat_wxyz_from_matrix(T[:3, :3]), T[:3, 3]
            if self._est_frame is None:
                self._est_frame = self.scene.add_frame(
                    "/estimate/pose",
                    wxyz=wxyz,
                    position=pos,
                    axes_length=3.0,
                    axes_radius=0.15,
                    visible=self.layers.scan,
                )
            else:
                self._est_frame.wxyz, self._est_frame.position = wxyz, pos

    def _hide_s2m(self) -> None:
        self._s2m_shown = None
        for node in (self._s2m_scan, self._s2m_box, self._s2m_label):
            if node is not None:
                node.visible = False

    def _draw_s2m(self, snap: Snapshot) -> None:
        s = snap.s2m
        if s is None:
            # a new run (restart) has no match yet: the old run's must not stay
            if self._s2m_shown is not None:
                self._hide_s2m()
            return
        if s is self._s2m_shown:
            return
        self._s2m_shown = s
        color = S2M_ACCEPTED_COLOR if s.accepted else S2M_REJECTED_COLOR
        vis = self.layers.s2m
        pts = np.asarray(s.scan_world, np.float32).reshape(-1, 3)
        if len(pts):
            if self._s2m_scan is not None:
                self._s2m_scan.remove()
            self._s2m_scan = self.scene.add_point_cloud(
                "/s2m/scan", pts, color, point_size=0.3, precision="float32", point_shading="flat", visible=vis
            )
        x0, y0, x1, y1 = (float(v) for v in s.region)
        z = float(np.asarray(s.pose)[2, 3])
        c = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], np.float32)
        box = np.stack([c, np.roll(c, -1, axis=0)], axis=1)
        if self._s2m_box is None:
            self._s2m_box = self.scene.add_line_segments(
                "/s2m/region", box, color, thickness=2.0, thickness_units="screen", visible=vis
            )
        else:
            self._set(self._s2m_box, points=box, colors=np.asarray(color, np.uint8))
            self._show(self._s2m_box, vis)
        verdict = "accepted" if s.accepted else "rejected" + (f" ({shorten(s.reason, 60)})" if s.reason else "")
        text = (
            f"S2M: started at scan {s.started_at}, landed at {s.landed_at}\n{verdict}, "
            f"score {s.score:.0f} (start {s.start_score:.0f}), {s.ms:.0f} ms"
        )
        if self._s2m_label is None:
            self._s2m_label = self.scene.add_label(
                "/s2m/label", text, position=(x0, y1, z + 2.0), anchor="bottom-left", visible=vis
            )
        else:
            self._s2m_label.text = text
            self._s2m_label.position = (x0, y1, z + 2.0)
            self._show(self._s2m_label, vis)

    def _draw_vehicles(self, snap: Snapshot) -> None:
        """The estimate's vehicle (orange) and, where the source knows it, the true one (lime)."""
        vis = self.layers.vehicles
        T = np.asarray(snap.mean_pose, float)
        if snap.scan_index >= 0 and np.isfinite(T).all():
            segs = vehicle_outline(T)
            self._node(
                "_est_vehicle",
                lambda v: self.scene.add_line_segments(
                    "/estimate/vehicle", segs, EST_COLOR, thickness=3.0, thickness_units="screen", visible=v
                ),
                lambda h: self._set(h, points=segs),
                vis,
            )
        G = snap.gt_pose
        self._gt_shown = G is not None and bool(np.isfinite(np.asarray(G, float)).all())
        if self._gt_shown:
            segs = vehicle_outline(np.asarray(G, float))
            self._node(
                "_gt_vehicle",
                lambda v: self.scene.add_line_segments(
                    "/truth/vehicle", segs, GT_COLOR, thickness=3.0, thickness_units="screen", visible=v
                ),
                lambda h: (self._set(h, points=segs), self._show(h, vis)),
                vis,
            )
        elif self._gt_vehicle is not None:
            self._gt_vehicle.visible = False

    def _draw_trajectories(self, history: History, cut: int | None = None) -> None:
        epoch, scans, est, gt = history.trajectories()
        if cut is not None:
            scans, est, gt = scans[:cut], est[:cut], gt[:cut]
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
    def _show(handle, visible: bool) -> None:
        """Set a node's visibility, sending nothing when it does not change."""
        if handle.visible != visible:
            handle.visible = visible

    @staticmethod
    def _set(handle, **props) -> None:
        for k, v in props.items():
            setattr(handle, k, v)

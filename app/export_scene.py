"""The scene of an exported run, drawn step by step into a viser scene whose messages are being
recorded: the map thinned for display, both trajectories, the particles, the estimate with its
2σ ellipse and vehicle, the truth's vehicle, the scan, the last S2M match, and — because a
recording carries no GUI panel — the figures a reader needs (scan, localized, std, error, N_eff)
as a label beside the estimate and as an overlay in the page's corner.

Colours and shapes are the live viewer's (app/viewer/style.py, shapes.py), so an exported run
reads like the viewer. Every array handed to viser is a fresh one: the recording keeps references
to the buffers until it is serialized.
"""

from __future__ import annotations

import json
import math

import numpy as np

from ..core.snapshot import Snapshot
from .viewer.shapes import downsample_for_display, log_weight_rank, quat_wxyz_from_matrix, vehicle_outline
from .viewer.style import (
    BEST_COLOR,
    ELLIPSE_COLOR,
    EST_COLOR,
    GT_COLOR,
    PARTICLE_ARROW_MAX,
    PARTICLE_ARROW_MIN,
    PARTICLE_HIGH,
    PARTICLE_LOW,
    S2M_ACCEPTED_COLOR,
    S2M_REJECTED_COLOR,
    SCAN_COLOR,
    css,
    height_colors,
)

#: the exported map's display budget: thinned (voxel grown from 0.5 m) until it fits. 400 k points
#: are ~6 MB in the recording: a share that leaves room for hundreds of steps of particles and scans
EXPORT_MAP_POINTS = 400_000
#: points per trajectory chunk: a step re-sends only the open chunk, finished ones stay as recorded
TRAJ_CHUNK = 64
#: a step's scan is thinned to at most this many points (a random, reproducible subset): a real
#: drive's prepared scan is ~18 k points, 0.2 MB a step; 5 k show its structure at a quarter of that
EXPORT_SCAN_POINTS = 5_000
HUD_ID = "lidarloc-hud"


def step_text(snap: Snapshot, step: int, n_steps: int) -> str:
    """The figures of one step as the export shows them (label and overlay)."""
    std = float(np.max(np.asarray(snap.std_xyz, float)[:2]))
    n = snap.n_particles or len(snap.particles)
    share = 100.0 * snap.n_eff / n if n else math.nan
    err = "error —" if snap.error_m is None else f"error {snap.error_m:.2f} m"
    state = "localized" if snap.localized else "not localized"
    return (
        f"scan {snap.scan_index} (step {step + 1} of {n_steps}) · {state}\n"
        f"std {std:.2f} m · {err} · N_eff {share:.1f} % of {n}"
    )


def _legend() -> str:
    items = (
        ("estimate", EST_COLOR),
        ("truth", GT_COLOR),
        ("particles", tuple(int(v) for v in PARTICLE_HIGH)),
        ("best particle", BEST_COLOR),
        ("2σ ellipse", ELLIPSE_COLOR),
        ("scan", SCAN_COLOR),
        ("S2M match", S2M_ACCEPTED_COLOR),
    )
    return "".join(f'<span style="color:{css(c)}">■</span> {name}&nbsp; ' for name, c in items)


def hud_script(title: str, text: str) -> str:
    """JavaScript that writes ``text`` into the page's overlay (created on first use)."""
    return (
        "(() => {"
        f"let d = document.getElementById({json.dumps(HUD_ID)});"
        "if (!d) {"
        "  d = document.createElement('div');"
        f"  d.id = {json.dumps(HUD_ID)};"
        "  d.style.cssText = 'position:fixed;top:10px;right:10px;z-index:1000;pointer-events:none;"
        "background:rgba(20,20,20,0.78);color:#f0f0f0;padding:7px 10px;border-radius:5px;"
        "font:13px/1.45 ui-monospace,Menlo,Consolas,monospace;max-width:46em';"
        '  d.innerHTML = \'<div style="font-weight:bold"></div><div style="white-space:pre"></div>'
        f'<div style="font-size:11px;opacity:0.85;margin-top:3px">{_legend()}</div>\';'
        "  document.body.appendChild(d);"
        "}"
        f"d.children[0].textContent = {json.dumps(title)};"
        f"d.children[1].textContent = {json.dumps(text)};"
        "})();"
    )


class _Polyline:
    """A growing polyline recorded in chunks of TRAJ_CHUNK points: each step updates only the
    open chunk, so a step's cost does not grow with the drive's length."""

    def __init__(self, scene, name: str, color, thickness: float = 2.0):
        self.scene, self.name, self.color, self.thickness = scene, name, color, thickness
        self.handles: list = []

    def draw(self, pts: np.ndarray, connected: np.ndarray) -> None:
        """``pts`` (n, 3): the whole polyline so far; ``connected[i]``: point i joins point i − 1."""
        n = len(pts)
        if n < 2:
            return
        c = (n - 2) // TRAJ_CHUNK
        lo, hi = c * TRAJ_CHUNK, n - 1
        a, b = pts[lo:hi], pts[lo + 1 : hi + 1]
        keep = connected[lo + 1 : hi + 1] & np.isfinite(a).all(axis=1) & np.isfinite(b).all(axis=1)
        if keep.any():
            segs = np.stack([a[keep], b[keep]], axis=1).astype(np.float32)
        else:  # nothing to join yet: a zero-length stand-in keeps the chunk's node
            p = np.nan_to_num(pts[lo : lo + 1]).astype(np.float32)
            segs = np.stack([p, p], axis=1)
        while len(self.handles) < c:  # a chunk skipped entirely (cannot happen step by step)
            self.handles.append(None)
        if c < len(self.handles) and self.handles[c] is not None:
            self.handles[c].points = segs
        else:
            h = self.scene.add_line_segments(
                f"{self.name}/c{c}", segs, self.color, thickness=self.thickness, thickness_units="screen"
            )
            if c < len(self.handles):
                self.handles[c] = h
            else:
                self.handles.append(h)


class ExportScene:
    """Draws a recorded run into ``scene`` (a viser SceneApi being recorded) one step at a time.
    ``hud``: a callable taking JavaScript source to run in the page, or None (label only)."""

    def __init__(self, scene, title: str, n_steps: int, hud=None, scan_points: int = EXPORT_SCAN_POINTS):
        self.scene, self.title, self.n_steps, self.hud = scene, title, n_steps, hud
        self.scan_points = scan_points
        self.est_line = _Polyline(scene, "/trajectory/estimate", EST_COLOR, 2.0)
        self.gt_line = _Polyline(scene, "/trajectory/ground_truth", GT_COLOR, 2.0)
        self._est: list[np.ndarray] = []
        self._gt: list[np.ndarray] = []
        self._scans: list[int] = []
        self._nodes: dict = {}
        self._s2m_shown = None
        self.map_points = 0
        self.map_voxel = None

    # -------------------------------------------------------------------- static
    def draw_map(self, points: np.ndarray, max_points: int = EXPORT_MAP_POINTS, voxel: float = 0.5) -> None:
        pts, self.map_voxel = downsample_for_display(np.asarray(points, np.float32), voxel, max_points)
        self.map_points = len(pts)
        self.scene.add_point_cloud(
            "/map",
            pts,
            height_colors(pts[:, 2]),
            point_size=self.map_voxel * 0.8,
            precision="float32",
            point_shape="square",
            point_shading="flat",
        )

    # -------------------------------------------------------------------- per step
    def _set(self, name: str, make, **props) -> None:
        """Create node ``name`` with ``make()`` on first use, else update its ``props``."""
        h = self._nodes.get(name)
        if h is None:
            self._nodes[name] = make()
            return
        for k, v in props.items():
            setattr(h, k, v)
        if not h.visible:
            h.visible = True

    def _hide(self, name: str) -> None:
        h = self._nodes.get(name)
        if h is not None and h.visible:
            h.visible = False

    def draw_step(self, step: int, snap: Snapshot) -> None:
        T = np.asarray(snap.mean_pose, float)
        self._draw_particles(snap)
        if np.isfinite(T).all():
            self._draw_estimate(snap, T)
        self._draw_truth(snap)
        self._draw_trajectories(snap, T)
        self._draw_scan(step, snap)
        self._draw_s2m(snap)
        text = step_text(snap, step, self.n_steps)
        if np.isfinite(T).all():
            pos = (float(T[0, 3]), float(T[1, 3]), float(T[2, 3]) + 3.0)
            self._set(
                "/estimate/label",
                lambda: self.scene.add_label("/estimate/label", text, position=pos, anchor="bottom-left"),
                text=text,
                position=pos,
            )
        if self.hud is not None:
            self.hud(hud_script(self.title, text))

    def _draw_particles(self, snap: Snapshot) -> None:
        P = np.asarray(snap.particles)
        if len(P) == 0:
            return
        w = np.asarray(snap.weights, np.float64)
        w_rel = (w / w.max()) if w.max() > 0 else np.ones_like(w)
        xyz = P[:, :3].astype(np.float32)
        yaw = P[:, 3]
        head = np.stack([np.cos(yaw), np.sin(yaw), np.zeros_like(yaw)], axis=1).astype(np.float32)
        length = (PARTICLE_ARROW_MIN + (PARTICLE_ARROW_MAX - PARTICLE_ARROW_MIN) * w_rel).astype(np.float32)[:, None]
        segs = np.stack([xyz, xyz + head * length], axis=1)
        lw = snap.log_weights if snap.log_weights is not None else np.log(np.maximum(w, 1e-300))
        rank = log_weight_rank(np.asarray(lw, np.float64)).astype(np.float32)[:, None]
        c = (PARTICLE_LOW + (PARTICLE_HIGH - PARTICLE_LOW) * rank).astype(np.uint8)
        seg_c = np.repeat(c[:, None, :], 2, axis=1)
        self._set(
            "/particles/headings",
            lambda: self.scene.add_line_segments(
                "/particles/headings", segs, seg_c, thickness=2.0, thickness_units="screen"
            ),
            points=segs,
            colors=seg_c,
        )
        self._set(
            "/particles/positions",
            lambda: self.scene.add_point_cloud(
                "/particles/positions",
                xyz,
                c,
                point_size=0.6,
                precision="float32",
                point_shape="circle",
                point_shading="flat",
            ),
            points=xyz,
            colors=c,
        )
        b = int(snap.best_index) if 0 <= snap.best_index < len(P) else int(np.argmax(w))
        p, hd = xyz[b], head[b]
        side = np.array([-hd[1], hd[0], 0], np.float32)
        t = p + hd * 8.0
        best = np.array([[p, t], [t, t - hd * 2.5 + side * 1.5], [t, t - hd * 2.5 - side * 1.5]], np.float32)
        self._set(
            "/particles/best",
            lambda: self.scene.add_line_segments(
                "/particles/best", best, BEST_COLOR, thickness=4.0, thickness_units="screen"
            ),
            points=best,
        )

    def _draw_estimate(self, snap: Snapshot, T: np.ndarray) -> None:
        veh = vehicle_outline(T)
        self._set(
            "/estimate/vehicle",
            lambda: self.scene.add_line_segments(
                "/estimate/vehicle", veh, EST_COLOR, thickness=3.0, thickness_units="screen"
            ),
            points=veh,
        )
        wxyz, pos = quat_wxyz_from_matrix(T[:3, :3]), T[:3, 3].copy()
        self._set(
            "/estimate/pose",
            lambda: self.scene.add_frame("/estimate/pose", wxyz=wxyz, position=pos, axes_length=3.0, axes_radius=0.15),
            wxyz=wxyz,
            position=pos,
        )
        a, b, ang = (float(v) for v in snap.ellipse_xy)
        if not all(math.isfinite(v) for v in (a, b, ang)):
            self._hide("/estimate/ellipse_2sigma")
            return
        th = np.linspace(0, 2 * np.pi, 73)
        ca, sa = math.cos(ang), math.sin(ang)
        ex, ey = a * np.cos(th), b * np.sin(th)
        pts = np.stack(
            [T[0, 3] + ca * ex - sa * ey, T[1, 3] + sa * ex + ca * ey, np.full_like(th, T[2, 3])], axis=1
        ).astype(np.float32)
        segs = np.stack([pts[:-1], pts[1:]], axis=1)[::2]  # every other piece: the paper's dotted circle
        self._set(
            "/estimate/ellipse_2sigma",
            lambda: self.scene.add_line_segments(
                "/estimate/ellipse_2sigma", segs, ELLIPSE_COLOR, thickness=2.5, thickness_units="screen"
            ),
            points=segs,
        )

    def _draw_truth(self, snap: Snapshot) -> None:
        G = snap.gt_pose
        if G is None or not np.isfinite(np.asarray(G, float)).all():
            self._hide("/truth/vehicle")
            return
        veh = vehicle_outline(np.asarray(G, float))
        self._set(
            "/truth/vehicle",
            lambda: self.scene.add_line_segments(
                "/truth/vehicle", veh, GT_COLOR, thickness=3.0, thickness_units="screen"
            ),
            points=veh,
        )

    def _draw_trajectories(self, snap: Snapshot, T: np.ndarray) -> None:
        G = snap.gt_pose
        self._est.append(T[:3, 3].astype(np.float32) if np.isfinite(T).all() else np.full(3, np.nan, np.float32))
        self._gt.append(
            np.asarray(G, float)[:3, 3].astype(np.float32) if G is not None else np.full(3, np.nan, np.float32)
        )
        self._scans.append(snap.scan_index)
        scans = np.asarray(self._scans)
        # the truth jumps where the vehicle was kidnapped (the scan index skips): no line there
        connected = np.r_[False, np.diff(scans) == 1]
        self.est_line.draw(np.asarray(self._est), np.r_[False, np.ones(len(scans) - 1, bool)])
        self.gt_line.draw(np.asarray(self._gt), connected)

    def _draw_scan(self, step: int, snap: Snapshot) -> None:
        pts = np.asarray(snap.scan_world, np.float32).reshape(-1, 3)
        if len(pts) == 0:
            self._hide("/estimate/scan")
            return
        if len(pts) > self.scan_points:
            keep = np.random.default_rng(step).choice(len(pts), self.scan_points, replace=False)
            pts = pts[np.sort(keep)]
        else:
            pts = pts.copy()
        self._set(
            "/estimate/scan",
            lambda: self.scene.add_point_cloud(
                "/estimate/scan", pts, SCAN_COLOR, point_size=0.25, precision="float32", point_shading="flat"
            ),
            points=pts,
        )

    def _draw_s2m(self, snap: Snapshot) -> None:
        s = snap.s2m
        if s is None or s is self._s2m_shown:
            return
        self._s2m_shown = s
        color = S2M_ACCEPTED_COLOR if s.accepted else S2M_REJECTED_COLOR
        pts = np.asarray(s.scan_world, np.float32).reshape(-1, 3).copy()
        if "/s2m/scan" in self._nodes:  # a new match: its own scan (colour and size differ)
            self._nodes.pop("/s2m/scan").remove()
        if len(pts):
            self._nodes["/s2m/scan"] = self.scene.add_point_cloud(
                "/s2m/scan", pts, color, point_size=0.3, precision="float32", point_shading="flat"
            )
        x0, y0, x1, y1 = (float(v) for v in s.region)
        z = float(np.asarray(s.pose)[2, 3])
        c = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], np.float32)
        box = np.stack([c, np.roll(c, -1, axis=0)], axis=1)
        col = np.asarray(color, np.uint8)
        self._set(
            "/s2m/region",
            lambda: self.scene.add_line_segments("/s2m/region", box, col, thickness=2.0, thickness_units="screen"),
            points=box,
            colors=col,
        )
        verdict = "accepted" if s.accepted else "rejected"
        text = f"S2M: started at scan {s.started_at}, landed at {s.landed_at}, {verdict}"
        pos = (x0, y1, z + 2.0)
        self._set(
            "/s2m/label",
            lambda: self.scene.add_label("/s2m/label", text, position=pos, anchor="bottom-left"),
            text=text,
            position=pos,
        )

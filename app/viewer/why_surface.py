"""The likelihood-surface view: on a button press (or for every scan), the scan's log-likelihood on
an x–y grid around the estimate (:meth:`~lidarloc.core.filter.surface.LikelihoodModel.surface`, the
filter's kernel and current options), drawn as an image on the ground with the estimate, the
truth and the surface's maximum marked, and its colour scale in the panel.

The computation runs on the views' worker thread, on that thread alone (~0.1–0.3 s on a quiet
machine; several times that while the filter, its child processes and the browser share the two
cores; see :meth:`~lidarloc.core.filter.surface.LikelihoodModel.surface`); a new request supersedes
one still running, and the display thread only asks. A surface asked for with the button comes
in two passes: first in :data:`COARSE_CELL` cells (a quarter of the work, on screen while the
scans play), then in the full :data:`~lidarloc.core.filter.surface.CELL` cells, which replace it.

Where it is drawn: the image floats :data:`LIFT` above the map's ground under it, above the
map's ground points (their squares reach half a point size above their height), and the marks
(estimate, truth, maximum) sit above the vehicles' outlines, which are drawn at the sensor's
height: lower, the map hid the image and the outlines hid the marks."""

from __future__ import annotations

import math
import threading

import numpy as np

from ...core.filter.surface import CELL, HALF_WIDTH, YAW_STEP, YAW_WINDOW, LikelihoodModel, Surface
from ...core.geometry import inv_pose, pose_to_xyz_ypr, transform_points
from ...core.snapshot import Snapshot
from .style import EST_COLOR, GT_COLOR, GT_NAME
from .why_style import SURFACE_BEST_COLOR, SURFACE_LUT, colour_bar_html, surface_rgba, surface_scale

HELP = (
    "Bright = likely. One bright spot: the scan pins the pose down. A long bright band along the "
    "road: the scan is ambiguous along it. Several spots: places that look alike."
)
SENSOR_ABOVE_GROUND = 1.73  # m, where the image goes when the map has no ground under the pose
LIFT = 0.6  # m above the road, clear of its points' squares and kerbs
MARK_ABOVE = 0.4  # m above the higher of the estimate and the truth (the vehicles' outlines)
MARK_SIZE = 1.5  # m, the smallest half-size of a mark: visible around a 4.5 m vehicle
COARSE_CELL = 2 * CELL  # m, the first pass's cells: a quarter of the cells, the same likelihood


def scan_in_sensor_frame(snap: Snapshot) -> np.ndarray:
    """The snapshot's prepared scan back in the sensor frame (it is stored at the estimate)."""
    return transform_points(
        inv_pose(np.asarray(snap.mean_pose, float)), np.asarray(snap.scan_world, np.float32).reshape(-1, 3)
    )


def compute_surface(snap: Snapshot, model: LikelihoodModel, best_over_yaw: bool, cell: float = CELL) -> Surface:
    """The surface around ``snap``'s estimate in ``cell`` metre cells (the work the worker thread
    does, on that thread alone)."""
    return model.surface(
        scan_in_sensor_frame(snap),
        pose_to_xyz_ypr(np.asarray(snap.mean_pose, float)),
        HALF_WIDTH,
        cell,
        YAW_WINDOW if best_over_yaw else 0.0,
        YAW_STEP,
        parallel=False,
    )


def image_height(surface: Surface, ground) -> float:
    """Where the image goes: :data:`LIFT` above the road around the grid's centre (``ground``:
    the scene's :class:`~lidarloc.app.viewer.ground.GroundHeight`, None without a map), so that
    neither the road's points nor a kerb hides it."""
    if ground is None:
        return float(surface.center[2]) - SENSOR_ABOVE_GROUND + LIFT
    return ground.level(float(surface.center[0]), float(surface.center[1])) + LIFT


def marks_height(snap: Snapshot, image_z: float) -> float:
    """Where the marks go: above the vehicles' outlines (drawn at the sensor's height), and above
    the image."""
    z = [float(np.asarray(snap.mean_pose, float)[2, 3])]
    if snap.gt_pose is not None:
        z.append(float(np.asarray(snap.gt_pose, float)[2, 3]))
    z = [v for v in z if math.isfinite(v)]
    return max(z + [image_z]) + MARK_ABOVE


def surface_markdown(surface: Surface, snap: Snapshot) -> str:
    """The panel's read-out: where the maximum is, against the estimate and the truth, and the cost."""
    best = surface.argmax_xy
    est = np.asarray(snap.mean_pose, float)[:2, 3]
    n = len(surface.xs)
    yaws = (
        "one yaw"
        if surface.yaw_window == 0
        else f"best of ±{math.degrees(surface.yaw_window):.0f}° in {math.degrees(YAW_STEP):.0f}° steps"
    )
    lines = [
        f"scan {snap.scan_index}: maximum at ({best[0]:.1f}, {best[1]:.1f}), "
        f"**{np.linalg.norm(best - est):.1f} m** from the estimate"
    ]
    if snap.gt_pose is not None:
        gt = np.asarray(snap.gt_pose, float)[:2, 3]
        x0, y0, x1, y1 = surface.extent
        outside = "" if x0 <= gt[0] <= x1 and y0 <= gt[1] <= y1 else " (outside the grid)"
        lines.append(
            f"truth **{np.linalg.norm(best - gt):.1f} m** from the maximum, "
            f"{np.linalg.norm(est - gt):.1f} m from the estimate{outside}"
        )
    if surface.yaw_window > 0:
        turn = math.degrees(surface.yaw[surface.argmax] - surface.center[3])
        lines.append(f"best yaw there: {turn:+.0f}° from the estimate's")
    lines.append(f"{n}×{n} cells of {surface.cell:g} m, {yaws}: {surface.ms:.0f} ms")
    if surface.cell > CELL:
        lines.append(f"_a first look: the surface in {CELL:g} m cells follows_")
    return "  \n".join(lines)


def _cross(x: float, y: float, z: float, r: float) -> np.ndarray:
    return np.array([[[x - r, y - r, z], [x + r, y + r, z]], [[x - r, y + r, z], [x + r, y - r, z]]], np.float32)


def _ring(x: float, y: float, z: float, r: float, n: int = 24) -> np.ndarray:
    th = np.linspace(0, 2 * np.pi, n + 1)
    pts = np.stack([x + r * np.cos(th), y + r * np.sin(th), np.full_like(th, z)], axis=1).astype(np.float32)
    return np.stack([pts[:-1], pts[1:]], axis=1)


class SurfaceView:
    """Controls (inside the Why folder), the image on the ground and its marks."""

    def __init__(self, scene, gui):
        self.scene = scene
        self._lock = threading.Lock()
        self._image = self._marks = None
        self.last: Surface | None = None
        self.last_snapshot: Snapshot | None = None
        self.button = gui.add_button(
            "Likelihood surface here",
            hint=f"The scan's log-likelihood on ±{HALF_WIDTH:g} m around the estimate: a first look in "
            f"{COARSE_CELL:g} m cells at once, then {CELL:g} m cells",
        )
        self.every_scan = gui.add_checkbox("Surface on every scan", False)
        self.over_yaw = gui.add_checkbox(
            f"Best over yaw (±{math.degrees(YAW_WINDOW):.0f}°)",
            False,
            hint=f"Each cell: the best of the yaws every {math.degrees(YAW_STEP):.0f}° "
            f"within ±{math.degrees(YAW_WINDOW):.0f}° of the estimate's (slower)",
        )
        self.bar = gui.add_html("", visible=False)
        self.readout = gui.add_markdown("")
        gui.add_markdown(
            f"<small>{HELP} {GT_NAME.capitalize()} ×: truth, orange ×: estimate, magenta ring: maximum.</small>"
        )

    @property
    def image(self):
        """The surface's image on the ground (its scene handle), or None while none is drawn."""
        return self._image

    @property
    def marks(self):
        """The truth, estimate and maximum marks (their scene handle), or None."""
        return self._marks

    def draw(self, surface: Surface, snap: Snapshot, ground) -> None:
        """Show a finished surface (any thread). ``ground``: the scene's
        :class:`~lidarloc.app.viewer.ground.GroundHeight` (None without a map)."""
        with self._lock:
            x0, y0, x1, y1 = surface.extent
            z = image_height(surface, ground)
            zm = marks_height(snap, z)
            rgba = surface_rgba(surface.ll)
            # a nearest-neighbour look: upsample so the image filter keeps the cells crisp
            rep = max(1, int(math.ceil(256 / max(rgba.shape[:2]))))
            if rep > 1:
                rgba = np.repeat(np.repeat(rgba, rep, axis=0), rep, axis=1)
            w, h = x1 - x0, y1 - y0
            if self._image is not None:
                self._image.remove()
            self._image = self.scene.add_image(
                "/why/surface",
                rgba,
                w,
                h,
                format="png",
                position=((x0 + x1) / 2, (y0 + y1) / 2, z),
                cast_shadow=False,
                receive_shadow=False,
            )
            r = max(surface.cell, MARK_SIZE)
            segs, colors = [], []
            est = np.asarray(snap.mean_pose, float)[:2, 3]
            marks = [(_cross(est[0], est[1], zm, r), EST_COLOR)]
            if snap.gt_pose is not None:
                gt = np.asarray(snap.gt_pose, float)[:2, 3]
                marks.append((_cross(gt[0], gt[1], zm, r), GT_COLOR))
            best = surface.argmax_xy
            marks.append((_ring(best[0], best[1], zm, 1.5 * r), SURFACE_BEST_COLOR))
            for s, c in marks:
                segs.append(s)
                colors.append(np.broadcast_to(np.asarray(c, np.uint8), s.shape).copy())
            segs, colors = np.concatenate(segs), np.concatenate(colors)
            if self._marks is not None:
                self._marks.remove()
            self._marks = self.scene.add_line_segments(
                "/why/surface_marks", segs, colors, thickness=4.0, thickness_units="screen"
            )
            lo, hi = surface_scale(surface.ll)
            self.bar.content = colour_bar_html(SURFACE_LUT, f"≤ max − {hi - lo:,.0f} nats", f"max {hi:,.0f}")
            self.bar.visible = True
            self.readout.content = surface_markdown(surface, snap)
            self.last, self.last_snapshot = surface, snap

    def busy(self, scan_index: int) -> None:
        """Say that a surface is being computed (the old one stays drawn until the new one is in)."""
        with self._lock:
            if self.last is None:
                self.readout.content = f"computing the surface of scan {scan_index}…"

    def failed(self, message: str) -> None:
        with self._lock:
            self.readout.content = f"surface failed: {message}"

    def clear(self) -> None:
        with self._lock:
            for node in (self._image, self._marks):
                if node is not None:
                    node.remove()
            self._image = self._marks = None
            self.last = self.last_snapshot = None
            self.bar.visible = False
            self.readout.content = ""

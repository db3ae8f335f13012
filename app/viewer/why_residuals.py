"""The scan-residual view: the current scan placed at the estimate, at the inspected particle or at
the truth, each point coloured by its lookup-table distance to the map (green ≤ σ, red ≥ d_max),
and the share of points beyond d_max in the panel.

One lookup per point (~15k points, well under a millisecond, numba), so it is drawn on the
display thread with the scan it belongs to."""

from __future__ import annotations

import threading

import numpy as np

from ...core.filter.residuals import Residuals, move_scan, scan_residuals
from ...core.filter.surface import LikelihoodModel
from ...core.snapshot import Snapshot
from .why_style import RESIDUAL_LUT, colour_bar_html, residual_colors

AT_ESTIMATE, AT_PARTICLE, AT_TRUTH = "estimate", "inspected particle", "truth"
AT_CHOICES = (AT_ESTIMATE, AT_PARTICLE, AT_TRUTH)
HELP = (
    "Red clusters: things the map does not have (cars, changes). Red everywhere: a wrong pose, or d_max / σ too small."
)
POINT_SIZE = 0.32  # a little larger than the green scan's 0.25 m, so it covers it


def residual_markdown(res: Residuals | None, where: str, note: str = "") -> str:
    """The panel's read-out of one residual view."""
    if res is None:
        return note or "*off*"
    n = len(res.distance)
    med = float(np.median(res.distance))
    return (
        f"at the {where}: **{res.share_beyond:.1%}** of {n:,} points beyond d_max ({res.d_max:.1f} m), "
        f"median distance {med:.2f} m" + (f"  \n{note}" if note else "")
    )


class ResidualView:
    """Controls (inside the Why folder) and the coloured cloud."""

    def __init__(self, scene, gui):
        self.scene = scene
        self._lock = threading.Lock()
        self._cloud = None
        self.last: Residuals | None = None
        self.enabled = gui.add_checkbox(
            "Show residuals", False, hint="Colour the current scan by its distance to the map"
        )
        self.at = gui.add_dropdown("Residuals at", AT_CHOICES, initial_value=AT_ESTIMATE)
        self.bar = gui.add_html(colour_bar_html(RESIDUAL_LUT, "≤ σ", "≥ d_max"), visible=False)
        self.readout = gui.add_markdown("*off*")
        gui.add_markdown(f"<small>{HELP}</small>")

    @property
    def cloud(self):
        """Its scene handle, or None while nothing is drawn."""
        return self._cloud

    def show(self, snap: Snapshot | None, model: LikelihoodModel | None, particle_pose: np.ndarray | None) -> None:
        """Draw the residuals of ``snap``'s scan at the chosen pose (hide them when off)."""
        with self._lock:
            if not self.enabled.value or snap is None or model is None:
                self._hide("*off*" if not self.enabled.value else "waiting for the first scan")
                return
            where = self.at.value
            pose, note = self._pose(snap, where, particle_pose)
            if pose is None:
                self._hide(note)
                return
            pts = np.asarray(snap.scan_world, np.float32).reshape(-1, 3)
            if len(pts) == 0:
                self._hide("no scan yet: play or step")
                return
            if where != AT_ESTIMATE:
                pts = move_scan(pts, snap.mean_pose, pose)
            res = scan_residuals(pts, model.lookup, model.d_max)
            colors = residual_colors(res.distance, model.sigma, res.d_max)
            self.last = res
            if self._cloud is None:
                self._cloud = self.scene.add_point_cloud(
                    "/why/residuals",
                    res.points,
                    colors,
                    point_size=POINT_SIZE,
                    precision="float32",
                    point_shading="flat",
                )
            else:
                self._cloud.points, self._cloud.colors = res.points, colors
                self._cloud.visible = True
            self.bar.visible = True
            self.readout.content = residual_markdown(res, where)

    @staticmethod
    def _pose(snap: Snapshot, where: str, particle_pose):
        if where == AT_TRUTH:
            if snap.gt_pose is None:
                return None, "no ground truth for this scan"
            return np.asarray(snap.gt_pose, float), ""
        if where == AT_PARTICLE:
            if particle_pose is None:
                return None, "no particle inspected: click one in the scene or press **Best particle**"
            return np.asarray(particle_pose, float), ""
        return np.asarray(snap.mean_pose, float), ""

    def _hide(self, note: str) -> None:
        if self._cloud is not None:
            self._cloud.visible = False
        self.last = None
        self.bar.visible = False
        self.readout.content = note

    def clear(self) -> None:
        with self._lock:
            if self._cloud is not None:
                self._cloud.remove()
                self._cloud = None
            self.last = None
            self.bar.visible = False
            self.readout.content = "*off*" if not self.enabled.value else "waiting for the first scan"

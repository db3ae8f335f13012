"""Inspect one particle: picked by a click near it in the scene (or the "Best particle" button),
its 11 states in the paper's units (degrees for angles), its weight, its log-likelihood for the
current scan and its rank among all particles by that log-likelihood; it is marked in blue in the
scene, and the residual view can show the scan at its pose.

Particle indices change at every resampling, so a pick follows the particle: on each new scan
the inspected one is the particle nearest to the last inspected state (x, y and heading), or the
best particle again when "Best particle" picked it. The log-likelihoods of all particles (the
filter's kernel, ~1000 × 15k points) are computed on the views' worker thread."""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass

import numpy as np

from ...core.config import ANGULAR_STATE, STATE_NAMES
from ...core.errors import LidarlocError
from ...core.filter.surface import LikelihoodModel
from ...core.geometry import pose_matrix, wrap_angle
from ...core.snapshot import Snapshot
from .params import q_units
from .why_style import SELECTED_COLOR
from .why_surface import scan_in_sensor_frame

HELP = "Click near a particle in the scene to inspect it (shift+click still resets)."
PICK_MIN_M = 2.0  # a click this close to a particle picks it, however far the camera …
PICK_ANGLE = 0.03  # … or within this share of the distance to the camera (~1.7°)
HEADING_M_PER_RAD = 2.0  # following a pick: 1 rad of heading counts as 2 m of distance


class NoParticleNear(LidarlocError):
    """A click that is not on a particle (a plain click in the scene is often just a look around)."""


def pick_particle(particles: np.ndarray, ray_origin, ray_direction) -> int:
    """Index of the particle nearest to a click's ray (within PICK_MIN_M or PICK_ANGLE of it);
    LidarlocError when none is that near."""
    P = np.asarray(particles, float)[:, :3]
    if len(P) == 0:
        raise LidarlocError("there are no particles to inspect yet")
    o = np.asarray(ray_origin, float)
    d = np.asarray(ray_direction, float)
    d = d / np.linalg.norm(d)
    rel = P - o
    along = rel @ d
    off = np.linalg.norm(rel - along[:, None] * d, axis=1)
    off[along <= 0] = np.inf  # behind the camera
    reach = np.maximum(PICK_MIN_M, PICK_ANGLE * along)
    j = int(np.argmin(np.where(off <= reach, off, np.inf)))
    if not off[j] <= reach[j]:
        raise NoParticleNear("no particle near that click: click on a particle's dot or arrow")
    return j


def follow_particle(particles: np.ndarray, state: np.ndarray) -> int:
    """The particle nearest to ``state`` in x, y and heading."""
    P = np.asarray(particles, float)
    d_xy = np.linalg.norm(P[:, :2] - state[:2], axis=1)
    d_yaw = np.abs(wrap_angle(P[:, 3] - state[3]))
    return int(np.argmin(d_xy + HEADING_M_PER_RAD * d_yaw))


@dataclass(frozen=True)
class ParticleReport:
    index: int
    scan_index: int
    state: np.ndarray  # (11,) SI
    weight: float
    best_weight: float
    log_likelihood: float  # for the snapshot's scan, the filter's kernel
    best_log_likelihood: float
    rank: int  # 1 = the highest log-likelihood (ties share a rank)
    n: int
    copies: int  # particles with exactly this state (resampling copies), itself included
    origin: tuple = (0.0, 0.0, 0.0)  # the map file's origin: x, y, z are shown in the map's own frame


def particle_report(snap: Snapshot, j: int, model: LikelihoodModel, origin=(0.0, 0.0, 0.0)) -> ParticleReport:
    """Particle ``j`` of ``snap`` with its log-likelihood and rank (the heavy part: every
    particle's log-likelihood for the scan). ``origin``: the prior map's (a georeferenced map
    file's local frame is its own minus this)."""
    P = np.asarray(snap.particles, float)
    if not 0 <= j < len(P):
        raise LidarlocError(f"particle {j} is not in this scan's {len(P)} particles")
    pts = scan_in_sensor_frame(snap)
    ll = model.log_likelihood(P, pts) if len(pts) else np.zeros(len(P))
    w = np.asarray(snap.weights, float)
    rank = int(np.sum(ll > ll[j])) + 1
    copies = int(np.sum(np.all(P == P[j], axis=1)))
    return ParticleReport(
        index=j,
        scan_index=snap.scan_index,
        state=P[j].copy(),
        weight=float(w[j]),
        best_weight=float(w.max()),
        log_likelihood=float(ll[j]),
        best_log_likelihood=float(ll.max()),
        rank=rank,
        n=len(P),
        copies=copies,
        origin=tuple(float(v) for v in origin),
    )


def particle_markdown(r: ParticleReport) -> str:
    """The 11 states in the paper's units, the weight, the log-likelihood and the rank."""
    units = q_units()
    rows = []
    shift = np.zeros(len(r.state))
    shift[:3] = r.origin  # positions in the map file's own coordinates
    for name, unit, angular, v in zip(STATE_NAMES, units, ANGULAR_STATE, r.state + shift):
        shown = math.degrees(v) if angular else v
        rows.append(f"| {name} | {shown:.3f} {unit} |")
    gap = r.log_likelihood - r.best_log_likelihood
    copies = (
        f"  \n{r.copies} of the {r.n} particles are copies of it (resampling duplicates the heavy ones)"
        if r.copies > 1
        else ""
    )
    return (
        f"**particle {r.index}** of {r.n} at scan {r.scan_index}: rank **{r.rank}** by log-likelihood  \n"
        f"log-likelihood {r.log_likelihood:,.1f} ({gap:,.1f} from the best)  \n"
        f"weight {r.weight:.3g} (heaviest {r.best_weight:.3g}){copies}\n\n"
        "| state | value |\n|---|---|\n" + "\n".join(rows)
    )


def _marker(state: np.ndarray) -> np.ndarray:
    """A ring round the particle and its heading arrow (line segments)."""
    x, y, z, yaw = (float(v) for v in state[:4])
    th = np.linspace(0, 2 * np.pi, 25)
    ring = np.stack([x + 1.6 * np.cos(th), y + 1.6 * np.sin(th), np.full_like(th, z)], axis=1)
    h = np.array([math.cos(yaw), math.sin(yaw), 0.0])
    side = np.array([-h[1], h[0], 0.0])
    p = np.array([x, y, z])
    t = p + 6.0 * h
    arrow = [[p, t], [t, t - 1.8 * h + 1.1 * side], [t, t - 1.8 * h - 1.1 * side]]
    return np.concatenate([np.stack([ring[:-1], ring[1:]], axis=1), np.array(arrow)]).astype(np.float32)


class ParticleInspector:
    """Controls (inside the Why folder), the selection and its marker."""

    def __init__(self, scene, gui):
        self.scene = scene
        self._lock = threading.Lock()
        self._marker = None
        self.index: int | None = None  # in the snapshot it was last resolved for
        self.state: np.ndarray | None = None
        self.follow_best = False
        self.report: ParticleReport | None = None
        self.best = gui.add_button("Best particle", hint="Inspect the highest-weight particle (and keep to it)")
        self.details = gui.add_markdown("")
        gui.add_markdown(f"<small>{HELP}</small>")

    @property
    def marker(self):
        """Its scene handle, or None while nothing is drawn."""
        return self._marker

    @property
    def selected(self) -> bool:
        return self.state is not None

    @property
    def pose(self) -> np.ndarray | None:
        """4×4 pose of the inspected particle (None when none is)."""
        s = self.state
        return None if s is None else pose_matrix(*s[:6])

    def select(self, snap: Snapshot, j: int, follow_best: bool) -> None:
        with self._lock:
            self.index, self.state, self.follow_best = int(j), np.asarray(snap.particles[j], float).copy(), follow_best
            self._draw_marker()
            self.details.content = f"particle {j}: computing its log-likelihood and rank…"

    def resolve(self, snap: Snapshot) -> int | None:
        """Re-find the inspected particle in a new snapshot (see the module docstring)."""
        with self._lock:
            if self.state is None or len(snap.particles) == 0:
                return None
            P = np.asarray(snap.particles, float)
            if self.follow_best and 0 <= snap.best_index < len(P):
                j = int(snap.best_index)
            else:
                j = follow_particle(P, self.state)
            self.index, self.state = j, P[j].copy()
            self._draw_marker()
            return j

    def show(self, report: ParticleReport) -> None:
        with self._lock:
            if self.state is None:
                return
            self.report = report
            self.details.content = particle_markdown(report)

    def failed(self, message: str) -> None:
        with self._lock:
            self.details.content = f"inspection failed: {message}"

    def _draw_marker(self) -> None:
        segs = _marker(self.state)
        if self._marker is None:
            self._marker = self.scene.add_line_segments(
                "/why/inspected_particle", segs, SELECTED_COLOR, thickness=4.0, thickness_units="screen"
            )
        else:
            self._marker.points = segs
            self._marker.visible = True

    def clear(self) -> None:
        with self._lock:
            if self._marker is not None:
                self._marker.remove()
                self._marker = None
            self.index = self.state = self.report = None
            self.follow_best = False
            self.details.content = ""

"""The last scan-to-map match in detail: where it started, the best poses its branch and bound
scored, what GICP made of the 2D match, the pose carried forward to the scan it landed at, and
why it was accepted or rejected — drawn in the scene under ``/s2m_detail/…`` and summed up as a
markdown table for the panel.

Only the newest match that landed is shown; a new one replaces it. The scene's own S2M layer
(its scan and search rectangle, :mod:`~lidarloc.app.viewer.scene`) stays as it is: this view adds
the inside of the search on top of it. Everything is redrawn only when another match has landed,
so calling :meth:`S2MDetailView.draw` on every display update costs a comparison.
"""

from __future__ import annotations

import math
import threading

import numpy as np

from ...core.geometry import pose_to_xyz_ypr
from ...core.matching.m3rsm import N_CANDIDATES
from ...core.snapshot import S2MView

ROOT = "/s2m_detail"

# Hues the rest of the scene does not use (style.py: green scan, magenta / grey S2M scan, cyan
# best particle, red ellipse and particles, lime truth, orange estimate, yellow BEV, blue map).
CANDIDATE_COLOR = (150, 100, 255)  # violet: the poses the search scored
WINNER_COLOR = (225, 210, 255)  # pale violet, drawn bigger: the best of them, the 2D match
START_COLOR = (255, 105, 180)  # pink: the particle's pose the match started from
REFINED_COLOR = (110, 255, 215)  # aquamarine: GICP's pose (and the line from the 2D match),
# ringed where the match was carried forward to

CANDIDATE_ARROW = 1.5  # m, length of a candidate's arrow …
CANDIDATE_WIDTH = 0.06  # m, … and its shaft radius
WINNER_ARROW = 3.0
WINNER_WIDTH = 0.15
POSE_ARROW = 2.5  # the start, GICP and carried-forward poses
POSE_WIDTH = 0.1
RING_RADIUS = 1.2  # m, around the carried-forward pose
LIFT = 0.05  # m above the plane of the search, so the arrows do not flicker in it


def _arrows(xy: np.ndarray, yaw: np.ndarray, z, length: float) -> np.ndarray:
    """(N, 2, 3) start and end points of arrows from (x, y, z) along yaw (viser's arrow layout)."""
    xy = np.asarray(xy, float).reshape(-1, 2)
    yaw = np.asarray(yaw, float).reshape(-1)
    z = np.broadcast_to(np.asarray(z, float), yaw.shape)
    tail = np.column_stack([xy, z])
    tip = tail + length * np.column_stack([np.cos(yaw), np.sin(yaw), np.zeros_like(yaw)])
    return np.stack([tail, tip], axis=1).astype(np.float32)


def _ring(x: float, y: float, z: float, r: float = RING_RADIUS, n: int = 20) -> np.ndarray:
    t = np.linspace(0, 2 * math.pi, n + 1)
    p = np.stack([x + r * np.cos(t), y + r * np.sin(t), np.full_like(t, z)], axis=1)
    return np.stack([p[:-1], p[1:]], axis=1)


def _xyyaw(T) -> tuple[float, float, float, float] | None:
    """(x, y, z, yaw) of a 4×4 pose, None if absent or not finite."""
    if T is None:
        return None
    T = np.asarray(T, float)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        return None
    x, y, z, yaw, _, _ = pose_to_xyz_ypr(T)
    return float(x), float(y), float(z), float(yaw)


def carried_pose(view: S2MView):
    """(x, y, z, yaw) of the match carried forward to the landing scan, None if it never was: a
    match refused by the search or GICP keeps its start pose. One refused at the landing (its
    particle's weight would drop) was carried forward, and is shown as where it would have gone."""
    if view.accepted or (view.start_pose is not None and not np.array_equal(view.pose, view.start_pose)):
        return _xyyaw(view.pose)
    return None


class S2MDetailView:
    """The last match's search and refinement in the scene (``scene`` is ``server.scene``; nodes
    under ``/s2m_detail``, shared by every tab like the rest of the scene)."""

    def __init__(self, scene):
        self.scene = scene
        self._lock = threading.Lock()
        self._root = None
        self._handles: dict[str, object] = {}
        self._shown: S2MView | None = None  # the view the scene holds
        self._pending: S2MView | None = None  # the newest view asked for (drawn once visible)
        self._visible = True

    # ---------------------------------------------------------------------------- public
    def draw(self, view: S2MView | None, visible: bool) -> None:
        """Show ``view`` (the last match that landed; None: none has, and the scene is emptied).
        While not visible, nothing is sent: the newest view is drawn when it becomes visible."""
        with self._lock:
            self._pending = view
            self._visible = bool(visible)
            if view is None:
                self._clear_locked()
                return
            if self._visible and view is not self._shown:
                self._build_locked(view)
            if self._root is not None and self._root.visible != self._visible:
                self._root.visible = self._visible

    def set_visible(self, visible: bool) -> None:
        with self._lock:
            self._visible = bool(visible)
            if self._visible and self._pending is not None and self._pending is not self._shown:
                self._build_locked(self._pending)
            if self._root is not None:
                self._root.visible = self._visible

    def clear(self) -> None:
        """Remove every node of this view (a restarted run has no last match)."""
        with self._lock:
            self._pending = None
            self._clear_locked()

    @property
    def node_names(self) -> list[str]:
        """Names of the scene nodes this view holds now (its root first)."""
        with self._lock:
            return ([ROOT] if self._root is not None else []) + sorted(self._handles)

    def handle(self, name: str):
        """The scene handle of the node ``name`` (``ROOT`` or ``ROOT/part``), None when not drawn."""
        with self._lock:
            return self._root if name == ROOT else self._handles.get(name)

    # ---------------------------------------------------------------------------- drawing
    def _clear_locked(self) -> None:
        if self._root is not None:
            self._root.remove()  # removes every child with it
        self._root = None
        self._handles = {}
        self._shown = None

    def _put(self, name: str, points: np.ndarray | None, color, width: float = 0.0) -> None:
        """Add (or replace) ``ROOT/name``: arrows of shaft radius ``width`` (m), or line segments
        (width 0); remove the node when there is nothing to draw."""
        full = f"{ROOT}/{name}"
        if points is None or len(points) == 0:
            old = self._handles.pop(full, None)
            if old is not None:
                old.remove()
            return
        if width > 0:
            self._handles[full] = self.scene.add_arrows(
                full, points, color, shaft_radius=width, head_radius=2.5 * width, head_length=6.0 * width
            )
        else:
            self._handles[full] = self.scene.add_line_segments(
                full, points, color, thickness=2.0, thickness_units="screen"
            )

    def _build_locked(self, view: S2MView) -> None:
        if self._root is None:
            self._root = self.scene.add_frame(ROOT, show_axes=False, visible=self._visible)
        carried = carried_pose(view)
        start = _xyyaw(view.start_pose)
        match = _xyyaw(view.match_pose)
        refined = _xyyaw(view.gicp_pose)
        # the candidates lie in the search's plane: the scene draws the search rectangle at the
        # carried-forward pose's height, so they go there too
        ref = _xyyaw(view.pose) or start or match
        plane_z = (ref[2] if ref is not None else 0.0) + LIFT
        c = np.asarray(view.candidates, float).reshape(-1, 4)
        c = c[np.isfinite(c).all(axis=1)]
        others = None
        if len(c) > 1:
            # dimmer the lower the score: the ranking reads at a glance
            lo, hi = c[1:, 3].min(), c[0, 3]
            t = np.clip((c[1:, 3] - lo) / max(hi - lo, 1e-9), 0.0, 1.0)[:, None]
            others = ((0.45 + 0.55 * t) * np.asarray(CANDIDATE_COLOR, float)).astype(np.uint8)
        self._put(
            "candidates",
            _arrows(c[1:, :2], c[1:, 2], plane_z, CANDIDATE_ARROW) if len(c) > 1 else None,
            others,
            CANDIDATE_WIDTH,
        )
        self._put(
            "winner",
            _arrows(c[:1, :2], c[:1, 2], plane_z + LIFT, WINNER_ARROW) if len(c) else None,
            WINNER_COLOR,
            WINNER_WIDTH,
        )
        self._put(
            "start",
            None if start is None else _arrows(start[:2], start[3], start[2], POSE_ARROW),
            START_COLOR,
            POSE_WIDTH,
        )
        self._put(
            "refined",
            None if refined is None else _arrows(refined[:2], refined[3], refined[2], POSE_ARROW),
            REFINED_COLOR,
            POSE_WIDTH,
        )
        self._put(
            "refine_line",
            None if refined is None or match is None else np.array([[match[:3], refined[:3]]], np.float32),
            REFINED_COLOR,
        )
        self._put(
            "carried",
            None if carried is None else _arrows(carried[:2], carried[3], carried[2], POSE_ARROW),
            REFINED_COLOR,
            POSE_WIDTH,
        )
        self._put(
            "carried_ring",
            None if carried is None else _ring(carried[0], carried[1], carried[2]).astype(np.float32),
            REFINED_COLOR,
        )
        self._root.visible = self._visible
        self._shown = view


# ------------------------------------------------------------------------------------ panel text
def _swatch(rgb, glyph: str = "➜") -> str:
    return "<span style='color:#{:02x}{:02x}{:02x}'>{}</span>".format(*(int(v) for v in rgb), glyph)


#: What each colour of this view means, for the panel beside the table.
LEGEND_MARKDOWN = (
    f"{_swatch(WINNER_COLOR)} best pose of the search (the 2D match) · "
    f"{_swatch(CANDIDATE_COLOR)} the next best it scored (dimmer: lower score) · "
    f"{_swatch(START_COLOR)} start (the particle) · "
    f"{_swatch(REFINED_COLOR)} after GICP, ringed where it was carried forward to"
)


def _num(v: float, fmt: str = ".0f") -> str:
    return "–" if v is None or not math.isfinite(v) else format(v, fmt)


def _pose_text(p) -> str:
    return "–" if p is None else f"{p[0]:.1f}, {p[1]:.1f} m, {math.degrees(p[3]):.1f}°"


def _carried_text(view: S2MView) -> str:
    carried = carried_pose(view)
    if carried is None:
        return "– (nothing to carry)"
    return _pose_text(carried) + ("" if view.accepted else " (not written)")


def _cell(text: str) -> str:
    """Safe inside a markdown table cell."""
    return " ".join(str(text).split()).replace("|", "/")


def verdict_text(view: S2MView) -> str:
    """Why the match was accepted (from the scores and GICP's figures) or rejected (its reason)."""
    if not view.accepted:
        return f"**rejected**: {view.reason or 'no reason given'}"
    if view.stage == "refined_start":
        why = (
            f"no pose of the search beat the start ({_num(view.start_score)}), the start refined by GICP "
            f"scored {_num(view.score)}"
        )
    elif math.isfinite(view.start_score):
        why = f"the 2D match scored {_num(view.score)} > the start's {_num(view.start_score)}"
    else:
        why = f"the best pose of the whole map scored {_num(view.score)}"
    if len(view.gicp_correction) == 2:
        why += f"; GICP kept it local ({view.gicp_correction[0]:.2f} m, {math.degrees(view.gicp_correction[1]):.1f}°)"
    return f"**accepted**: {why}"


def _places_rows(view: S2MView, match) -> list[tuple[str, str]]:
    """A whole-map match by candidates: the places it verified with their scores, its answer
    first (for an "ambiguous" answer, every place it could not tell apart)."""
    if view.search != "candidates":
        return []
    others = np.asarray(view.alternatives, float).reshape(-1, 4)
    places = [] if match is None else [f"**{_num(view.score)}** at {match[0]:.1f}, {match[1]:.1f} m"]
    places += [f"{_num(s)} at {x:.1f}, {y:.1f} m" for x, y, _, s in others]
    label = "places (ambiguous)" if view.ambiguous else "places verified"
    return [(label, " · ".join(places) or "–")]


def s2m_detail_markdown(view: S2MView | None) -> str:
    """The last match as a compact markdown table (degrees and metres, as the panel shows them)."""
    if view is None:
        return "S2M: no match has landed yet"
    x0, y0, x1, y1 = (float(v) for v in view.region) if len(view.region) == 4 else (math.nan,) * 4
    mode = {"global": "whole map", "local": "around the particle"}.get(view.mode, view.mode or "–")
    c = np.asarray(view.candidates, float).reshape(-1, 4)
    nodes = view.nodes_per_level
    nodes_text = (
        (" · ".join(f"L{lv} {n}" for lv, n in enumerate(nodes) if n) or "none") + f" (total {sum(nodes)})"
        if nodes
        else "–"
    )
    best = " · ".join(_num(s) for s in c[:, 3]) if len(c) else "–"
    start = _xyyaw(view.start_pose)
    match = _xyyaw(view.match_pose)
    refined = _xyyaw(view.gicp_pose)
    if refined is not None:
        moved, turned = (view.gicp_correction + (math.nan, math.nan))[:2]
        source = "the start" if view.stage == "refined_start" else "2D match"
        gicp = (
            f"{source} {_pose_text(match)} → {_pose_text(refined)}: moved {_num(moved, '.2f')} m, "
            f"turned {_num(math.degrees(turned), '.1f')}°"
        )
        fitness = "–" if view.gicp_fitness is None else f"{100 * view.gicp_fitness:.0f} %"
    else:
        gicp, fitness = "not run", "–"
    search = f"{mode}, {_num(x1 - x0)} × {_num(y1 - y0)} m from {_pose_text(start)}"
    if view.search == "candidates":
        search = f"whole map by the place index's candidates, their windows within {_num(x1 - x0)} × {_num(y1 - y0)} m"
    elif view.search == "exact":
        search = f"whole map, exact (the whole-map branch and bound) from {_pose_text(start)}"
    rows = [
        ("scans", f"started {view.started_at} → landed {view.landed_at}, {view.ms:.0f} ms"),
        ("search", search),
        ("nodes expanded", nodes_text),
        (
            "best scores",
            f"{best} (start {_num(view.start_score)})"
            + (
                f"; only {len(c)} scored at the finest level, the rest pruned higher up"
                if 0 < len(c) < N_CANDIDATES
                else ""
            ),
        ),
        *_places_rows(view, match),
        ("GICP", gicp),
        ("GICP fitness", fitness),
        (f"carried to scan {view.landed_at}", _carried_text(view)),
        ("verdict", verdict_text(view)),
    ]
    return "\n".join(["| S2M | last match |", "|---|---|"] + [f"| {k} | {_cell(v)} |" for k, v in rows])

"""The panel's overview: a small top-down image of the whole map (where the map has points, in
grey), the particles as red dots, the estimate and the truth as markers, the places the last
whole-map match verified (an "ambiguous" answer shows every place it found), and the tiles shown
at full density outlined. Rendered here with numpy; the panel only shows the image."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ...core.snapshot import Snapshot
from .style import (
    EST_COLOR,
    GT_COLOR,
    MINIMAP_INTERVAL_S,
    MINIMAP_PX,
    PARTICLE_HIGH,
    PLACE_ANSWER_COLOR,
    PLACE_OTHER_COLOR,
    TILE_COLOR,
)

BACKGROUND = (22, 24, 30)
GREY_LOW, GREY_HIGH = 70, 200  # grey of the emptiest and of the fullest pixel with map points
OUTLINE = (0, 0, 0)  # round the markers, so they stand out on the grey and the dots


@dataclass(frozen=True, eq=False)
class Footprint:
    """The map seen from above: ``base`` (H, W, 3) uint8 with the map's occupancy in grey, its
    bottom-left corner at world (x0, y0), ``scale`` metres a pixel; row 0 is the top (largest y)."""

    base: np.ndarray
    x0: float
    y0: float
    scale: float

    @classmethod
    def of_points(cls, points: np.ndarray, lo, hi, size: int = MINIMAP_PX) -> Footprint:
        """The footprint of ``points`` (any thinned copy of the map) in a square image of
        ``size`` pixels round the box lo–hi, with a small margin."""
        lo, hi = np.asarray(lo, float)[:2], np.asarray(hi, float)[:2]
        side = max(float((hi - lo).max()), 1.0) * 1.04
        center = (lo + hi) / 2.0
        scale = side / size
        x0, y0 = float(center[0] - side / 2), float(center[1] - side / 2)
        fp = cls(np.zeros((size, size, 3), np.uint8), x0, y0, scale)
        rows, cols, inside = fp.pixels(np.asarray(points)[:, :2])
        counts = np.bincount(rows[inside] * size + cols[inside], minlength=size * size).reshape(size, size)
        grey = GREY_LOW + (GREY_HIGH - GREY_LOW) * np.log1p(counts) / max(math.log1p(int(counts.max())), 1e-9)
        base = np.repeat(grey.astype(np.uint8)[..., None], 3, axis=2)
        base[counts == 0] = BACKGROUND
        return cls(base, x0, y0, scale)

    @property
    def size(self) -> tuple[int, int]:
        return self.base.shape[0], self.base.shape[1]

    def pixels(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(rows, cols, inside) of world points (N, 2)."""
        xy = np.asarray(xy, np.float64).reshape(-1, 2)
        h, w = self.size
        with np.errstate(invalid="ignore"):
            cols = np.floor((xy[:, 0] - self.x0) / self.scale)
            rows = h - 1 - np.floor((xy[:, 1] - self.y0) / self.scale)
        inside = np.isfinite(cols) & np.isfinite(rows) & (cols >= 0) & (cols < w) & (rows >= 0) & (rows < h)
        rows = np.where(inside, rows, 0).astype(np.int64)
        cols = np.where(inside, cols, 0).astype(np.int64)
        return rows, cols, inside


def _square(img: np.ndarray, r: int, c: int, half: int, color, hollow: bool = False) -> None:
    h, w = img.shape[:2]
    r0, r1, c0, c1 = max(r - half, 0), min(r + half + 1, h), max(c - half, 0), min(c + half + 1, w)
    if r0 >= r1 or c0 >= c1:
        return
    if not hollow:
        img[r0:r1, c0:c1] = color
        return
    for rr in (r - half, r + half):
        if 0 <= rr < h:
            img[rr, c0:c1] = color
    for cc in (c - half, c + half):
        if 0 <= cc < w:
            img[r0:r1, cc] = color


def render(
    fp: Footprint,
    particles_xy: np.ndarray | None = None,
    estimate_xy=None,
    truth_xy=None,
    tiles=(),
    places=(),
) -> np.ndarray:
    """The overview image (H, W, 3) uint8: the footprint, the ``tiles`` ((x0, y0, x1, y1) each)
    outlined, the particles as 3-pixel dots, the ``places`` a whole-map match verified ((x, y,
    colour) each) as hollow squares, the truth as a hollow square and the estimate as a filled
    one on top (each marker outlined in black)."""
    img = fp.base.copy()
    h, w = fp.size
    for x0, y0, x1, y1 in tiles:
        (r1, r0), (c0, c1), _ = fp.pixels(np.array([[x0, y0], [x1 - 1e-6, y1 - 1e-6]]))
        r0, r1 = int(np.clip(r0, 0, h - 1)), int(np.clip(r1, 0, h - 1))
        c0, c1 = int(np.clip(c0, 0, w - 1)), int(np.clip(c1, 0, w - 1))
        img[r0, c0 : c1 + 1] = img[r1, c0 : c1 + 1] = TILE_COLOR
        img[r0 : r1 + 1, c0] = img[r0 : r1 + 1, c1] = TILE_COLOR
    if particles_xy is not None and len(particles_xy):
        rows, cols, inside = fp.pixels(particles_xy)
        rows, cols = rows[inside], cols[inside]
        color = np.asarray(PARTICLE_HIGH, np.uint8)
        for dr in (-1, 0, 1):
            for dc in (-1, 0, 1):
                rr, cc = rows + dr, cols + dc
                ok = (rr >= 0) & (rr < h) & (cc >= 0) & (cc < w)
                img[rr[ok], cc[ok]] = color
    marks = [((x, y), 7, color, True) for x, y, color in places]
    marks += [(truth_xy, 5, GT_COLOR, True), (estimate_xy, 3, EST_COLOR, False)]
    for xy, half, color, hollow in marks:
        if xy is None:
            continue
        rows, cols, inside = fp.pixels(np.asarray(xy, float)[:2])
        if not inside[0]:
            continue
        r, c = int(rows[0]), int(cols[0])
        if hollow:
            _square(img, r, c, half + 1, OUTLINE, hollow=True)
            _square(img, r, c, half - 1, OUTLINE, hollow=True)
            _square(img, r, c, half, color, hollow=True)
        else:
            _square(img, r, c, half + 1, OUTLINE)
            _square(img, r, c, half, color)
    return img


def verified_places(view) -> list[tuple[float, float, tuple]]:
    """The places a whole-map match by candidates verified, for the overview: its answer (the
    2D match) and the other distinct places, each (x, y, colour); none for any other match."""
    if view is None or getattr(view, "search", "") != "candidates":
        return []
    others = np.asarray(getattr(view, "alternatives", np.zeros((0, 4))), float).reshape(-1, 4)
    ambiguous = bool(getattr(view, "ambiguous", False))
    out = []
    best = _finite_xy(view.match_pose)
    if best is not None:
        out.append((float(best[0]), float(best[1]), PLACE_OTHER_COLOR if ambiguous else PLACE_ANSWER_COLOR))
    out += [(float(x), float(y), PLACE_OTHER_COLOR) for x, y, _, _ in others if math.isfinite(x) and math.isfinite(y)]
    return out


def _finite_xy(T) -> np.ndarray | None:
    if T is None:
        return None
    p = np.asarray(T, float)[:2, 3]
    return p if np.isfinite(p).all() else None


class Overview:
    """The overview image in the panel (``handle``: viser's GUI image, or anything with an
    ``image`` and a ``visible``): redrawn at most every ``interval`` seconds, and only when the
    map, the snapshot shown or the tiles at full density changed."""

    def __init__(self, handle, interval: float = MINIMAP_INTERVAL_S):
        self.handle, self.interval = handle, interval
        self.footprint: Footprint | None = None
        self._shown: tuple | None = None
        self._last = -math.inf
        self.renders = 0

    def set_map(self, footprint: Footprint | None) -> None:
        """A new map (any thread): the next :meth:`update` draws it."""
        self.footprint = footprint

    def update(self, snap: Snapshot | None, tiles: tuple, now: float) -> bool:
        """Redraw if something changed and the last drawing is old enough; True if it did."""
        fp = self.footprint
        if fp is None:
            return False
        last = self._shown
        if last is not None and last[0] is fp and last[1] is snap and last[2] == tiles:
            return False
        if now - self._last < self.interval:
            return False
        P = None if snap is None else np.asarray(snap.particles)
        particles = P[:, :2] if P is not None and P.ndim == 2 and len(P) else None
        est = None if snap is None else _finite_xy(snap.mean_pose)
        truth = None if snap is None else _finite_xy(snap.gt_pose)
        places = verified_places(getattr(snap, "s2m", None))
        self.handle.image = render(fp, particles, est, truth, tiles, places)
        if not self.handle.visible:
            self.handle.visible = True
        self._shown, self._last = (fp, snap, tiles), now
        self.renders += 1
        return True

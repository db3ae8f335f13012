"""Colours of the "why" views: the residual ramp (green where the map explains a point, red where
it does not), the likelihood surface's colour map, the selected particle, and their colour bars
for the panel. Shared by the viewer and by ``lidarloc inspect``'s images."""

from __future__ import annotations

import numpy as np

RESIDUAL_GOOD = np.array([40, 220, 70], np.float32)  # ≤ σ: the map explains the point
RESIDUAL_MID = np.array([250, 215, 40], np.float32)  # half way between σ and d_max
RESIDUAL_BAD = np.array([240, 40, 40], np.float32)  # ≥ d_max: nothing in the map near it
SELECTED_COLOR = (40, 120, 255)  # the inspected particle: saturated blue, unlike the
# map's pale blues and the warm colours around the estimate
SURFACE_BEST_COLOR = (255, 60, 255)  # the surface's maximum
SURFACE_ALPHA = 215  # the ground stays faintly visible under it

# perceptually ordered dark → bright (viridis' stops): the brightest cell is the likeliest
_SURFACE_STOPS = np.array([[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]], np.float32)


def _lut(stops: np.ndarray) -> np.ndarray:
    t = np.linspace(0.0, 1.0, 256)
    pos = t * (len(stops) - 1)
    i = np.minimum(pos.astype(int), len(stops) - 2)
    f = (pos - i)[:, None]
    return ((1 - f) * stops[i] + f * stops[i + 1]).astype(np.uint8)


SURFACE_LUT = _lut(_SURFACE_STOPS)
RESIDUAL_LUT = _lut(np.stack([RESIDUAL_GOOD, RESIDUAL_MID, RESIDUAL_BAD]))


def residual_fraction(distance: np.ndarray, sigma: float, d_max: float) -> np.ndarray:
    """Where each distance sits on the ramp: 0 at ≤ σ, 1 at ≥ d_max, linear between."""
    d = np.asarray(distance, np.float64)
    lo, hi = float(sigma), float(d_max)
    if hi <= lo:  # σ ≥ d_max: every point below the cap is as good as it gets
        return (d >= np.float32(hi)).astype(np.float64)
    t = np.clip((d - lo) / (hi - lo), 0.0, 1.0)
    t[d >= np.float32(hi)] = 1.0  # distances are float32, capped at float32(d_max)
    return t


def residual_colors(distance: np.ndarray, sigma: float, d_max: float) -> np.ndarray:
    """(M, 3) uint8: green ≤ σ, red ≥ d_max, a ramp through yellow between."""
    t = residual_fraction(distance, sigma, d_max)
    return RESIDUAL_LUT[np.rint(t * 255).astype(np.intp)]


def surface_scale(ll: np.ndarray) -> tuple[float, float]:
    """(low, high) of the colour scale of a log-likelihood surface: its maximum, and its 2nd
    percentile (a few cells outside the map would otherwise squash the rest into one colour)."""
    finite = ll[np.isfinite(ll)]
    if finite.size == 0:
        return 0.0, 1.0
    hi = float(finite.max())
    lo = float(np.percentile(finite, 2))
    return (lo, hi) if hi > lo else (hi - 1.0, hi)


def surface_rgba(ll: np.ndarray, alpha: int = SURFACE_ALPHA) -> np.ndarray:
    """(ny, nx, 4) uint8 image of a surface indexed ``ll[ix, iy]``: rows run from the largest y
    (top) down, columns along +x, the brightest colour at the maximum."""
    lo, hi = surface_scale(ll)
    t = np.clip((np.nan_to_num(ll, nan=lo, neginf=lo) - lo) / (hi - lo), 0.0, 1.0)
    img = SURFACE_LUT[np.rint(t * 255).astype(np.intp)].transpose(1, 0, 2)[::-1]
    rgba = np.empty(img.shape[:2] + (4,), np.uint8)
    rgba[..., :3] = img
    rgba[..., 3] = alpha
    return np.ascontiguousarray(rgba)


def _css(rgb) -> str:
    return "rgb({},{},{})".format(*(int(v) for v in rgb))


def colour_bar_html(lut: np.ndarray, left: str, right: str) -> str:
    """A horizontal colour bar of ``lut`` with a label under each end, for the panel."""
    stops = ", ".join(_css(lut[i]) for i in np.linspace(0, 255, 9).astype(int))
    return (
        "<div style='font-size:0.8em;margin:2px 0 4px 0'>"
        f"<div style='height:10px;border-radius:3px;background:linear-gradient(to right, {stops})'></div>"
        f"<div style='display:flex;justify-content:space-between'><span>{left}</span><span>{right}</span></div>"
        "</div>"
    )

"""The viewer's look: colours, sizes, refresh rates, and the few text and colour helpers that
every part of the page shares."""

from __future__ import annotations

import numpy as np

# Dark background: the paper's colour code (green scan, red particles) reads best on it, and the
# height ramp of the map avoids pure green and red so neither gets lost in the map.
SCAN_COLOR = (40, 255, 40)
S2M_ACCEPTED_COLOR = (255, 60, 255)
S2M_REJECTED_COLOR = (150, 150, 150)  # grey: discarded (and unlike the BEV yellow)
BEST_COLOR = (0, 230, 255)
ELLIPSE_COLOR = (255, 70, 70)
# the truth, its trajectory and its vehicle: lime, far from every colour of the map's ramp (white
# roofs hid a white truth) and from the scene's other colours
GT_COLOR = (170, 255, 0)
GT_NAME = "lime"
EST_COLOR = (255, 150, 30)
PARTICLE_LOW = np.array([110, 30, 40], np.float32)  # lowest log-weight rank
PARTICLE_HIGH = np.array([255, 70, 50], np.float32)  # highest log-weight rank
BEV_COLOR = (255, 225, 90)
RESET_COLOR = (255, 255, 255)
# the second run on screen (a branch's original, or view --run's second run): a blue the scene
# uses nowhere else, its particles darker
REF_COLOR = (80, 170, 255)
REF_PARTICLE_COLOR = (60, 120, 230)
CURSOR_COLOR = "#ffe14d"  # the plots' marker of the scan on the timeline
ERROR_CSS = "#ff6b6b"  # refusals and failures in the panel

DISPLAY_VOXEL = 0.5  # m, the displayed map's voxel size: the map is sent whole at it …
DISPLAY_MAX_POINTS = 1_500_000  # … when that is at most this many points; a bigger map is sent in tiles:
DISPLAY_BUDGET = 2_000_000  # map points sent to a browser at most, every map layer together
DISPLAY_TILE_M = 200.0  # m, side of a tile of a map sent in tiles
COARSE_MAX_POINTS = 500_000  # the coarse layer of the whole map, always sent, at most
ROAD_REMOVED_MAX_POINTS = 300_000  # the road-removed layer of a map sent in tiles (coarse), at most
NEAR_TILE_RADIUS_M = 300.0  # m, tiles this close to the estimate at full density, nearest first …
NEAR_TILE_HYSTERESIS_M = 50.0  # … and, once shown, until this much farther
NEAR_TILE_UPDATE_S = 1.0  # s, the tiles at full density are revisited at most this often
MINIMAP_PX = 256  # side of the overview image of the whole map in the panel
MINIMAP_INTERVAL_S = 1.0  # s, it is redrawn at most this often (and only when something changed)
TILE_COLOR = (110, 200, 255)  # the overview's outline of the tiles shown at full density
# the overview's rings at the places a whole-map match verified: the answer, and the others (all
# of them in the second colour when the answer was "ambiguous")
PLACE_ANSWER_COLOR = S2M_ACCEPTED_COLOR
PLACE_OTHER_COLOR = (255, 225, 90)
MIN_DRAW_INTERVAL = 1 / 30  # s, the display refreshes at most this often
PLOT_INTERVAL = 0.5  # s, the plots at most this often (they resend whole series)
PLOT_MAX_POINTS = 1500  # longer series are decimated for the plots
TRAJ_CHUNK = 256  # points per trajectory chunk (finished chunks are never re-sent)
EVENTS_SHOWN = 6
MESSAGE_SHOWN_S = 6.0  # s, a message (and its notification) is shown this long …
ERROR_SHOWN_S = 10.0  # … and a refusal or an error this long, unless it must stay
REALTIME_LATE_S = 0.1  # s behind the sensor clock from which the status warns (a late scan)
RATE_WINDOW_S = 3.0  # s of recent steps the achieved scans/s is measured over
COLLAPSED_N_EFF_SHARE = 0.01  # N_eff / N below this: the help line on weight collapse shows

# particles: the arrow length grows with the particle's weight relative to the heaviest one
PARTICLE_ARROW_MIN = 1.0  # m, weight ≈ 0
PARTICLE_ARROW_MAX = 6.0  # m, the heaviest particle
VEHICLE_LENGTH = 4.5  # m, the footprint drawn for the estimate and the truth
VEHICLE_WIDTH = 1.8

SPEEDS = ("1", "2", "5", "10", "20", "50", "max")  # scans per second in replay
SHIFT = "shift"  # the modifier of the scene's pointer picks (reset the particles)


def _height_lut() -> np.ndarray:
    """256-entry RGB ramp for map heights: slate blue (low) → light blue → warm white (high)."""
    stops = np.array([[62, 80, 135], [80, 120, 190], [145, 180, 228], [245, 235, 215]], np.float32)
    t = np.linspace(0, 1, 256)
    pos = t * (len(stops) - 1)
    i = np.minimum(pos.astype(int), len(stops) - 2)
    f = (pos - i)[:, None]
    return ((1 - f) * stops[i] + f * stops[i + 1]).astype(np.uint8)


HEIGHT_LUT = _height_lut()


def height_colors(z: np.ndarray, span: tuple[float, float] | None = None) -> np.ndarray:
    """(N,) heights → (N, 3) uint8, the 2nd–98th percentile (or ``span``: the same ramp for
    every tile of a map) spread over the ramp."""
    if len(z) == 0:
        return np.zeros((0, 3), np.uint8)
    lo, hi = np.percentile(z, [2, 98]) if span is None else span
    t = np.clip((z - lo) / max(hi - lo, 1e-6), 0, 1)
    return HEIGHT_LUT[(t * 255).astype(np.intp)]


def css(rgb) -> str:
    """An RGB triple as a CSS colour."""
    return "#{:02x}{:02x}{:02x}".format(*(int(v) for v in rgb))


def shorten(text: str, limit: int = 70) -> str:
    """One line of at most ``limit`` characters (the panel and labels are narrow; the localizer's
    event log keeps the full text)."""
    text = " ".join(str(text).split())
    return text if len(text) <= limit else text[: limit - 1].rstrip() + "…"


def error_markdown(text: str) -> str:
    """``text`` as a bold red line of the panel."""
    return f"<span style='color:{ERROR_CSS}'>**{text}**</span>"

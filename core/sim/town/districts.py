"""The city's districts: which style each place is built in, and what each style builds.

A town of ``extent_m`` ≥ :data:`~.constants.CITY_EXTENT` (1000 m) is a city; a smaller one keeps
the town's single style, unchanged. Why 1 km: a highway ring around a downtown, with suburbs,
an industrial strip and parks beside it, needs about that much room (at 1 km the ring runs some
300 m from the centre, downtown's radius is 220 m and the parks 100 m), while a town below it is
one neighbourhood, which is what the single style draws. Its district map (8 m cells) assigns
every place one of five styles:

- **downtown** around the centre (a disc of radius 16 % of the extent, 220–700 m, with a wavy
  edge): a dense grid of narrow, deep, tall buildings right at the sidewalk, no
  gaps, few trees, streets busy with parked cars and traffic lights;
- **suburb**, everywhere else: detached houses with gable roofs set back behind front gardens,
  hedges, fences and trees on the lot lines, long blocks (every other cross street left out,
  the direction changing by neighbourhood), quiet narrow streets. Suburb blocks repeat, as they
  do in real suburbs: places that look alike are part of the test;
- **industrial**, a strip along one side of the highway ring (outside it where there is room):
  large low halls far apart, chain-link fences along the street, yards with containers and
  trucks, superblocks (two of three streets left out), wide streets;
- **parks** (one per km of extent, and at least two): no streets inside, dense trees and
  bushes, footpaths, lamps along them, a hedge or a low wall along the edge;
- the **highway** corridor: a ring road around downtown on four of the grid's streets (11 m
  half width, 90 km/h), crossed only by the arterials, with guard rails along its verges,
  noise walls behind them in places and nothing built within its corridor.

Every fourth to sixth street of the grid is an **arterial** (7.5 m half width, 50 km/h) that
runs through every district. Street classes, and so speed limits, come from the edge's
district and line (see :mod:`.city_layout`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

DOWNTOWN, SUBURB, INDUSTRIAL, PARK, HIGHWAY = range(5)
STYLE_NAMES = ("downtown", "suburb", "industrial", "park", "highway")

DISTRICT_CELL = 8.0  # m, cells of the district map
HIGHWAY_CORRIDOR = 45.0  # m from the ring's centre line: nothing is built this close


@dataclass(frozen=True)
class Style:
    """What one district style builds along its streets (lengths in m)."""

    lot_width: tuple[float, float]  # frontage of one building
    depth: tuple[float, float]  # building depth, away from the street
    setback: tuple[float, float]  # from the property line
    gap: tuple[float, float]  # between neighbouring buildings
    no_gap: float  # share of buildings that touch their neighbour
    height: tuple[float, float]  # m above the ground, drawn log-uniformly
    gable: float  # share of gable roofs
    empty_lot: float  # share of frontage left empty
    street_trees: float  # share of street sides with a row of trees
    front_fence: float  # share of lots fenced, walled or hedged along the street
    fences: tuple[float, float, float]  # wall, fence, hedge probabilities
    green: float  # trees or bushes tried per 90 m² of free ground
    parking_fill: tuple[float, float]  # share of parking spots taken
    traffic_lights: float  # share of junctions with lights rather than signs


STYLES = {
    DOWNTOWN: Style(
        lot_width=(8.0, 22.0),
        depth=(14.0, 30.0),
        setback=(0.0, 0.8),
        gap=(0.0, 3.0),
        no_gap=0.75,
        height=(12.0, 80.0),
        gable=0.0,
        empty_lot=0.02,
        street_trees=0.4,
        front_fence=0.0,
        fences=(0.7, 0.3, 0.0),
        green=0.03,
        parking_fill=(0.6, 0.95),
        traffic_lights=0.7,
    ),
    SUBURB: Style(
        lot_width=(9.0, 14.0),
        depth=(8.0, 12.0),
        setback=(4.0, 9.0),
        gap=(4.0, 10.0),
        no_gap=0.0,
        height=(3.5, 8.0),
        gable=0.8,
        empty_lot=0.05,
        street_trees=0.7,
        front_fence=0.6,
        fences=(0.15, 0.35, 0.5),
        green=0.35,
        parking_fill=(0.15, 0.6),
        traffic_lights=0.05,
    ),
    INDUSTRIAL: Style(
        lot_width=(30.0, 80.0),
        depth=(25.0, 60.0),
        setback=(8.0, 20.0),
        gap=(10.0, 30.0),
        no_gap=0.0,
        height=(6.0, 14.0),
        gable=0.1,
        empty_lot=0.15,
        street_trees=0.15,
        front_fence=0.85,
        fences=(0.15, 0.85, 0.0),
        green=0.04,
        parking_fill=(0.05, 0.4),
        traffic_lights=0.2,
    ),
    PARK: Style(
        lot_width=(6.0, 10.0),
        depth=(5.0, 8.0),
        setback=(10.0, 30.0),
        gap=(200.0, 400.0),
        no_gap=0.0,
        height=(3.0, 5.0),
        gable=0.5,
        empty_lot=0.9,
        street_trees=0.9,
        front_fence=0.5,
        fences=(0.3, 0.0, 0.7),
        green=2.0,
        parking_fill=(0.0, 0.2),
        traffic_lights=0.0,
    ),
    HIGHWAY: Style(
        lot_width=(10.0, 10.0),
        depth=(10.0, 10.0),
        setback=(0.0, 0.0),
        gap=(0.0, 0.0),
        no_gap=0.0,
        height=(3.0, 3.0),
        gable=0.0,
        empty_lot=1.0,
        street_trees=0.0,
        front_fence=0.0,
        fences=(0.0, 1.0, 0.0),
        green=0.08,
        parking_fill=(0.0, 0.0),
        traffic_lights=0.0,
    ),
}


@dataclass
class DistrictMap:
    """The style of every DISTRICT_CELL cell over the city and its margin."""

    x0: float
    y0: float
    codes: np.ndarray  # (nx, ny) uint8 style codes
    centre: tuple[float, float]
    downtown_radius: float  # m
    ring: tuple[float, float, float, float]  # x_west, x_east, y_south, y_north of the highway ring

    def style_at(self, x, y) -> np.ndarray:
        i = np.clip(
            np.floor((np.asarray(x, float) - self.x0) / DISTRICT_CELL).astype(np.int64), 0, self.codes.shape[0] - 1
        )
        j = np.clip(
            np.floor((np.asarray(y, float) - self.y0) / DISTRICT_CELL).astype(np.int64), 0, self.codes.shape[1] - 1
        )
        return self.codes[i, j]

    def on_raster(self, raster) -> np.ndarray:
        """The style codes on the 0.5 m ground-plan raster (uint8, one byte per cell)."""
        xs, ys = raster.centres()
        i = np.clip(np.floor((xs - self.x0) / DISTRICT_CELL).astype(np.int64), 0, self.codes.shape[0] - 1)
        j = np.clip(np.floor((ys - self.y0) / DISTRICT_CELL).astype(np.int64), 0, self.codes.shape[1] - 1)
        return self.codes[i[:, None], j[None, :]]

    def shares(self, extent: float) -> dict[str, float]:
        """Share of the city's square each style covers."""
        n = np.floor(np.array([-self.x0, -self.y0]) / DISTRICT_CELL).astype(int)
        m = int(extent / DISTRICT_CELL)
        inside = self.codes[n[0] : n[0] + m, n[1] : n[1] + m]
        return {STYLE_NAMES[k]: float(np.mean(inside == k)) for k in range(len(STYLE_NAMES))}


def _wobble(rng, shape, feature_cells: float) -> np.ndarray:
    """A smooth random field in [−0.5, 0.5] with blobs about ``feature_cells`` cells across."""
    coarse = rng.random((int(shape[0] / feature_cells) + 4, int(shape[1] / feature_cells) + 4))
    u = np.arange(shape[0]) / feature_cells + 1.5
    v = np.arange(shape[1]) / feature_cells + 1.5
    U, V = np.meshgrid(u, v, indexing="ij")
    field = ndimage.map_coordinates(coarse, [U.ravel(), V.ravel()], order=3, mode="nearest").reshape(shape)
    lo, hi = np.percentile(field, [1, 99])
    return np.clip((field - lo) / max(hi - lo, 1e-9), 0.0, 1.0) - 0.5


def plan_districts(rng: np.random.Generator, extent: float, margin: float, centre, ring) -> DistrictMap:
    """The district map of a city of side ``extent`` around ``centre`` with the highway ``ring``
    (x_west, x_east, y_south, y_north of its centre lines)."""
    x0 = y0 = -margin - DISTRICT_CELL
    n = int(math.ceil((extent + 2 * margin + 2 * DISTRICT_CELL) / DISTRICT_CELL))
    xs = x0 + (np.arange(n) + 0.5) * DISTRICT_CELL
    X, Y = np.meshgrid(xs, xs, indexing="ij")
    codes = np.full((n, n), SUBURB, np.uint8)
    wobble = _wobble(rng, (n, n), 150.0 / DISTRICT_CELL)
    xw, xe, ys, yn = ring
    cx, cy = centre

    # The industrial strip along one side of the ring: outside it where there is room.
    width = float(np.clip(0.1 * extent, 150.0, 450.0))
    side = int(rng.integers(4))
    lo_edge, hi_edge = (xw, xe) if side < 2 else (ys, yn)
    along_lo, along_hi = (ys, yn) if side < 2 else (xw, xe)
    length = float(np.clip(0.6 * (along_hi - along_lo), 300.0, 2400.0))
    start = along_lo + rng.uniform(0.0, max(along_hi - along_lo - length, 0.0))
    if side % 2 == 0:  # west or south side
        outside = lo_edge - HIGHWAY_CORRIDOR >= width
        a, b = (
            (lo_edge - HIGHWAY_CORRIDOR - width, lo_edge - HIGHWAY_CORRIDOR)
            if outside
            else (lo_edge + HIGHWAY_CORRIDOR, lo_edge + HIGHWAY_CORRIDOR + width)
        )
    else:  # east or north side
        outside = extent - hi_edge - HIGHWAY_CORRIDOR >= width
        a, b = (
            (hi_edge + HIGHWAY_CORRIDOR, hi_edge + HIGHWAY_CORRIDOR + width)
            if outside
            else (hi_edge - HIGHWAY_CORRIDOR - width, hi_edge - HIGHWAY_CORRIDOR)
        )
    across, along = (X, Y) if side < 2 else (Y, X)
    strip = (across >= a) & (across <= b) & (along >= start) & (along <= start + length)
    codes[strip] = INDUSTRIAL

    # Downtown around the centre, inside the ring.
    radius = float(np.clip(0.16 * extent, 220.0, 700.0))
    radius = min(radius, 0.5 * min(xe - xw, yn - ys) - HIGHWAY_CORRIDOR - 40.0)
    r = np.hypot(X - cx, Y - cy) / radius
    codes[r * (1.0 + 0.5 * wobble) < 1.0] = DOWNTOWN

    # Parks: discs with wavy edges in the suburbs, away from downtown.
    n_parks = max(2, int(round(extent / 1000.0)))
    park_r = float(np.clip(0.065 * extent, 100.0, 260.0))
    for _ in range(n_parks):
        for _attempt in range(200):
            px, py = rng.uniform(park_r, extent - park_r, 2)
            if np.hypot(px - cx, py - cy) < radius + park_r + 60.0:
                continue
            i, j = int((px - x0) / DISTRICT_CELL), int((py - y0) / DISTRICT_CELL)
            if codes[i, j] == SUBURB:
                break
        d = np.hypot(X - px, Y - py) / park_r
        codes[(d * (1.0 + 0.6 * wobble) < 1.0) & (codes == SUBURB)] = PARK

    # The highway's corridor along the ring's four sides.
    near = np.zeros((n, n), bool)
    for x in (xw, xe):
        near |= (np.abs(X - x) <= HIGHWAY_CORRIDOR) & (Y >= ys - HIGHWAY_CORRIDOR) & (Y <= yn + HIGHWAY_CORRIDOR)
    for y in (ys, yn):
        near |= (np.abs(Y - y) <= HIGHWAY_CORRIDOR) & (X >= xw - HIGHWAY_CORRIDOR) & (X <= xe + HIGHWAY_CORRIDOR)
    codes[near] = HIGHWAY
    return DistrictMap(x0, y0, codes, (float(cx), float(cy)), radius, (float(xw), float(xe), float(ys), float(yn)))

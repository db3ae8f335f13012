"""``lidarloc corpus staleness``: where the prior map disagrees with the world, again and again,
over a corpus run's drives.

Each drive's scans are placed at the drive's own estimate (only where the filter was localized)
and compared with the prior map in two ways:

- **new**: scan points whose distance to the map (the lookup table the particle filter reads)
  is at least ``min_distance`` — something is there that the map lacks (an object added or moved
  there, a grown tree, and passing traffic);
- **gone**: map points standing above the ground that the scan's beams passed through — the
  scan's range image holds, around the map point's direction, only returns farther than the map
  point by ``min_distance`` — something the map has is not there any more (an object removed or
  moved away, a cut tree). The nearest return over the 3 × 3 neighbouring bins of the range image
  is what counts, so the edge of an object a beam grazes is not taken for a hole.

Both are counted on a 2D grid over the map's top view. A cell is *observed* by a scan when scan
points fall in it or map points in it were checked; it *disagrees* in a scan when new or gone
points fall in it. Per drive, a cell disagrees when it disagreed in at least ``DRIVE_MIN_SCANS``
scans, in at least ``scan_share`` of the scans that observed it, and from scans at least
``DRIVE_SPAN_M`` apart along the drive: a car passing is in a cell for a moment while the drive
sees that cell for many scans, and the car ahead, which moves and stops with the drive, is seen
in a cell from one short stretch of the drive only, while a change is seen from all along the
approach. A cell is
**stale** when it disagrees in at least ``min_drives`` drives and in at least ``drive_share``
of the drives that observed it: a change of the world is seen by every drive that passes, traffic by
one drive at one moment. A corpus of one drive therefore flags nothing. Cells without map points
within two cells are not judged: there the map is not stale, it ends.

Stale cells at most one cell apart form one *stale place*; its points (the new and gone
points of its cells) are the point layer.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ...core.config import Config, update_from_dict
from ...core.errors import LidarlocError
from ...core.geometry import pose_matrix
from ...core.sequences.factory import SourceSpec
from .spec import IDENTITY_FILE

CELL_M = 1.0  # m, side of a grid cell: a parked car is a few cells, a sign post one
MIN_DISTANCE_M = 1.0  # m: beyond the localization error (~0.2 m), lookup quantisation and motion skew
RANGE_M = 40.0  # m, farthest point judged: farther, beams are sparse and a pose error grows with range
EVERY = 2  # every 2nd localized scan: neighbouring scans see the same
DRIVE_MIN_SCANS = 2  # one scan's disagreement is noise
# m of the drive's path between the first and the last scan that disagreed: a change is seen
# from all along the approach, the car ahead (which moves and stops with the drive) or a
# pedestrian passing a stopped drive from one stretch of it
DRIVE_SPAN_M = 10.0
SCAN_SHARE = 0.3  # of a drive's scans that observed a cell
# of the drives that observed a cell: a change is in most drives that pass it, though a drive
# passing at a distance or with a sparse sensor misses some (half lost recall over 6 drives)
DRIVE_SHARE = 0.3
MIN_DRIVES = 2
ABOVE_GROUND_M = 0.3  # map points lower than this over the ground are ground: beams graze it
# Higher than this over the ground nothing is judged: the map's sensor may not have seen that high
# (an HDL-64E looks 2° up: a wall 10 m away is mapped to 2.1 m), and what changes in a street
# (parked cars, bins, signs, the lower crowns of trees) stands lower.
BELOW_M = 2.5
BIN_RAD = math.radians(1.0)  # range image bin, azimuth and elevation
POINT_VOXEL_M = 0.3  # the point layer's spacing


@dataclass(frozen=True)
class Settings:
    cell_m: float = CELL_M
    min_distance: float = MIN_DISTANCE_M
    range_m: float = RANGE_M
    every: int = EVERY
    scan_share: float = SCAN_SHARE
    drive_share: float = DRIVE_SHARE
    min_drives: int = MIN_DRIVES

    def check(self) -> Settings:
        for ok, text in (
            (0.1 <= self.cell_m <= 10, "--cell must be in 0.1..10 m"),
            (0.2 <= self.min_distance <= 5, "--min-distance must be in 0.2..5 m"),
            (5 <= self.range_m <= 200, "--range must be in 5..200 m"),
            (self.every >= 1, "--every must be ≥ 1"),
            (0 < self.scan_share <= 1, "--scan-share must be in (0, 1]"),
            (0 < self.drive_share <= 1, "--drive-share must be in (0, 1]"),
            (self.min_drives >= 1, "--min-drives must be ≥ 1"),
        ):
            if not ok:
                raise LidarlocError(text)
        return self


@dataclass
class DriveData:
    """What the staleness needs of one drive of a corpus run."""

    name: str
    folder: Path
    spec: SourceSpec
    cfg: Config


def corpus_drives(folder: Path) -> list[DriveData]:
    """The finished drives of the corpus run in ``folder`` (one-line errors for a missing folder
    or one that is not a corpus run's --out)."""
    from .figures import read_output

    drives = []
    for drive in read_output(folder, "RUN_DIR").drives.values():
        if drive.identity is None or not (drive.folder / "scans.csv").is_file():
            raise LidarlocError(f"{drive.folder}: no {IDENTITY_FILE} or scans.csv: the drive's run is incomplete")
        cfg = update_from_dict(Config(), drive.identity["config"])
        drives.append(DriveData(drive.name, drive.folder, SourceSpec.from_dict(drive.identity["source"]), cfg))
    if not drives:
        raise LidarlocError(f"{folder}: no finished drive to judge the map by")
    return drives


@dataclass
class MapGrid:
    """The grid over one map's top view and its per-cell counts."""

    origin: np.ndarray  # (2,) m, the corner of cell (0, 0) in the map's frame
    cell_m: float
    shape: tuple[int, int]
    supported: np.ndarray  # (nx, ny) bool: map points within two cells
    ground: np.ndarray  # (nx, ny) m, the lowest map point near the cell
    scans_observed: np.ndarray = field(init=False)
    scans_disagree: np.ndarray = field(init=False)
    drives_observed: np.ndarray = field(init=False)
    drives_disagree: np.ndarray = field(init=False)
    points: list = field(default_factory=list)  # per drive: the disagreeing points in cells it flagged
    drives: list = field(default_factory=list)

    def __post_init__(self):
        self.scans_observed = np.zeros(self.shape, np.int32)
        self.scans_disagree = np.zeros(self.shape, np.int32)
        self.drives_observed = np.zeros(self.shape, np.int16)
        self.drives_disagree = np.zeros(self.shape, np.int16)

    @classmethod
    def over(cls, map_points: np.ndarray, cell_m: float) -> MapGrid:
        from scipy import ndimage

        lo = np.floor(map_points[:, :2].min(axis=0) / cell_m) * cell_m - 2 * cell_m
        hi = map_points[:, :2].max(axis=0) + 2 * cell_m
        shape = tuple(int(v) for v in np.ceil((hi - lo) / cell_m))
        grid = cls(lo, cell_m, shape, np.zeros(shape, bool), np.zeros(shape))
        ij = grid.cells(map_points)
        low = np.full(shape, np.inf)
        np.minimum.at(low, (ij[:, 0], ij[:, 1]), map_points[:, 2].astype(np.float64))
        grid.supported = ndimage.binary_dilation(np.isfinite(low), iterations=2)
        reach = max(3, int(round(5.0 / cell_m)) | 1)  # the ground over ~5 m: under a car there is none
        grid.ground = ndimage.minimum_filter(low, size=reach, mode="nearest")
        return grid

    def cells(self, xy: np.ndarray) -> np.ndarray:
        ij = np.floor((np.asarray(xy)[:, :2] - self.origin) / self.cell_m).astype(np.int64)
        return np.clip(ij, 0, np.array(self.shape) - 1)

    def flat(self, xy: np.ndarray) -> np.ndarray:
        ij = self.cells(xy)
        return ij[:, 0] * self.shape[1] + ij[:, 1]

    def stale(self, s: Settings) -> np.ndarray:
        d = self.drives_disagree
        return (d >= s.min_drives) & (d >= s.drive_share * np.maximum(self.drives_observed, 1))


class MapPoints:
    """The map's points above the ground, bucketed by grid cell: those near a pose, fast."""

    def __init__(self, points: np.ndarray, grid: MapGrid):
        ij = grid.cells(points)
        height = points[:, 2] - grid.ground[ij[:, 0], ij[:, 1]]
        above = (height > ABOVE_GROUND_M) & (height <= BELOW_M)
        pts = points[above]
        flat = grid.flat(pts)
        order = np.argsort(flat, kind="stable")
        self.points, self.grid = pts[order].astype(np.float64), grid
        self.starts = np.searchsorted(flat[order], np.arange(grid.shape[0] * grid.shape[1] + 1))

    def near(self, xy: np.ndarray, radius: float) -> np.ndarray:
        g = self.grid
        lo = np.maximum(np.floor((xy - radius - g.origin) / g.cell_m).astype(int), 0)
        hi = np.minimum(np.floor((xy + radius - g.origin) / g.cell_m).astype(int), np.array(g.shape) - 1)
        chunks = [
            self.points[self.starts[i * g.shape[1] + lo[1]] : self.starts[i * g.shape[1] + hi[1] + 1]]
            for i in range(lo[0], hi[0] + 1)
        ]
        return np.concatenate(chunks) if chunks else np.zeros((0, 3))


def _bins(q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Range, azimuth bin and elevation bin of sensor-frame points."""
    r = np.linalg.norm(q, axis=1)
    az = np.floor((np.arctan2(q[:, 1], q[:, 0]) + math.pi) / BIN_RAD).astype(np.int64)
    el = np.floor((np.arcsin(np.clip(q[:, 2] / np.maximum(r, 1e-9), -1, 1)) + math.pi / 2) / BIN_RAD).astype(np.int64)
    n_az, n_el = int(round(2 * math.pi / BIN_RAD)), int(round(math.pi / BIN_RAD))
    return r, np.clip(az, 0, n_az - 1), np.clip(el, 0, n_el - 1)


def seen_through(scan: np.ndarray, map_sensor: np.ndarray, margin: float) -> tuple[np.ndarray, np.ndarray]:
    """For map points in the sensor's frame: (checked, gone) — checked where the scan has a return
    in the point's range-image bin, gone where every return around it is ``margin`` farther."""
    from scipy import ndimage

    n_az, n_el = int(round(2 * math.pi / BIN_RAD)), int(round(math.pi / BIN_RAD))
    rs, az, el = _bins(scan)
    image = np.full((n_az, n_el), np.inf)
    np.minimum.at(image, (az, el), rs)
    around = ndimage.minimum_filter(image, size=3, mode=("wrap", "nearest"))
    rm, az_m, el_m = _bins(map_sensor)
    checked = np.isfinite(image[az_m, el_m])
    return checked, checked & (rm < around[az_m, el_m] - margin)


def localized_scans(folder: Path, every: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(scan indices, their 4×4 estimated poses, their times) of the localized scans, every
    ``every``-th."""
    from .health import read_run

    table, _ = read_run(folder)
    if "localized" not in table or not len(table["scan"]):
        return np.zeros(0, int), np.zeros((0, 4, 4)), np.zeros(0)
    rows = np.flatnonzero(table["localized"] == 1)[::every]
    state = [table[k][rows] for k in ("x", "y", "z", "yaw", "pitch", "roll")]
    return table["scan"][rows].astype(int), pose_matrix(*state).reshape(-1, 4, 4), table["time"][rows]


def judge_drive(
    grid: MapGrid,
    map_points: MapPoints,
    lookup,
    seq,
    scans,
    poses,
    s: Settings,
    name: str,
    tick: Callable[[int, int], None],
) -> None:
    """Count one drive's scans into ``grid`` (see the module's docstring)."""
    from ...core.filter.scanprep import voxel_downsample_random

    n_cells = grid.shape[0] * grid.shape[1]
    observed = np.zeros(n_cells, np.int32)
    disagree = np.zeros(n_cells, np.int32)
    cap = lookup.capped(lookup.d_max_built)
    first = np.full(n_cells, np.inf)
    last = np.full(n_cells, -np.inf)
    steps = np.linalg.norm(np.diff(poses[:, :2, 3], axis=0), axis=1) if len(poses) else np.zeros(0)
    travelled = np.concatenate([[0.0], np.cumsum(steps)])
    found = []
    for k, (i, T) in enumerate(zip(scans, poses, strict=True)):
        raw = np.asarray(seq.scan(int(i)))[:, :3].astype(np.float64)
        raw = raw[np.linalg.norm(raw, axis=1) <= s.range_m]
        pts = voxel_downsample_random(raw, 0.2, int(i), math.pi / 2).astype(np.float64)
        world = pts @ T[:3, :3].T + T[:3, 3]
        ij = grid.flat(world)
        new = lookup.query(world, cap) >= s.min_distance
        new &= grid.supported.reshape(-1)[ij] & (world[:, 2] - grid.ground.reshape(-1)[ij] <= BELOW_M)
        near = map_points.near(T[:2, 3], s.range_m)
        local = (near - T[:3, 3]) @ T[:3, :3]
        checked, gone = seen_through(raw, local, s.min_distance)
        ij_m = grid.flat(near)
        obs = np.unique(np.concatenate([ij, ij_m[checked]]))
        dis = np.unique(np.concatenate([ij[new], ij_m[gone]]))
        observed[obs] += 1
        disagree[dis] += 1
        first[dis] = np.minimum(first[dis], travelled[k])
        last[dis] = np.maximum(last[dis], travelled[k])
        found.append(np.concatenate([world[new], near[gone]]))
        tick(k + 1, len(scans))
    grid.scans_observed += observed.reshape(grid.shape)
    grid.scans_disagree += disagree.reshape(grid.shape)
    flagged = (disagree >= DRIVE_MIN_SCANS) & (disagree >= s.scan_share * np.maximum(observed, 1))
    flagged &= last - first >= DRIVE_SPAN_M
    grid.drives_observed += (observed > 0).reshape(grid.shape).astype(np.int16)
    grid.drives_disagree += flagged.reshape(grid.shape).astype(np.int16)
    pts = np.concatenate(found) if found else np.zeros((0, 3))
    pts = pts[flagged[grid.flat(pts)]] if len(pts) else pts
    grid.points.append(_thin(pts))
    grid.drives.append(name)


def _thin(points: np.ndarray) -> np.ndarray:
    """One point per POINT_VOXEL_M voxel."""
    if not len(points):
        return np.zeros((0, 3))
    _, first = np.unique(np.floor(points / POINT_VOXEL_M).astype(np.int64), axis=0, return_index=True)
    return points[np.sort(first)]


def stale_places(grid: MapGrid, s: Settings) -> tuple[np.ndarray, list[dict]]:
    """The stale-place label of each cell (0: none) and per place its cells, centre and extent."""
    from scipy import ndimage

    stale = grid.stale(s)
    joined, _ = ndimage.label(ndimage.binary_dilation(stale, np.ones((3, 3), bool)), structure=np.ones((3, 3), bool))
    labels = np.where(stale, joined, 0)
    places = []
    for k, sl in enumerate(ndimage.find_objects(labels), start=1):
        if sl is None:
            continue
        ii, jj = np.nonzero(labels[sl] == k)
        ii, jj = ii + sl[0].start, jj + sl[1].start
        centre = grid.origin + (np.array([ii.mean(), jj.mean()]) + 0.5) * grid.cell_m
        places.append(
            {
                "place": k,
                "x": round(float(centre[0]), 2),
                "y": round(float(centre[1]), 2),
                "cells": int(len(ii)),
                "drives": int(grid.drives_disagree[ii, jj].max()),
                "drives_observed": int(grid.drives_observed[ii, jj].max()),
            }
        )
    return labels, places


def stale_points(grid: MapGrid, s: Settings) -> np.ndarray:
    """The disagreeing points that lie in stale cells, one per voxel."""
    pts = np.concatenate(grid.points) if grid.points else np.zeros((0, 3))
    if not len(pts):
        return pts
    return _thin(pts[grid.stale(s).reshape(-1)[grid.flat(pts)]])

"""The 0.5 m raster the ground plan is drawn on, the smooth ground height over it, and the two
plane-geometry helpers the street layout, the drive and the objects share."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .constants import BLOCK_CELLS, CELL, NODE_CELLS


@dataclass
class Raster:
    """An axis-aligned grid of CELL-sized cells; array[i, j] is the cell at x index i, y index j."""

    x0: float
    y0: float
    nx: int
    ny: int
    cell: float = CELL

    @classmethod
    def covering(cls, xmin: float, ymin: float, xmax: float, ymax: float) -> Raster:
        quantum = CELL * BLOCK_CELLS  # whole ground blocks, so block reshapes are exact
        x0 = math.floor(xmin / quantum) * quantum
        y0 = math.floor(ymin / quantum) * quantum
        nx = int(math.ceil((xmax - x0) / quantum)) * BLOCK_CELLS
        ny = int(math.ceil((ymax - y0) / quantum)) * BLOCK_CELLS
        return cls(x0, y0, nx, ny)

    @property
    def shape(self) -> tuple[int, int]:
        return (self.nx, self.ny)

    def ij(self, x, y):
        """Cell indices of points, clipped into the raster, and whether they were inside."""
        i = np.floor((np.asarray(x) - self.x0) / self.cell).astype(np.int64)
        j = np.floor((np.asarray(y) - self.y0) / self.cell).astype(np.int64)
        ok = (i >= 0) & (i < self.nx) & (j >= 0) & (j < self.ny)
        return np.clip(i, 0, self.nx - 1), np.clip(j, 0, self.ny - 1), ok

    def lookup(self, array, x, y, outside=0):
        i, j, ok = self.ij(x, y)
        return np.where(ok, array[i, j], outside)

    def paint(self, mask, x, y, value=True):
        i, j, ok = self.ij(x, y)
        mask[i[ok], j[ok]] = value

    def centres(self):
        xs = self.x0 + (np.arange(self.nx) + 0.5) * self.cell
        ys = self.y0 + (np.arange(self.ny) + 0.5) * self.cell
        return xs, ys


class HeightField:
    """Ground height z(x, y): bilinear interpolation of nodes every NODE_CELLS cells."""

    def __init__(self, raster: Raster, z: np.ndarray):
        self.x0, self.y0 = raster.x0, raster.y0
        self.spacing = raster.cell * NODE_CELLS
        self.z = np.asarray(z, dtype=np.float64)
        assert self.z.shape == (raster.nx // NODE_CELLS + 1, raster.ny // NODE_CELLS + 1)

    @staticmethod
    def node_coordinates(raster: Raster):
        spacing = raster.cell * NODE_CELLS
        xs = raster.x0 + np.arange(raster.nx // NODE_CELLS + 1) * spacing
        ys = raster.y0 + np.arange(raster.ny // NODE_CELLS + 1) * spacing
        return np.meshgrid(xs, ys, indexing="ij")

    def __call__(self, x, y) -> np.ndarray:
        u = np.clip((np.asarray(x, float) - self.x0) / self.spacing, 0.0, self.z.shape[0] - 1.000001)
        v = np.clip((np.asarray(y, float) - self.y0) / self.spacing, 0.0, self.z.shape[1] - 1.000001)
        i = u.astype(np.int64)
        j = v.astype(np.int64)
        fu, fv = u - i, v - j
        z = self.z
        return (z[i, j] * (1 - fu) + z[i + 1, j] * fu) * (1 - fv) + (z[i, j + 1] * (1 - fu) + z[i + 1, j + 1] * fu) * fv


def left_normal(t: np.ndarray) -> np.ndarray:
    """Directions ``t`` (..., 2) turned 90° to the left: the left normals of unit tangents."""
    return np.stack([-t[..., 1], t[..., 0]], axis=-1)


def densify(points: np.ndarray, step: float) -> np.ndarray:
    """Points along a polyline at most ``step`` apart (for rasterising lines)."""
    points = np.asarray(points, float)
    out = [points[:1]]
    for a, b in zip(points[:-1], points[1:]):
        n = max(1, int(math.ceil(np.linalg.norm(b - a) / step)))
        f = (np.arange(1, n + 1) / n)[:, None]
        out.append(a + (b - a) * f)
    return np.concatenate(out)

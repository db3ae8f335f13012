"""Where the pointer meets the map: the ground height under every point of the map, and the
ground points and areas a shift+click or a shift+drag on the scene picks."""

from __future__ import annotations

import math

import numpy as np
import viser

from ...core.errors import LidarlocError


class GroundHeight:
    """Lowest map height per 2D cell, so a click on the screen lands on the road, not on a roof."""

    def __init__(self, points: np.ndarray, cell: float = 2.0, max_cells: int = 4_000_000):
        self.z_default = float(np.percentile(points[:, 2], 5)) if len(points) else 0.0
        lo = points[:, :2].min(axis=0) if len(points) else np.zeros(2)
        hi = points[:, :2].max(axis=0) if len(points) else np.ones(2)
        while np.prod(np.ceil((hi - lo) / cell) + 1) > max_cells:
            cell *= 2
        self.cell, self.origin = cell, lo
        shape = (np.ceil((hi - lo) / cell) + 1).astype(int)
        self.grid = np.full(shape, np.inf, np.float32)
        if len(points):
            idx = ((points[:, :2] - lo) / cell).astype(int)
            np.minimum.at(self.grid, (idx[:, 0], idx[:, 1]), points[:, 2])

    @classmethod
    def from_grid(cls, grid: np.ndarray, origin: np.ndarray, cell: float, z_default: float) -> GroundHeight:
        """The lowest heights computed elsewhere (a map too big to pass whole: map_tiles)."""
        g = cls.__new__(cls)
        g.grid, g.origin, g.cell, g.z_default = grid, origin, float(cell), float(z_default)
        return g

    def at(self, x: float, y: float) -> float:
        i = int((x - self.origin[0]) // self.cell)
        j = int((y - self.origin[1]) // self.cell)
        if 0 <= i < self.grid.shape[0] and 0 <= j < self.grid.shape[1] and np.isfinite(self.grid[i, j]):
            return float(self.grid[i, j])
        return self.z_default

    def level(self, x: float, y: float, radius: float = 5.0) -> float:
        """The road's height around (x, y): the median of the lowest heights of the cells within
        ``radius`` (one cell's lowest point is its lowest road point, below the road's mean by
        the noise; a cell inside a building has its roof as lowest point, outvoted here). The
        default height outside the map."""
        r = int(math.ceil(radius / self.cell))
        i = int((x - self.origin[0]) // self.cell)
        j = int((y - self.origin[1]) // self.cell)
        cells = self.grid[max(i - r, 0) : max(i + r + 1, 0), max(j - r, 0) : max(j + r + 1, 0)]
        low = cells[np.isfinite(cells)]
        return float(np.median(low)) if low.size else self.z_default

    def hit(self, origin, direction) -> np.ndarray | None:
        """Where a ray meets the ground (two passes: a flat ground, then the local height there)."""
        o, d = np.asarray(origin, float), np.asarray(direction, float)
        if abs(d[2]) < 1e-9:
            return None
        z = self.z_default
        p = None
        for _ in range(2):
            s = (z - o[2]) / d[2]
            if s <= 0:
                return None
            p = o + s * d
            z = self.at(p[0], p[1])
        return p


def screen_ray(camera, u: float, v: float) -> tuple[np.ndarray, np.ndarray]:
    """World ray through the normalised screen point (u, v) ∈ [0, 1]², (0, 0) top left, of a
    viser camera (OpenCV convention: x right, y down, z forward; fov is vertical)."""
    R = viser.transforms.SO3(np.asarray(camera.wxyz)).as_matrix()
    t = math.tan(camera.fov / 2.0)
    d_cam = np.array([(2 * u - 1) * t * camera.aspect, (2 * v - 1) * t, 1.0])
    d = R @ d_cam
    return np.asarray(camera.position, float), d / np.linalg.norm(d)


def clicked_point(ground: GroundHeight | None, ray_origin, ray_direction) -> np.ndarray:
    """The ground point a click's ray hits (x, y, z)."""
    if ground is None:
        raise LidarlocError("the map is not loaded yet")
    hit = ground.hit(ray_origin, ray_direction)
    if hit is None:
        raise LidarlocError("that click does not meet the ground")
    return hit


def dragged_region(ground: GroundHeight | None, camera, screen_min, screen_max) -> tuple[float, float, float, float]:
    """The (x0, y0, x1, y1) box round the ground points under the corners of a rectangle dragged
    on the screen of ``camera``."""
    if ground is None:
        raise LidarlocError("the map is not loaded yet")
    (u0, v0), (u1, v1) = screen_min, screen_max
    corners = []
    for u, v in ((u0, v0), (u1, v0), (u1, v1), (u0, v1)):
        o, d = screen_ray(camera, u, v)
        hit = ground.hit(o, d)
        if hit is None:
            raise LidarlocError("the rectangle reaches above the horizon: drag it on the ground")
        corners.append(hit)
    return region_from_corners(np.array(corners)[:, :2])


def region_from_corners(xy: np.ndarray) -> tuple[float, float, float, float]:
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])


def pose_on_ground(ground: GroundHeight | None, x: float, y: float, sensor_height: float) -> np.ndarray:
    """A sensor pose standing on the ground at (x, y); heading unknown (identity)."""
    T = np.eye(4)
    z = ground.at(x, y) if ground is not None else 0.0
    T[:3, 3] = (x, y, z + float(sensor_height))
    return T

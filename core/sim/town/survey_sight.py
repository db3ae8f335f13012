"""What a street survey's scanner sees of a city cell: the ground's height there, and whether a
straight line from the road to it is clear of the city's cover (numba kernels of :mod:`.survey`)."""

from __future__ import annotations

import math

import numba as nb
import numpy as np


@nb.njit(cache=True, nogil=True, inline="always")
def height(x, y, z, x0, y0, spacing):
    """The ground's height at (x, y): :class:`~.raster.HeightField`'s bilinear interpolation."""
    u = min(max((x - x0) / spacing, 0.0), z.shape[0] - 1.000001)
    v = min(max((y - y0) / spacing, 0.0), z.shape[1] - 1.000001)
    i, j = int(u), int(v)
    fu, fv = u - i, v - j
    return (z[i, j] * (1 - fu) + z[i + 1, j] * fu) * (1 - fv) + (z[i, j + 1] * (1 - fu) + z[i + 1, j + 1] * fu) * fv


@nb.njit(cache=True, nogil=True, inline="always")
def clear(x, y, height, tx, ty, length, cover, step, scanner, rx0, ry0, cell):
    """No cover rises above the line from (x, y) at ``height`` m above the ground to a scanner
    ``scanner`` m above the ground ``length`` m away along (tx, ty)."""
    n = int(length / (0.5 * cell))
    for s in range(1, n):
        t = s * 0.5 * cell
        i = int(math.floor((x + tx * t - rx0) / cell))
        j = int(math.floor((y + ty * t - ry0) / cell))
        if cover[i, j] * step > height + (scanner - height) * t / length:
            return False
    return True


@nb.njit(cache=True, nogil=True, inline="always")
def clear_to_road(x, y, height, tx, ty, road, cover, step, scanner, rx0, ry0, cell, max_length):
    """:func:`clear` to where the way from (x, y) along (tx, ty) first meets the road (within
    ``max_length``)."""
    for s in range(1, int(max_length / (0.5 * cell))):
        t = s * 0.5 * cell
        i = int(math.floor((x + tx * t - rx0) / cell))
        j = int(math.floor((y + ty * t - ry0) / cell))
        if i < 0 or j < 0 or i >= road.shape[0] or j >= road.shape[1]:
            return False
        if road[i, j]:
            return clear(x, y, height, tx, ty, t, cover, step, scanner, rx0, ry0, cell)
    return False


@nb.njit(cache=True, nogil=True, inline="always")
def sight(x, y, height, nx, ny, road, road_i, road_j, cover, step, scanner, rx0, ry0, cell, reach):
    """Whether a point at (x, y), ``height`` m above the ground, on a surface facing (nx, ny)
    (horizontally; zeros for none), is in sight of a scanner ``scanner`` m above the road:
    along the way to the nearest road cell, or else halfway between that way and the surface's
    facing (the way a passing scanner sees a side wall), or else straight along its facing (a
    back wall facing another street across open ground). The line starts 0.5 m in front of the
    surface, clear of the cells the surface itself stands on."""
    x, y = x + 0.5 * nx, y + 0.5 * ny
    i0 = int(math.floor((x - rx0) / cell))
    j0 = int(math.floor((y - ry0) / cell))
    if i0 < 0 or j0 < 0 or i0 >= road.shape[0] or j0 >= road.shape[1]:
        return False
    if road[i0, j0]:
        return True
    dx = (road_i[i0, j0] - i0) * cell
    dy = (road_j[i0, j0] - j0) * cell
    length = math.sqrt(dx * dx + dy * dy)
    if length > 0 and clear(x, y, height, dx / length, dy / length, length, cover, step, scanner, rx0, ry0, cell):
        return True
    if nx == 0.0 and ny == 0.0 or length == 0.0:
        return False
    tx, ty = dx / length + nx, dy / length + ny
    norm = math.sqrt(tx * tx + ty * ty)
    if norm > 0.3 and clear_to_road(
        x, y, height, tx / norm, ty / norm, road, cover, step, scanner, rx0, ry0, cell, reach + 10.0
    ):
        return True
    return clear_to_road(x, y, height, nx, ny, road, cover, step, scanner, rx0, ry0, cell, reach + 10.0)


@nb.njit(cache=True, nogil=True)
def cells_in_sight(ci, cj, height, road, road_i, road_j, cover, step, scanner, rx0, ry0, cell, reach):
    """:func:`sight` of the ground at the centres of cells (ci, cj)."""
    out = np.empty(ci.shape[0], np.bool_)
    for k in range(ci.shape[0]):
        out[k] = sight(
            rx0 + (ci[k] + 0.5) * cell,
            ry0 + (cj[k] + 0.5) * cell,
            height[k],
            0.0,
            0.0,
            road,
            road_i,
            road_j,
            cover,
            step,
            scanner,
            rx0,
            ry0,
            cell,
            reach,
        )
    return out


@nb.njit(cache=True, nogil=True)
def ground_columns(vx0, vx1, vy0, vy1, voxel, seen, i0, j0, road, z, hx0, hy0, spacing, rx0, ry0, cell, curb):
    """One point per voxel column whose cell is ``seen`` (cells from (i0, j0)): on the road, or
    on the raised lot surface."""
    out = np.empty(((vx1 - vx0) * (vy1 - vy0), 3))
    m = 0
    for a in range(vx0, vx1):
        x = (a + 0.5) * voxel
        i = int(math.floor((x - rx0) / cell))
        if i - i0 < 0 or i - i0 >= seen.shape[0]:
            continue
        for b in range(vy0, vy1):
            y = (b + 0.5) * voxel
            j = int(math.floor((y - ry0) / cell))
            if j - j0 < 0 or j - j0 >= seen.shape[1] or not seen[i - i0, j - j0]:
                continue
            out[m, 0] = x
            out[m, 1] = y
            out[m, 2] = height(x, y, z, hx0, hy0, spacing) + (0.0 if road[i, j] else curb)
            m += 1
    return out[:m]

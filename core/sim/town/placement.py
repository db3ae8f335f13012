"""Where an object may go on the town's ground plan: free cells around a rectangle or a point
(not on the road, not on another object), and marking them taken."""

from __future__ import annotations

import math

import numpy as np

from .constants import CELL, EGO_CLEARANCE_STATIC, SIDEWALK_MIN
from .layout import Plan


def rect_points(cx, cy, yaw, length, width, step=CELL):
    nu = max(2, int(math.ceil(length / step)) + 1)
    nv = max(2, int(math.ceil(width / step)) + 1)
    U, V = np.meshgrid(np.linspace(-length / 2, length / 2, nu), np.linspace(-width / 2, width / 2, nv))
    c, s = math.cos(yaw), math.sin(yaw)
    return cx + U.ravel() * c - V.ravel() * s, cy + U.ravel() * s + V.ravel() * c


def rect_free(plan: Plan, cx, cy, yaw, length, width, clearance=0.0):
    """A footprint can be built: inside the build area, off the road and its sidewalks, away
    from the drive and from everything already placed (``clearance`` keeps a gap)."""
    x, y = rect_points(cx, cy, yaw, length + 2 * clearance, width + 2 * clearance)
    i, j, ok = plan.raster.ij(x, y)
    return bool(
        np.all(
            ok
            & plan.build_area[i, j]
            & ~plan.occupied[i, j]
            & (plan.dist_road[i, j] >= SIDEWALK_MIN)
            & (plan.dist_ego[i, j] >= 5.0)
        )
    )


def mark_rect(plan: Plan, cx, cy, yaw, length, width):
    x, y = rect_points(cx, cy, yaw, length, width, step=CELL / 2)
    plan.raster.paint(plan.occupied, x, y)


def point_free(plan: Plan, x, y, radius, min_road=0.6):
    ang = np.linspace(0, 2 * np.pi, 8, endpoint=False)
    px = np.concatenate([[x], x + radius * np.cos(ang)])
    py = np.concatenate([[y], y + radius * np.sin(ang)])
    i, j, ok = plan.raster.ij(px, py)
    return bool(
        np.all(
            ok
            & ~plan.occupied[i, j]
            & (plan.dist_road[i, j] >= min_road)
            & (plan.dist_ego[i, j] >= EGO_CLEARANCE_STATIC)
        )
    )


def mark_point(plan: Plan, x, y, radius):
    x2, y2 = rect_points(x, y, 0.0, 2 * radius, 2 * radius, step=CELL / 2)
    plan.raster.paint(plan.occupied, x2, y2)

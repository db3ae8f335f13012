"""The town's smaller objects, one builder each: fences, walls and hedges along a line, trees
(crowns of small triangles), poles (street lights, signs), parked cars."""

from __future__ import annotations

import math

import numpy as np

from .constants import CELL, CURB, EGO_CLEARANCE_STATIC
from .layout import Plan
from .placement import mark_point, mark_rect, rect_points
from .solids import Item, Solids


def fence_line(plan: Plan, solids: Solids, rng, p0, p1, kind):
    """A wall, fence or hedge from p0 to p1 on the ground, split where its cells are not free."""
    length = float(np.linalg.norm(p1 - p0))
    if length < 2.0:
        return
    u = np.arange(0.0, length, CELL) + CELL / 2
    pts = p0 + (p1 - p0) / length * u[:, None]
    i, j, ok = plan.raster.ij(pts[:, 0], pts[:, 1])
    free = ok & ~plan.occupied[i, j] & ~plan.road[i, j] & (plan.dist_ego[i, j] >= EGO_CLEARANCE_STATIC)
    runs = np.flatnonzero(np.diff(np.concatenate([[0], free.astype(np.int8), [0]])))
    yaw = math.atan2(*(p1 - p0)[::-1])
    ground = plan.ground
    for r0, r1 in zip(runs[::2], runs[1::2]):
        if (r1 - r0) * CELL < 2.0:
            continue
        a, b = pts[r0] - (pts[1] - pts[0]) * 0.5, pts[r1 - 1] + (pts[1] - pts[0]) * 0.5
        seg = float(np.linalg.norm(b - a))
        mid = 0.5 * (a + b)
        gz = ground(np.array([a[0], mid[0], b[0]]), np.array([a[1], mid[1], b[1]]))
        if kind == "wall":
            h = rng.uniform(0.8, 2.2)
            solids.boxes["wall"].append(
                (mid[0], mid[1], yaw, seg, 0.25, gz.min() - 0.3, gz.max() + CURB + h, float(rng.uniform(0.3, 0.55)))
            )
        elif kind == "hedge":
            h = rng.uniform(1.0, 2.0)
            n = int(seg * h * 14)
            solids.blobs["hedge"].append(
                (mid[0], mid[1], gz.mean() + CURB + h / 2, seg / 2, 0.45, h / 2, yaw, n, 0.3, 2, 0.5)
            )
        else:  # fence: posts every 2.5 m and two rails; rays pass between them
            h = rng.uniform(1.0, 1.8)
            n_posts = int(seg / 2.5) + 1
            for k in range(n_posts):
                q = a + (b - a) * (k / max(n_posts - 1, 1))
                z = float(ground(q[0:1], q[1:2])[0])
                solids.boxes["fence"].append((q[0], q[1], yaw, 0.08, 0.08, z - 0.2, z + CURB + h, 0.45))
            for frac in (0.45, 0.9):
                z = float(gz.mean()) + CURB + h * frac
                solids.boxes["fence"].append((mid[0], mid[1], yaw, seg, 0.04, z - 0.05, z + 0.05, 0.45))
        mark_rect(plan, mid[0], mid[1], yaw, seg, 0.5)
        solids.counts[kind + "s"] += 1


def tree(plan: Plan, solids: Solids, rng, x, y, scale=1.0):
    ground_z = float(plan.ground(np.array([x]), np.array([y]))[0]) + CURB
    conifer = rng.random() < 0.25
    trunk_r = rng.uniform(0.12, 0.3) * scale
    if conifer:
        crown_h = rng.uniform(5.0, 12.0) * scale
        crown_r = crown_h * rng.uniform(0.25, 0.35)
        crown_base = ground_z + rng.uniform(0.8, 2.0)
        trunk_top = crown_base + crown_h * 0.6
        n = int(np.clip(crown_r * crown_h * 12, 80, 450))
        crown = solids.add(
            "blobs",
            "crown",
            (x, y, crown_base, crown_r, crown_r, crown_h, 0.0, n, 0.4, 1, float(rng.uniform(0.4, 0.6))),
        )
    else:
        crown_r = rng.uniform(1.5, 4.0) * scale
        crown_v = crown_r * rng.uniform(0.7, 1.2)
        trunk_top = ground_z + rng.uniform(2.2, 4.0) * scale
        n = int(np.clip(crown_r * crown_v * 22, 80, 450))
        crown = solids.add(
            "blobs",
            "crown",
            (
                x,
                y,
                trunk_top + crown_v * 0.7,
                crown_r,
                crown_r * rng.uniform(0.8, 1.2),
                crown_v,
                rng.uniform(0, np.pi),
                n,
                0.45,
                0,
                float(rng.uniform(0.45, 0.7)),
            ),
        )
    trunk = solids.add("cylinders", "trunk", (x, y, trunk_r, ground_z - 0.3, trunk_top, float(rng.uniform(0.25, 0.4))))
    solids.items.append(Item("tree", x, y, rows=[trunk, crown]))
    mark_point(plan, x, y, max(trunk_r, 0.6))
    solids.counts["trees"] += 1


def pole(plan: Plan, solids: Solids, rng, x, y, toward_road, kind):
    z = float(plan.ground(np.array([x]), np.array([y]))[0]) + CURB
    yaw = math.atan2(toward_road[1], toward_road[0])
    if kind == "light":
        h = rng.uniform(7.0, 9.0)
        solids.cylinders["pole"].append((x, y, 0.1, z - 0.3, z + h, 0.5))
        arm = 1.8
        solids.boxes["pole"].append(
            (x + toward_road[0] * arm / 2, y + toward_road[1] * arm / 2, yaw, arm, 0.15, z + h - 0.25, z + h, 0.5)
        )
        solids.boxes["pole"].append(
            (x + toward_road[0] * arm, y + toward_road[1] * arm, yaw, 0.7, 0.3, z + h - 0.4, z + h - 0.1, 0.6)
        )
    elif kind == "utility":
        h = rng.uniform(9.0, 11.0)
        solids.cylinders["pole"].append((x, y, 0.14, z - 0.3, z + h, 0.35))
        solids.boxes["pole"].append((x, y, yaw + np.pi / 2, 1.8, 0.12, z + h - 0.8, z + h - 0.65, 0.35))
    elif kind == "traffic_light":
        h = rng.uniform(5.0, 6.0)
        solids.cylinders["pole"].append((x, y, 0.12, z - 0.3, z + h, 0.5))
        arm = rng.uniform(3.0, 5.0)
        solids.boxes["pole"].append(
            (x + toward_road[0] * arm / 2, y + toward_road[1] * arm / 2, yaw, arm, 0.15, z + h - 0.2, z + h, 0.5)
        )
        solids.boxes["sign"].append(
            (x + toward_road[0] * arm, y + toward_road[1] * arm, yaw, 0.35, 0.35, z + h - 1.1, z + h, 0.3)
        )
    else:  # sign: thin post with a retro-reflective plate facing the road
        h = rng.uniform(2.2, 3.0)
        post = solids.add("cylinders", "pole", (x, y, 0.04, z - 0.3, z + h, 0.5))
        plate = solids.add("boxes", "sign", (x, y, yaw, 0.03, 0.65, z + h - 0.7, z + h, 0.95))
        solids.items.append(Item("sign", x, y, yaw, rows=[post, plate]))
    mark_point(plan, x, y, 0.5)
    solids.counts["poles"] += 1


def parked_car(plan: Plan, solids: Solids, rng, x, y, yaw):
    kind = rng.choice(3, p=[0.6, 0.3, 0.1])  # car, SUV, van
    length = [rng.uniform(3.9, 4.7), rng.uniform(4.4, 4.9), rng.uniform(4.8, 5.4)][kind]
    width = [rng.uniform(1.7, 1.85), rng.uniform(1.8, 1.95), rng.uniform(1.9, 2.05)][kind]
    body_h = [rng.uniform(0.65, 0.8), rng.uniform(0.8, 1.0), rng.uniform(1.5, 1.9)][kind]
    cabin_h = [rng.uniform(0.45, 0.55), rng.uniform(0.55, 0.7), 0.0][kind]
    fx, fy = rect_points(x, y, yaw, length, width, step=length)
    z = float(plan.ground(fx, fy).min())
    c, s = math.cos(yaw), math.sin(yaw)
    refl = float(rng.uniform(0.1, 0.75))
    rows = [solids.add("boxes", "car", (x, y, yaw, length, width, z + 0.3, z + 0.3 + body_h, refl))]
    if cabin_h > 0:
        back = -0.15 * length
        rows.append(
            solids.add(
                "boxes",
                "glass",
                (
                    x + back * c,
                    y + back * s,
                    yaw,
                    0.55 * length,
                    width - 0.15,
                    z + 0.3 + body_h,
                    z + 0.3 + body_h + cabin_h,
                    0.08,
                ),
            )
        )
    for u in (-1, 1):
        for v in (-1, 1):
            ux, uy = u * (length / 2 - 0.85), v * (width / 2 - 0.12)
            rows.append(
                solids.add(
                    "boxes", "wheel", (x + ux * c - uy * s, y + ux * s + uy * c, yaw, 0.62, 0.22, z, z + 0.62, 0.05)
                )
            )
    solids.items.append(Item("parked_car", x, y, yaw, length, width, rows))
    solids.counts["parked_cars"] += 1

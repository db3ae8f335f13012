"""Everything standing on the ground plan: buildings, walls, fences and hedges, trees and bushes,
street lights, signs and traffic lights, parked cars and centre-line dashes.

:func:`populate` places them beside the streets of a :class:`~.layout.Plan` and returns their
parameters per material (:class:`Solids`); :mod:`.meshes` turns those into triangles.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from .constants import CELL, CURB, EGO_CLEARANCE, JUNCTION_CLEAR

#: Objects of the mapped town that can plausibly move between two drives (a parked car drives
#: off, a sign is put up elsewhere); bins are only ever added (see :mod:`.changes`).
from .furniture import fence_line, parked_car, pole, tree
from .layout import Plan
from .placement import mark_point, mark_rect, point_free, rect_free, rect_points
from .raster import left_normal
from .solids import Item, Solids

#: Objects of the mapped town that can plausibly move between two drives (a parked car drives
#: off, a sign is put up elsewhere); bins are only ever added (see :mod:`.changes`).
MOVABLE_KINDS = ("parked_car", "sign")


def _building(plan: Plan, solids: Solids, rng, cx, cy, yaw, length, width, density):
    """A building: main block, maybe an annex of another height, a gable roof on low houses or
    roof plant on tall ones. Its base is buried below the lowest ground under it."""
    ground = plan.ground
    fx, fy = rect_points(cx, cy, yaw, length, width, step=max(length, width) / 2)
    gz = ground(fx, fy)
    base = float(gz.min()) - 0.5
    top_ground = float(gz.max()) + CURB
    storeys = 1 + int(rng.gamma(1.0 + 5.0 * density**1.5, 1.0 + 1.2 * density))
    height = min(storeys * rng.uniform(2.9, 3.4) + rng.uniform(0.2, 1.0), 45.0)
    refl = float(rng.uniform(0.2, 0.65))
    solids.boxes["building"].append((cx, cy, yaw, length, width, base, top_ground + height, refl))
    building_top(solids, rng, cx, cy, yaw, length, width, top_ground, height, refl, gable=0.6, tower_max=5.0)
    c, s = math.cos(yaw), math.sin(yaw)
    solids.counts["buildings"] += 1
    if rng.random() < 0.35:
        # Annex behind or beside the main block: L- and T-shaped footprints.
        al = rng.uniform(0.35, 0.8) * length
        aw = rng.uniform(4.0, 10.0)
        ux = rng.uniform(-0.5, 0.5) * (length - al)
        uy = width / 2 + aw / 2 - 0.3  # behind: local +v points away from the street (see populate)
        ax, ay = cx + ux * c - uy * s, cy + ux * s + uy * c
        if rect_free(plan, ax, ay, yaw, al, aw - 0.6):
            solids.boxes["building"].append(
                (ax, ay, yaw, al, aw, base, top_ground + max(3.0, height * rng.uniform(0.3, 1.3)), refl)
            )
            mark_rect(plan, ax, ay, yaw, al, aw)
    mark_rect(plan, cx, cy, yaw, length, width)


def building_top(solids: Solids, rng, cx, cy, yaw, length, width, ground, height, refl, gable: float, tower_max: float):
    """What tops a building of ``height`` m standing on ``ground``: a gabled roof on a low one
    (with chance ``gable``), now and then a rooftop block (stairs, machinery; up to ``tower_max``
    m a side) on a tall one. The draws from ``rng`` are the town's own: the town stays the same."""
    if height < 10.0 and rng.random() < gable:
        along = length >= width
        solids.prisms["roof"].append(
            (
                cx,
                cy,
                yaw if along else yaw + np.pi / 2,
                max(length, width),
                min(length, width),
                ground + height,
                rng.uniform(1.2, 3.0),
                float(rng.uniform(0.1, 0.4)),
            )
        )
    elif height > 12.0 and rng.random() < 0.5:
        c, s = math.cos(yaw), math.sin(yaw)
        ux, uy = rng.uniform(-0.3, 0.3) * length, rng.uniform(-0.3, 0.3) * width
        solids.boxes["building"].append(
            (
                cx + ux * c - uy * s,
                cy + ux * s + uy * c,
                yaw,
                rng.uniform(2.5, tower_max),
                rng.uniform(2.5, tower_max),
                ground + height - 0.5,
                ground + height + rng.uniform(2.0, 3.5),
                refl,
            )
        )


def footprint(item: Item) -> tuple[np.ndarray, np.ndarray]:
    """Corner x and y of an item's footprint (its post or trunk for point-like items)."""
    return rect_points(
        item.x, item.y, item.yaw, max(item.length, 1e-3), max(item.width, 1e-3), step=max(item.length, item.width, 1e-3)
    )


def car_spot_free(plan: Plan, x, y, yaw) -> bool:
    """A car can park at (x, y) heading ``yaw``: free road clear of the drive and of junctions
    (the checks of the parking lanes in :func:`populate`)."""
    px, py = rect_points(x, y, yaw, 5.0, 2.0)
    i, j, ok = plan.raster.ij(px, py)
    if not np.all(ok & plan.road[i, j] & ~plan.occupied[i, j] & (plan.dist_ego[i, j] >= EGO_CLEARANCE)):
        return False
    return not (len(plan.junctions) and np.min(np.hypot(*(plan.junctions - [x, y]).T)) < JUNCTION_CLEAR)


def post_spot_free(plan: Plan, x, y) -> bool:
    """A sign post can stand at (x, y) (the check of the signs in :func:`populate`)."""
    return point_free(plan, x, y, 0.3, min_road=0.1)


def occupy(plan: Plan, item: Item) -> None:
    """Mark the ground an item now stands on."""
    if item.kind == "parked_car":
        mark_rect(plan, item.x, item.y, item.yaw, 4.8, 1.9)
    else:
        mark_point(plan, item.x, item.y, 0.5)


def add_parked_car(plan: Plan, solids: Solids, rng, x, y, yaw) -> bool:
    """Park a car at (x, y) heading ``yaw`` if :func:`car_spot_free`; True if it was parked."""
    if not car_spot_free(plan, x, y, yaw):
        return False
    parked_car(plan, solids, rng, x, y, yaw)
    mark_rect(plan, x, y, yaw, 4.8, 1.9)
    return True


def add_sign(plan: Plan, solids: Solids, rng, x, y, toward_road) -> bool:
    """Put up a sign post at (x, y) facing ``toward_road`` if the spot is free; True if it was."""
    if not post_spot_free(plan, x, y):
        return False
    pole(plan, solids, rng, x, y, toward_road, "sign")
    return True


def add_bin(plan: Plan, solids: Solids, rng, x, y, yaw) -> bool:
    """Stand a wheelie bin (about 0.6 × 0.7 × 1.1 m) at (x, y) on the sidewalk if the spot is free."""
    if not point_free(plan, x, y, 0.5, min_road=0.3):
        return False
    z = float(plan.ground(np.array([x]), np.array([y]))[0]) + CURB
    length, width, h = rng.uniform(0.55, 0.75), rng.uniform(0.6, 0.8), rng.uniform(0.95, 1.25)
    row = solids.add("boxes", "bin", (x, y, yaw, length, width, z - 0.05, z + h, float(rng.uniform(0.15, 0.5))))
    solids.items.append(Item("bin", x, y, yaw, length, width, [row]))
    mark_point(plan, x, y, 0.5)
    solids.counts["bins"] += 1
    return True


def populate(plan: Plan, rng) -> Solids:
    """Place everything beside the streets: buildings, walls/fences/hedges, trees, poles, cars,
    centre-line dashes; then back buildings and parks in the remaining space."""
    solids = Solids()
    raster = plan.raster
    junction_tree = cKDTree(plan.junctions) if len(plan.junctions) else None

    def near_junction(p, dist):
        return junction_tree is not None and junction_tree.query(p)[0] < dist

    for st in plan.streets:
        for side in (-1.0, 1.0):
            # Per street side: its own building line and planting style.
            setback_style = rng.uniform(0.0, 1.0)
            has_trees = rng.random() < 0.55
            fence_kind = rng.choice(["wall", "fence", "hedge"])
            prop = st.half_width + st.sidewalk
            s = rng.uniform(0.0, 8.0)
            while s < st.length - 4.0:
                p, t = st.at(s)
                d = float(raster.lookup(plan.density, p[0], p[1]))
                if raster.lookup(plan.park, *(p + side * left_normal(t) * (prop + 6.0))):
                    s += 8.0
                    continue
                width = rng.uniform(8.0, 14.0 + 30.0 * d)
                depth = rng.uniform(8.0, 12.0 + 18.0 * d)
                setback = (rng.uniform(0.0, 1.5) if d > 0.5 else rng.uniform(1.0, 6.0)) * (0.4 + setback_style)
                pm, tm = st.at(s + width / 2)
                normal = side * left_normal(tm)
                centre = pm + normal * (prop + setback + depth / 2)
                yaw = math.atan2(tm[1], tm[0])
                if rng.random() < 0.05 + 0.2 * (1 - d):
                    gap = rng.uniform(8.0, 25.0)  # an empty lot: maybe walled or fenced off
                    if rng.random() < 0.5:
                        a = st.at(s)[0] + side * left_normal(st.at(s)[1]) * (prop + 0.3)
                        b = st.at(s + gap)[0] + side * left_normal(st.at(s + gap)[1]) * (prop + 0.3)
                        fence_line(plan, solids, rng, a, b, fence_kind)
                    s += gap
                    continue
                # In a footprint's own frame (rect_points) +v is to the left of its yaw; turning
                # right-side buildings by π makes +v point away from the street on both sides.
                b_yaw = yaw if side > 0 else yaw + np.pi
                if rect_free(plan, centre[0], centre[1], b_yaw, width - 0.6, depth - 0.6):
                    _building(plan, solids, rng, centre[0], centre[1], b_yaw, width, depth, d)
                    if setback > 2.5 and rng.random() < 0.45:
                        a = st.at(s)[0] + normal * (prop + 0.3)
                        b = st.at(s + width)[0] + normal * (prop + 0.3)
                        fence_line(plan, solids, rng, a, b, fence_kind)
                    s += width + (0.0 if (d > 0.55 and rng.random() < 0.6) else rng.uniform(1.5, 8.0))
                else:
                    s += 2.0

            # Street trees on the sidewalk, near the curb.
            curb_off = st.half_width + min(max(st.sidewalk * 0.45, 0.8), 1.5)
            if has_trees:
                for u in np.arange(rng.uniform(2, 8), st.length, rng.uniform(7.0, 11.0)):
                    p, t = st.at(u + rng.uniform(-0.8, 0.8))
                    q = p + side * left_normal(t) * curb_off
                    if not near_junction(q, st.half_width + 6.0) and point_free(plan, q[0], q[1], 0.6):
                        tree(plan, solids, rng, q[0], q[1], scale=rng.uniform(0.7, 1.0))
        # Street lights (or utility poles) at the curb, on one side or alternating.
        light_kind = "light" if rng.random() < 0.7 else "utility"
        alternate = rng.random() < 0.5
        for k, u in enumerate(np.arange(rng.uniform(5, 20), st.length, rng.uniform(25.0, 40.0))):
            side = (1.0 if k % 2 else -1.0) if alternate else 1.0
            p, t = st.at(u)
            q = p + side * left_normal(t) * (st.half_width + 0.7)
            if point_free(plan, q[0], q[1], 0.3, min_road=0.1):
                pole(plan, solids, rng, q[0], q[1], -side * left_normal(t), light_kind)

    # Signs and traffic lights at junction corners.
    for jp in plan.junctions:
        lights = rng.random() < 0.3
        for ang in rng.uniform(0, 2 * np.pi) + np.arange(4) * np.pi / 2:
            if rng.random() < (0.6 if lights else 0.35):
                for dist in (8.5, 9.5, 10.5, 7.5):
                    q = jp + dist * np.array([math.cos(ang), math.sin(ang)])
                    i, j, ok = raster.ij(q[0], q[1])
                    if ok and 0.2 <= plan.dist_road[i, j] <= 2.0 and point_free(plan, q[0], q[1], 0.3, min_road=0.1):
                        pole(plan, solids, rng, q[0], q[1], plan.road_dir[i, j], "traffic_light" if lights else "sign")
                        break

    # Parked cars in the parking lanes; right curb faces the street's direction, left curb against.
    for st in plan.streets:
        if not st.parking:
            continue
        for side in (-1.0, 1.0):
            fill = rng.uniform(0.25, 0.85)
            u = rng.uniform(2.0, 6.0)
            while u < st.length - 3.0:
                p, t = st.at(u)
                q = p + side * left_normal(t) * (st.half_width - 1.15)
                yaw = math.atan2(t[1], t[0]) + (0.0 if side < 0 else np.pi) + rng.uniform(-0.03, 0.03)
                if rng.random() < fill and not near_junction(q, JUNCTION_CLEAR):
                    x, y = rect_points(q[0], q[1], yaw, 5.0, 2.0)
                    i, j, ok = raster.ij(x, y)
                    if np.all(ok & plan.road[i, j] & ~plan.occupied[i, j] & (plan.dist_ego[i, j] >= EGO_CLEARANCE)):
                        parked_car(plan, solids, rng, q[0], q[1], yaw)
                        mark_rect(plan, q[0], q[1], yaw, 4.8, 1.9)
                u += rng.uniform(5.6, 7.0)

    # Dashed centre lines, not across junctions.
    for st in plan.streets:
        for u in np.arange(rng.uniform(0, 9), st.length - 3.0, 9.0):
            p, t = st.at(u + 1.5)
            if not near_junction(p, JUNCTION_CLEAR) and raster.lookup(plan.road, p[0], p[1]):
                solids.decals["marking"].append((p[0], p[1], math.atan2(t[1], t[0]), 3.0, 0.15, 0.85))

    # Back buildings inside big blocks, then trees and bushes in yards and parks.
    free_cells = np.flatnonzero((plan.build_area & ~plan.occupied & ~plan.park & (plan.dist_road >= 12.0)).ravel())
    if len(free_cells):
        for cell in rng.choice(free_cells, size=min(len(free_cells), 400), replace=False):
            i, j = np.unravel_index(cell, raster.shape)
            if plan.occupied[i, j]:
                continue
            d = float(plan.density[i, j])
            x, y = raster.x0 + (i + 0.5) * CELL, raster.y0 + (j + 0.5) * CELL
            rd = plan.road_dir[i, j]
            yaw = math.atan2(rd[1], rd[0]) + np.pi / 2 + rng.choice([0.0, np.pi / 2]) + rng.normal(0, 0.05)
            length, width = rng.uniform(8.0, 14.0 + 20.0 * d), rng.uniform(7.0, 10.0 + 14.0 * d)
            if rect_free(plan, x, y, yaw, length, width, clearance=2.5):
                _building(plan, solids, rng, x, y, yaw, length, width, d)
    green = ~plan.road & ~plan.occupied & (plan.dist_road >= 1.5) & (plan.dist_ego >= 3.0)
    cells = np.flatnonzero(green.ravel())
    if len(cells):
        tries = rng.choice(cells, size=min(len(cells), int(len(cells) * CELL * CELL / 90.0)), replace=False)
        for cell in tries:
            i, j = np.unravel_index(cell, raster.shape)
            in_park = plan.park[i, j]
            if rng.random() > (0.9 if in_park else 0.25 * (1.0 - plan.density[i, j]) ** 2):
                continue
            x = raster.x0 + (i + rng.random()) * CELL
            y = raster.y0 + (j + rng.random()) * CELL
            if rng.random() < 0.3:  # a bush
                if point_free(plan, x, y, 0.8, min_road=1.5):
                    gz = float(plan.ground(np.array([x]), np.array([y]))[0]) + CURB
                    r = rng.uniform(0.5, 1.3)
                    solids.blobs["bush"].append(
                        (
                            x,
                            y,
                            gz + r * 0.6,
                            r,
                            r,
                            r * 0.7,
                            0.0,
                            int(40 * r * r + 20),
                            0.3,
                            0,
                            float(rng.uniform(0.4, 0.6)),
                        )
                    )
                    mark_point(plan, x, y, r * 0.8)
                    solids.counts["bushes"] += 1
            elif point_free(plan, x, y, 1.2, min_road=1.5):
                tree(plan, solids, rng, x, y)
    return solids

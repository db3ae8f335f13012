"""Everything standing in a city, district by district: the same kinds of objects as a town's
(:mod:`.objects`, whose placement rules it reuses), placed by each district's :class:`~.districts.Style`
— downtown towers wall to wall, suburban houses behind front gardens and hedges, industrial
halls behind fences with containers in their yards, parks of trees with footpaths and lamps —
and the highway's own: guard rails along its verges, noise walls, tall lights, lane lines.

:func:`populate_city` returns the objects' parameters (:class:`~.objects.Solids`) as
:func:`~.objects.populate` does for a town, so that meshes, changes and traffic treat both alike.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from .constants import CELL, CURB, JUNCTION_CLEAR
from .districts import DOWNTOWN, HIGHWAY, INDUSTRIAL, PARK, STYLES, SUBURB, Style
from .furniture import fence_line, parked_car, pole, tree
from .layout import Plan, Street
from .objects import building_top
from .placement import mark_point, mark_rect, point_free, rect_free, rect_points
from .raster import left_normal
from .solids import Solids


def populate_city(plan: Plan, rng: np.random.Generator) -> Solids:
    solids = Solids()
    tree = cKDTree(plan.junctions) if len(plan.junctions) else None

    def near_junction(p, dist):
        return tree is not None and tree.query(p)[0] < dist

    for st in plan.streets:
        if st.kind == "highway":
            _highway(plan, solids, rng, st, near_junction)
            continue
        for side in (-1.0, 1.0):
            _frontage(plan, solids, rng, st, side, near_junction)
        _street_lights(plan, solids, rng, st)
    _junction_poles(plan, solids, rng)
    _parking(plan, solids, rng, near_junction)
    _markings(plan, solids, rng, near_junction)
    _back_lots(plan, solids, rng)
    _park_paths(plan, solids, rng)
    _greenery(plan, solids, rng)
    return solids


def _style_at(plan: Plan, p) -> int:
    return int(plan.districts.style_at(p[0], p[1]))


# --------------------------------------------------------------------------------- along the streets
def _frontage(plan: Plan, solids: Solids, rng, st: Street, side: float, near_junction) -> None:
    """Buildings along one side of a street, each in the style of the district behind it, with
    front fences and (in suburbs) side hedges on the lot lines; then the street's trees."""
    prop = st.half_width + st.sidewalk
    mid, mid_t = st.at(st.length / 2)
    side_style = STYLES[_style_at(plan, mid + side * left_normal(mid_t) * (prop + 10.0))]
    fence_kind = str(rng.choice(["wall", "fence", "hedge"], p=np.asarray(side_style.fences) / sum(side_style.fences)))
    has_trees = rng.random() < side_style.street_trees
    s = rng.uniform(0.0, 8.0)
    while s < st.length - 4.0:
        p, t = st.at(s)
        normal = side * left_normal(t)
        code = _style_at(plan, p + normal * (prop + 10.0))
        S = STYLES[code]
        if code == HIGHWAY or rng.random() < S.empty_lot:
            gap = rng.uniform(8.0, 25.0)
            if rng.random() < S.front_fence:
                a = p + normal * (prop + 0.3)
                q, tq = st.at(s + gap)
                fence_line(plan, solids, rng, a, q + side * left_normal(tq) * (prop + 0.3), fence_kind)
            s += gap
            continue
        width, depth, setback = rng.uniform(*S.lot_width), rng.uniform(*S.depth), rng.uniform(*S.setback)
        pm, tm = st.at(s + width / 2)
        normal = side * left_normal(tm)
        centre = pm + normal * (prop + setback + depth / 2)
        yaw = math.atan2(tm[1], tm[0])
        b_yaw = yaw if side > 0 else yaw + np.pi  # local +v away from the street on both sides
        if rect_free(plan, centre[0], centre[1], b_yaw, width - 0.6, depth - 0.6):
            _building(plan, solids, rng, centre[0], centre[1], b_yaw, width, depth, code)
            if setback > 2.5 and rng.random() < S.front_fence:
                a = st.at(s)[0] + normal * (prop + 0.3)
                b = st.at(s + width)[0] + normal * (prop + 0.3)
                fence_line(plan, solids, rng, a, b, fence_kind)
            if code == SUBURB and rng.random() < 0.5:  # a hedge or fence between two gardens
                a = st.at(s - 1.0)[0] + normal * (prop + 0.5)
                fence_line(
                    plan,
                    solids,
                    rng,
                    a,
                    a + normal * (setback + depth + 6.0),
                    "hedge" if rng.random() < 0.6 else "fence",
                )
            s += width + (0.0 if rng.random() < S.no_gap else rng.uniform(*S.gap))
        else:
            s += 2.0
    if has_trees:
        curb_off = st.half_width + min(max(st.sidewalk * 0.45, 0.8), 1.5)
        for u in np.arange(rng.uniform(2, 8), st.length, rng.uniform(7.0, 11.0)):
            p, t = st.at(u + rng.uniform(-0.8, 0.8))
            q = p + side * left_normal(t) * curb_off
            if not near_junction(q, st.half_width + 6.0) and point_free(plan, q[0], q[1], 0.6):
                tree(plan, solids, rng, q[0], q[1], scale=rng.uniform(0.7, 1.0))


def _building(plan: Plan, solids: Solids, rng, cx, cy, yaw, length, width, code: int) -> None:
    """One building in its district's style: its height drawn log-uniformly in the style's range
    (downtown: taller towards the centre), a gable roof on some low ones, roof plant on tall
    ones, a garage or an annex beside some. The base is buried below the lowest ground under it."""
    S: Style = STYLES[code]
    fx, fy = rect_points(cx, cy, yaw, length, width, step=max(length, width) / 2)
    gz = plan.ground(fx, fy)
    base, top_ground = float(gz.min()) - 0.5, float(gz.max()) + CURB
    lo, hi = S.height
    u = rng.random()
    if code == DOWNTOWN:
        d = plan.districts
        closeness = 1.0 - min(math.hypot(cx - d.centre[0], cy - d.centre[1]) / d.downtown_radius, 1.0)
        u *= 0.4 + 0.6 * closeness
    height = lo * (hi / lo) ** u
    refl = float(rng.uniform(0.2, 0.65))
    solids.boxes["building"].append((cx, cy, yaw, length, width, base, top_ground + height, refl))
    building_top(solids, rng, cx, cy, yaw, length, width, top_ground, height, refl, gable=S.gable, tower_max=6.0)
    solids.counts["buildings"] += 1
    if code in (SUBURB, INDUSTRIAL) and rng.random() < 0.35:
        # A garage beside a house, an office or loading bay beside a hall.
        c, s = math.cos(yaw), math.sin(yaw)
        al = rng.uniform(4.0, 7.0) if code == SUBURB else rng.uniform(8.0, 20.0)
        aw = rng.uniform(0.5, 0.8) * width
        ux = (length / 2 + al / 2 + 0.2) * rng.choice([-1.0, 1.0])
        uy = (width - aw) / 2
        ax, ay = cx + ux * c - uy * s, cy + ux * s + uy * c
        if rect_free(plan, ax, ay, yaw, al - 0.6, aw - 0.6):
            ah = rng.uniform(2.6, 3.2) if code == SUBURB else rng.uniform(4.0, 7.0)
            solids.boxes["building"].append((ax, ay, yaw, al, aw, base, top_ground + ah, refl))
            mark_rect(plan, ax, ay, yaw, al, aw)
    mark_rect(plan, cx, cy, yaw, length, width)


def _street_lights(plan: Plan, solids: Solids, rng, st: Street) -> None:
    code = st.style
    light_kind = "utility" if code == SUBURB and rng.random() < 0.5 else "light"
    alternate = rng.random() < 0.5
    for k, u in enumerate(np.arange(rng.uniform(5, 20), st.length, rng.uniform(25.0, 40.0))):
        side = (1.0 if k % 2 else -1.0) if alternate else 1.0
        p, t = st.at(u)
        q = p + side * left_normal(t) * (st.half_width + 0.7)
        if point_free(plan, q[0], q[1], 0.3, min_road=0.1):
            pole(plan, solids, rng, q[0], q[1], -side * left_normal(t), light_kind)


def _junction_poles(plan: Plan, solids: Solids, rng) -> None:
    """Signs or traffic lights at junction corners (lights mostly downtown)."""
    raster = plan.raster
    for jp in plan.junctions:
        lights = rng.random() < STYLES[_style_at(plan, jp)].traffic_lights
        for ang in rng.uniform(0, 2 * np.pi) + np.arange(4) * np.pi / 2:
            if rng.random() < (0.6 if lights else 0.35):
                for dist in (8.5, 9.5, 10.5, 12.5, 14.5):
                    q = jp + dist * np.array([math.cos(ang), math.sin(ang)])
                    i, j, ok = raster.ij(q[0], q[1])
                    if ok and 0.2 <= plan.dist_road[i, j] <= 2.0 and point_free(plan, q[0], q[1], 0.3, min_road=0.1):
                        pole(plan, solids, rng, q[0], q[1], plan.road_dir[i, j], "traffic_light" if lights else "sign")
                        break


def _parking(plan: Plan, solids: Solids, rng, near_junction) -> None:
    """Parked cars in the parking lanes, as full as the district's streets are."""
    raster = plan.raster
    for st in plan.streets:
        if not st.parking:
            continue
        lo, hi = STYLES[st.style if st.style >= 0 else SUBURB].parking_fill
        for side in (-1.0, 1.0):
            fill = rng.uniform(lo, hi)
            u = rng.uniform(2.0, 6.0)
            while u < st.length - 3.0:
                p, t = st.at(u)
                q = p + side * left_normal(t) * (st.half_width - 1.15)
                yaw = math.atan2(t[1], t[0]) + (0.0 if side < 0 else np.pi) + rng.uniform(-0.03, 0.03)
                if rng.random() < fill and not near_junction(q, JUNCTION_CLEAR):
                    x, y = rect_points(q[0], q[1], yaw, 5.0, 2.0)
                    i, j, ok = raster.ij(x, y)
                    if np.all(ok & plan.road[i, j] & ~plan.occupied[i, j]):
                        parked_car(plan, solids, rng, q[0], q[1], yaw)
                        mark_rect(plan, q[0], q[1], yaw, 4.8, 1.9)
                u += rng.uniform(5.6, 7.0)


def _markings(plan: Plan, solids: Solids, rng, near_junction) -> None:
    """Dashed centre lines (and the ring's lane lines), not across junctions."""
    for st in plan.streets:
        offsets = (-7.0, -3.5, 0.0, 3.5, 7.0) if st.kind == "highway" else (0.0,)
        for u in np.arange(rng.uniform(0, 9), st.length - 3.0, 9.0):
            p, t = st.at(u + 1.5)
            if near_junction(p, JUNCTION_CLEAR + (st.half_width if st.kind == "highway" else 0.0)):
                continue
            for off in offsets:
                q = p + left_normal(t) * off
                if plan.raster.lookup(plan.road, q[0], q[1]):
                    solids.decals["marking"].append((q[0], q[1], math.atan2(t[1], t[0]), 3.0, 0.15, 0.85))


def _highway(plan: Plan, solids: Solids, rng, st: Street, near_junction) -> None:
    """The ring: guard rails on both verges (open at junctions), noise walls behind them along
    about half its length, tall lights on both sides, and nothing else nearby."""
    step = 4.0
    for side in (-1.0, 1.0):
        us = np.arange(2.0, st.length - 2.0, step)
        rail, wall = [], []
        wall_on = rng.random() < 0.5
        next_switch = rng.uniform(60.0, 300.0)
        wall_off = rng.uniform(3.0, 8.0)
        for u in us:
            p, t = st.at(u)
            n = side * left_normal(t)
            if u >= next_switch:
                wall_on, next_switch = not wall_on, u + rng.uniform(60.0, 300.0)
            clear = not near_junction(p, st.half_width + 14.0)
            rail.append(p + n * (st.half_width + 0.6) if clear else None)
            wall.append(p + n * (st.half_width + st.sidewalk + wall_off) if clear and wall_on else None)
        _runs(plan, solids, rail, step, "barrier", 0.3, 0.8, 0.3)
        _runs(plan, solids, wall, step, "wall", 0.3, rng.uniform(3.5, 5.0), float(rng.uniform(0.3, 0.5)))
    for k, u in enumerate(np.arange(rng.uniform(5, 20), st.length, rng.uniform(40.0, 50.0))):
        side = 1.0 if k % 2 else -1.0
        p, t = st.at(u)
        q = p + side * left_normal(t) * (st.half_width + 1.5)
        if not near_junction(p, st.half_width + 10.0) and point_free(plan, q[0], q[1], 0.3, min_road=0.1):
            pole(plan, solids, rng, q[0], q[1], -side * left_normal(t), "light")


def _runs(
    plan: Plan, solids: Solids, points: list, step: float, material: str, thickness: float, height: float, refl: float
) -> None:
    """Upright boxes along consecutive points (None breaks a run), at most 40 m each."""
    ground = plan.ground
    run: list = []
    for q in points + [None]:
        if q is not None and len(run) * step < 40.0:
            run.append(q)
            continue
        if len(run) >= 2:
            a, b = run[0] - (run[1] - run[0]) / 2, run[-1] + (run[-1] - run[-2]) / 2
            mid, length = 0.5 * (a + b), float(np.linalg.norm(b - a))
            gz = ground(np.array([a[0], mid[0], b[0]]), np.array([a[1], mid[1], b[1]]))
            solids.boxes[material].append(
                (
                    mid[0],
                    mid[1],
                    math.atan2(*(b - a)[::-1]),
                    length,
                    thickness,
                    gz.min() - 0.3,
                    gz.max() + CURB + height,
                    refl,
                )
            )
            mark_rect(plan, mid[0], mid[1], math.atan2(*(b - a)[::-1]), length, thickness + 0.2)
            solids.counts[material + "s"] += 1
        run = [q] if q is not None else []


# --------------------------------------------------------------------------------- behind the streets
def _free_samples(plan: Plan, rng, n: int, min_road: float, codes) -> np.ndarray:
    """Up to ``n`` random points of the city on buildable, free ground at least ``min_road`` from
    the road, in districts of ``codes``."""
    raster = plan.raster
    x = raster.x0 + rng.random(n) * raster.nx * CELL
    y = raster.y0 + rng.random(n) * raster.ny * CELL
    i, j, _ = raster.ij(x, y)
    ok = plan.build_area[i, j] & ~plan.occupied[i, j] & (plan.dist_road[i, j] >= min_road)
    ok &= np.isin(plan.districts.style_at(x, y), codes)
    return np.stack([x[ok], y[ok]], axis=1)


def _back_lots(plan: Plan, solids: Solids, rng) -> None:
    """Courtyard buildings downtown, sheds in suburban back gardens, containers and trailers in
    industrial yards."""
    raster = plan.raster
    area = raster.nx * raster.ny * CELL * CELL
    for x, y in _free_samples(plan, rng, int(area / 2500.0), 12.0, (DOWNTOWN, SUBURB)):
        i, j, _ = raster.ij(x, y)
        rd = plan.road_dir[i, j]
        yaw = math.atan2(rd[1], rd[0]) + np.pi / 2 + rng.normal(0, 0.05)
        code = _style_at(plan, (x, y))
        if code == DOWNTOWN:
            length, width = rng.uniform(10.0, 25.0), rng.uniform(8.0, 18.0)
            if rect_free(plan, x, y, yaw, length, width, clearance=2.5):
                _building(plan, solids, rng, x, y, yaw, length, width, DOWNTOWN)
        elif rng.random() < 0.3:
            length, width = rng.uniform(2.5, 4.0), rng.uniform(2.0, 3.0)
            if rect_free(plan, x, y, yaw, length, width, clearance=1.0):
                z = float(plan.ground(np.array([x]), np.array([y]))[0])
                solids.boxes["building"].append(
                    (x, y, yaw, length, width, z - 0.3, z + CURB + rng.uniform(2.0, 2.6), float(rng.uniform(0.2, 0.5)))
                )
                mark_rect(plan, x, y, yaw, length, width)
                solids.counts["sheds"] += 1
    for x, y in _free_samples(plan, rng, int(area / 600.0), 10.0, (INDUSTRIAL,)):
        i, j, _ = raster.ij(x, y)
        rd = plan.road_dir[i, j]
        yaw = math.atan2(rd[1], rd[0]) + rng.choice([0.0, np.pi / 2]) + rng.normal(0, 0.03)
        trailer = rng.random() < 0.25
        length, width = (13.6, 2.55) if trailer else (float(rng.choice([6.06, 12.19])), 2.44)
        if not rect_free(plan, x, y, yaw, length, width, clearance=0.8):
            continue
        z = float(plan.ground(*rect_points(x, y, yaw, length, width, step=length)).min())
        levels = 1 if trailer else int(rng.choice([1, 1, 2, 3]))
        height = 4.0 if trailer else 2.59
        solids.boxes["container"].append(
            (x, y, yaw, length, width, z - 0.2, z + CURB + height * levels, float(rng.uniform(0.15, 0.7)))
        )
        mark_rect(plan, x, y, yaw, length, width)
        solids.counts["containers"] += 1


def _park_paths(plan: Plan, solids: Solids, rng) -> None:
    """Footpaths wandering through the parks (paving a little brighter than the grass), with a
    lamp every 25 m and a bench now and then."""
    raster = plan.raster
    park_cells = int(plan.park.sum())
    n_paths = int(park_cells * CELL * CELL / 8000.0)
    if n_paths == 0:
        return
    starts = _free_samples(plan, rng, 50 * n_paths, 4.0, (PARK,))[:n_paths]
    for x, y in starts:
        heading = rng.uniform(0, 2 * np.pi)
        p = np.array([x, y])
        since_lamp = rng.uniform(0.0, 25.0)
        for _ in range(int(rng.uniform(40, 120))):
            heading += rng.normal(0.0, 0.12)
            q = p + 2.5 * np.array([math.cos(heading), math.sin(heading)])
            i, j, ok = raster.ij(q[0], q[1])
            if not (ok and plan.park[i, j] and plan.dist_road[i, j] > 3.0):
                break
            mid = 0.5 * (p + q)
            z = float(plan.ground(mid[0:1], mid[1:2])[0]) + CURB  # on the lawn, not at road level
            solids.boxes["path"].append(
                (mid[0], mid[1], heading, 2.6, 2.4, z - 0.1, z + 0.02, float(rng.uniform(0.32, 0.4)))
            )
            mark_rect(plan, mid[0], mid[1], heading, 2.5, 2.4)
            since_lamp += 2.5
            if since_lamp >= 25.0:
                n = left_normal(np.array([math.cos(heading), math.sin(heading)]))
                lamp = mid + 1.8 * n
                if point_free(plan, lamp[0], lamp[1], 0.3, min_road=0.1):
                    pole(plan, solids, rng, lamp[0], lamp[1], -n, "light")
                    since_lamp = 0.0
                elif rng.random() < 0.3:
                    bench = mid - 1.8 * n
                    if point_free(plan, bench[0], bench[1], 1.0, min_road=0.1):
                        z = float(plan.ground(np.array([bench[0]]), np.array([bench[1]]))[0]) + CURB
                        solids.boxes["bench"].append((bench[0], bench[1], heading, 1.8, 0.6, z, z + 0.85, 0.4))
                        mark_point(plan, bench[0], bench[1], 1.0)
            p = q
    solids.counts["paths"] += len(starts)


def _greenery(plan: Plan, solids: Solids, rng) -> None:
    """Trees and bushes on the free ground left, as many as each district's style plants."""
    raster = plan.raster
    share = np.array([STYLES[k].green for k in range(len(STYLES))])
    n = int(raster.nx * raster.ny * CELL * CELL / 90.0 * share.max())
    x = raster.x0 + rng.random(n) * raster.nx * CELL
    y = raster.y0 + rng.random(n) * raster.ny * CELL
    i, j, _ = raster.ij(x, y)
    green = ~plan.road[i, j] & ~plan.occupied[i, j] & (plan.dist_road[i, j] >= 1.5)
    keep = green & (rng.random(n) < share[plan.districts.style_at(x, y)] / share.max())
    bush_draw = rng.random(n)
    for k in np.flatnonzero(keep):
        if bush_draw[k] < 0.3:
            if point_free(plan, x[k], y[k], 0.8, min_road=1.5):
                gz = float(plan.ground(x[k : k + 1], y[k : k + 1])[0]) + CURB
                r = rng.uniform(0.5, 1.3)
                solids.blobs["bush"].append(
                    (
                        x[k],
                        y[k],
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
                mark_point(plan, x[k], y[k], r * 0.8)
                solids.counts["bushes"] += 1
        elif point_free(plan, x[k], y[k], 1.2, min_road=1.5):
            tree(plan, solids, rng, x[k], y[k])

"""What changed in the town between the mapping drive and a later drive (``town.changes``).

With share ``c`` in [0, 1]:

- of the N movable objects of the mapped town (parked cars and sign posts, see
  :data:`~.objects.MOVABLE_KINDS`), ``round(c·N)`` change, about a third each: **moved** (a car
  parked again up or down the street, a sign post put up along it: 2–8 m and 1.5–5 m away,
  farther where there is no room), **removed**,
  or **added** (a new object where none was: half parked cars, 30 % wheelie bins on the
  sidewalk, 20 % sign posts). The mapped town has no bins: adding them to it would change every
  scan of the default town and every cached map, so bins only ever appear as additions. A move
  that finds no free spot becomes a removal (the count stays);
- of the T trees, ``round(c·T)`` change, half **cut** (gone), half **grown** (crown 15–40 %
  wider and taller, with new foliage).

Everything is drawn from the town seed's own changes stream, so a given (seed, c) is always the
same changed town, and c = 0 is the mapped town itself. The changed world's triangles are the
mapped world's minus those of every removed, moved or regrown object, plus one new set for the
objects where they are now.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from ..lidar_sim import MeshPart
from .constants import CHANGES_STREAM
from .meshes import object_parts, row_triangles
from .objects import (
    MOVABLE_KINDS,
    add_bin,
    add_parked_car,
    add_sign,
    car_spot_free,
    footprint,
    occupy,
    post_spot_free,
)
from .raster import left_normal
from .solids import Item, Solids
from .world import Town

ADDED_KINDS = ("parked_car", "bin", "sign")
ADDED_P = (0.5, 0.3, 0.2)


@dataclass
class ChangeRecord:
    """What changed: the items as they were mapped, except ``moved_to`` (where the ``moved``
    ones are now, in the same order), ``added`` and ``grown`` (the new crowns)."""

    n_movable: int
    n_trees: int
    moved: list[Item] = field(default_factory=list)
    moved_to: list[Item] = field(default_factory=list)
    removed: list[Item] = field(default_factory=list)
    added: list[Item] = field(default_factory=list)
    cut: list[Item] = field(default_factory=list)
    grown: list[Item] = field(default_factory=list)

    def counts(self) -> dict:
        return dict(
            movable=self.n_movable,
            moved=len(self.moved),
            removed=len(self.removed),
            added=len(self.added),
            trees=self.n_trees,
            cut=len(self.cut),
            grown=len(self.grown),
        )


def changed_world(town: Town, share: float) -> tuple[list[MeshPart], ChangeRecord, Solids]:
    """The town's triangles after ``share`` of its movable objects and trees changed, what
    changed, and the new objects' parameters."""
    rng = np.random.default_rng([town.seed, *CHANGES_STREAM])
    plan = replace(town.plan, occupied=town.plan.occupied.copy())
    solids = town.solids
    movable = [it for it in solids.items if it.kind in MOVABLE_KINDS]
    trees = [it for it in solids.items if it.kind == "tree"]
    record = ChangeRecord(len(movable), len(trees))
    new = Solids()

    n = int(round(share * len(movable)))
    n_moved = int(round(n / 3))
    n_removed = int(round(n / 3))
    picked = [movable[k] for k in rng.permutation(len(movable))[: n_moved + n_removed]]
    # The ground under removed and moved objects stays taken: nothing new takes their place,
    # so every change is one a scan can see.
    record.removed = picked[n_moved:]
    for item in picked[:n_moved]:
        now = _move(plan, solids, new, rng, item)
        if now is None:
            record.removed.append(item)  # nowhere to go: it is gone
        else:
            record.moved.append(item)
            record.moved_to.append(now)
    record.added = _add(plan, new, rng, n - n_moved - n_removed)

    m = int(round(share * len(trees)))
    picked_trees = [trees[k] for k in rng.permutation(len(trees))[:m]]
    record.cut = picked_trees[: m // 2]
    grown = [_grow(solids, new, rng, tree) for tree in picked_trees[m // 2 :]]

    gone = [key for item in record.removed + record.moved + record.cut for key in item.rows]
    gone += [key for item in picked_trees[m // 2 :] for key in item.rows if key[0] == "blobs"]  # the old crowns
    record.grown = grown
    parts = _without(town.parts, solids, gone) + object_parts(new, plan.ground, rng)
    return parts, record, new


def _without(parts: list[MeshPart], solids: Solids, keys) -> list[MeshPart]:
    """The parts without the triangles of the object rows ``keys``."""
    offsets = row_triangles(solids)
    drop: dict[str, list[np.ndarray]] = {}
    for store, material, index in keys:
        o = offsets[(store, material)]
        drop.setdefault(material, []).append(np.arange(o[index], o[index + 1]))
    out = []
    for part in parts:
        if part.name not in drop:
            out.append(part)
            continue
        keep = np.ones(part.n_triangles, bool)
        keep[np.concatenate(drop[part.name])] = False
        out.append(MeshPart(part.name, part.vertices, part.triangles[keep], part.reflectivity[keep]))
    return out


def _shifted_row(store: str, row: tuple, dx: float, dy: float, dz: float) -> tuple:
    shifted = list(row)
    shifted[0] += dx
    shifted[1] += dy
    if store in ("boxes", "prisms"):
        shifted[5] += dz
        if store == "boxes":
            shifted[6] += dz
    elif store == "cylinders":
        shifted[3] += dz
        shifted[4] += dz
    elif store == "blobs":
        shifted[2] += dz
    return tuple(shifted)


def _move(plan, solids: Solids, new: Solids, rng, item: Item) -> Item | None:
    """Put ``item`` a few metres along its street if there is room; the item where it is now,
    or None if there was no room."""
    if item.kind == "parked_car":
        along = np.array([math.cos(item.yaw), math.sin(item.yaw)])
        distances = (2.0, 8.0)
    else:  # a sign faces the road: along the street is across its yaw
        along = left_normal(np.array([math.cos(item.yaw), math.sin(item.yaw)]))
        distances = (1.5, 5.0)
    for attempt in range(40):  # farther and farther along the street until there is room
        d = rng.uniform(distances[0], distances[1] * (1.0 + attempt / 8.0)) * rng.choice([-1.0, 1.0])
        x, y = item.x + d * along[0], item.y + d * along[1]
        moved = Item(item.kind, x, y, item.yaw, item.length, item.width)
        free = car_spot_free(plan, x, y, item.yaw) if item.kind == "parked_car" else post_spot_free(plan, x, y)
        if not free:
            continue
        # Cars sit on the lowest ground under their footprint, posts on the ground at their foot.
        dz = float(plan.ground(*footprint(moved)).min() - plan.ground(*footprint(item)).min())
        for store, material, index in item.rows:
            moved.rows.append(
                new.add(
                    store,
                    material,
                    _shifted_row(store, solids.row((store, material, index)), x - item.x, y - item.y, dz),
                )
            )
        new.items.append(moved)
        occupy(plan, moved)
        return moved
    return None


def _add(plan, new: Solids, rng, n: int) -> list[Item]:
    """``n`` new objects beside random streets (cars in the parking lanes, bins and signs on the
    sidewalk near the curb)."""
    streets = plan.streets
    parking = [st for st in streets if st.parking]
    added: list[Item] = []
    for _ in range(200 * n):
        if len(added) >= n:
            break
        kind = ADDED_KINDS[int(rng.choice(len(ADDED_KINDS), p=ADDED_P))]
        pool = parking if kind == "parked_car" and parking else streets
        st = pool[int(rng.integers(len(pool)))]
        side = float(rng.choice([-1.0, 1.0]))
        p, t = st.at(rng.uniform(0.0, st.length))
        normal = side * left_normal(t)
        before = len(new.items)
        if kind == "parked_car" and st.parking:
            q = p + normal * (st.half_width - 1.15)
            yaw = math.atan2(t[1], t[0]) + (0.0 if side < 0 else math.pi) + rng.uniform(-0.03, 0.03)
            add_parked_car(plan, new, rng, q[0], q[1], yaw)
        elif kind == "bin":
            q = p + normal * (st.half_width + rng.uniform(0.5, 0.9))
            add_bin(plan, new, rng, q[0], q[1], math.atan2(t[1], t[0]))
        else:
            q = p + normal * (st.half_width + 0.7)
            add_sign(plan, new, rng, q[0], q[1], -normal)
        added.extend(new.items[before:])
    return added


def _grow(solids: Solids, new: Solids, rng, tree: Item) -> Item:
    """A new, bigger crown for ``tree`` (its trunk stays): 15–40 % wider and taller, grown
    upwards from where it starts, with foliage as dense as before."""
    key = next(k for k in tree.rows if k[0] == "blobs")
    cx, cy, cz, rx, ry, rz, yaw, n, leaf, shape, refl = solids.row(key)
    g = float(rng.uniform(1.15, 1.4))
    if shape == 1:  # a cone from its base: the base stays
        row = (cx, cy, cz, rx * g, ry * g, rz * g, yaw, int(n * g * g), leaf, shape, refl)
    else:  # an ellipsoid around its centre: its bottom stays
        row = (cx, cy, cz - rz + rz * g, rx * g, ry * g, rz * g, yaw, int(n * g * g), leaf, shape, refl)
    grown = Item("tree", tree.x, tree.y, rows=[new.add("blobs", "crown", row)])
    new.items.append(grown)
    return grown

"""What the town's objects are made of: the solid primitives (boxes, prisms, cylinders, crowns)
the meshes are cut from, and the movable items among them."""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, field


@dataclass
class Item:
    """One object the town's changes can move, remove or regrow, and the rows that draw it: each
    row is (store, material, index) into :class:`Solids` (e.g. ("boxes", "car", 12))."""

    kind: str  # "parked_car" | "sign" | "tree" | "bin"
    x: float
    y: float
    yaw: float = 0.0
    length: float = 0.0  # m, footprint on the ground (0 for posts and trunks)
    width: float = 0.0
    rows: list = field(default_factory=list)


class Solids:
    """Collects object parameters per material; meshes are made in bulk at the end."""

    def __init__(self):
        self.boxes = defaultdict(list)  # material → (cx, cy, yaw, length, width, z0, z1, refl)
        self.prisms = defaultdict(list)  # gable roofs: (cx, cy, yaw, length, width, z0, rise, refl)
        self.cylinders = defaultdict(list)  # (cx, cy, r, z0, z1, refl)
        self.blobs = defaultdict(list)  # (cx, cy, cz, rx, ry, rz, yaw, n, leaf, shape, refl)
        self.decals = defaultdict(list)  # flat quads on the ground: (cx, cy, yaw, length, width, refl)
        self.counts = defaultdict(int)
        self.items: list[Item] = []  # the objects that can change between drives

    def add(self, store: str, material: str, row: tuple) -> tuple[str, str, int]:
        """Append ``row`` to ``store`` (boxes, cylinders, blobs …) under ``material``; returns its key."""
        rows = getattr(self, store)[material]
        rows.append(row)
        return (store, material, len(rows) - 1)

    def row(self, key: tuple[str, str, int]) -> tuple:
        store, material, index = key
        return getattr(self, store)[material][index]

"""Triangles for the ray caster: the ground (road level, raised sidewalks and lots, curbs) and the
objects collected in :class:`~.objects.Solids`, as one :class:`~..lidar_sim.MeshPart` per material."""

from __future__ import annotations

from collections import defaultdict

import numpy as np

from ..lidar_sim import MeshPart
from .constants import BLOCK_CELLS, CELL, CURB, NODE_CELLS
from .layout import Plan
from .raster import HeightField, Raster
from .solids import Solids

_BOX_FACES = np.array(
    [  # bottom 0-3, top 4-7; no bottom face (it sits on or in the ground)
        [4, 5, 6],
        [4, 6, 7],
        [0, 1, 5],
        [0, 5, 4],
        [1, 2, 6],
        [1, 6, 5],
        [2, 3, 7],
        [2, 7, 6],
        [3, 0, 4],
        [3, 4, 7],
    ]
)


def _rect_corners(cx, cy, yaw, L, W):
    """Corners (R, 4) x and y of rectangles centred at (cx, cy), L long along ``yaw`` and W wide,
    counter-clockwise from the one at (−L/2, −W/2) in their own frame."""
    u = np.array([-0.5, 0.5, 0.5, -0.5])[None] * L[:, None]
    v = np.array([-0.5, -0.5, 0.5, 0.5])[None] * W[:, None]
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    return cx[:, None] + u * c - v * s, cy[:, None] + u * s + v * c


def _boxes_mesh(rows):
    a = np.asarray(rows, float).reshape(-1, 8)
    cx, cy, yaw, L, W, z0, z1, refl = a.T
    x, y = _rect_corners(cx, cy, yaw, L, W)
    V = np.empty((len(a), 8, 3))
    V[:, :4, 0] = V[:, 4:, 0] = x
    V[:, :4, 1] = V[:, 4:, 1] = y
    V[:, :4, 2] = z0[:, None]
    V[:, 4:, 2] = z1[:, None]
    T = _BOX_FACES[None] + 8 * np.arange(len(a))[:, None, None]
    return V.reshape(-1, 3), T.reshape(-1, 3), np.repeat(refl, len(_BOX_FACES))


def boxes_part(name: str, rows) -> MeshPart:
    """One mesh part of upright boxes, rows (cx, cy, yaw, length, width, z0, z1, reflectivity)."""
    return MeshPart(name, *_boxes_mesh(rows))


def _prisms_mesh(rows):
    a = np.asarray(rows, float).reshape(-1, 8)
    cx, cy, yaw, L, W, z0, rise, refl = a.T
    u = np.array([-0.5, 0.5, 0.5, -0.5, -0.5, 0.5])[None] * L[:, None]
    v = np.array([-0.5, -0.5, 0.5, 0.5, 0.0, 0.0])[None] * W[:, None]
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    V = np.empty((len(a), 6, 3))
    V[..., 0] = cx[:, None] + u * c - v * s
    V[..., 1] = cy[:, None] + u * s + v * c
    V[..., 2] = z0[:, None] + np.array([0, 0, 0, 0, 1, 1])[None] * rise[:, None]
    faces = np.array([[0, 1, 5], [0, 5, 4], [2, 3, 4], [2, 4, 5], [0, 4, 3], [1, 2, 5]])
    T = faces[None] + 6 * np.arange(len(a))[:, None, None]
    return V.reshape(-1, 3), T.reshape(-1, 3), np.repeat(refl, len(faces))


_CYLINDER_SIDES = 8


def _cylinders_mesh(rows, sides=_CYLINDER_SIDES):
    a = np.asarray(rows, float).reshape(-1, 6)
    cx, cy, r, z0, z1, refl = a.T
    ang = np.arange(sides) * 2 * np.pi / sides
    V = np.empty((len(a), 2 * sides, 3))
    V[:, :, 0] = cx[:, None] + r[:, None] * np.tile(np.cos(ang), 2)[None]
    V[:, :, 1] = cy[:, None] + r[:, None] * np.tile(np.sin(ang), 2)[None]
    V[:, :sides, 2] = z0[:, None]
    V[:, sides:, 2] = z1[:, None]
    k = np.arange(sides)
    k1 = (k + 1) % sides
    faces = np.concatenate(
        [
            np.stack([k, k1, k1 + sides], 1),
            np.stack([k, k1 + sides, k + sides], 1),
            np.stack([np.full(sides - 2, sides), np.arange(1, sides - 1) + sides, np.arange(2, sides) + sides], 1),
        ]
    )
    T = faces[None] + 2 * sides * np.arange(len(a))[:, None, None]
    return V.reshape(-1, 3), T.reshape(-1, 3), np.repeat(refl, len(faces))


def _blobs_mesh(rows, rng):
    """Clouds of small randomly oriented triangles filling an ellipsoid (shape 0, denser towards
    its surface like foliage), a cone (1, conifers) or a box (2, hedges)."""
    a = np.asarray(rows, float).reshape(-1, 11)
    n = a[:, 7].astype(np.int64)
    rep = np.repeat(np.arange(len(a)), n)
    cx, cy, cz, rx, ry, rz, yaw, _, leaf, shape, refl = (col[rep] for col in a.T)
    m = len(rep)
    dirs = rng.standard_normal((m, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    radial = rng.random(m) ** 0.25
    ell = dirs * radial[:, None]
    f = rng.random(m)  # cone: fraction of the height; radius shrinks linearly to the tip
    disc = np.sqrt(rng.random(m))
    phi = rng.random(m) * 2 * np.pi
    cone = np.stack([(1 - f) * disc * np.cos(phi), (1 - f) * disc * np.sin(phi), f], axis=1)
    box = rng.uniform(-1.0, 1.0, (m, 3))
    local = np.where((shape == 0)[:, None], ell, np.where((shape == 1)[:, None], cone, box))
    local *= np.stack([rx, ry, rz], axis=1)
    c, s = np.cos(yaw), np.sin(yaw)
    centre = np.stack(
        [cx + local[:, 0] * c - local[:, 1] * s, cy + local[:, 0] * s + local[:, 1] * c, cz + local[:, 2]], 1
    )
    V = centre[:, None, :] + rng.standard_normal((m, 3, 3)) * (0.6 * leaf)[:, None, None]
    T = np.arange(3 * m).reshape(-1, 3)
    return V.reshape(-1, 3), T, refl * rng.uniform(0.8, 1.2, m)


def _decals_mesh(rows, ground: HeightField):
    a = np.asarray(rows, float).reshape(-1, 6)
    cx, cy, yaw, L, W, refl = a.T
    x, y = _rect_corners(cx, cy, yaw, L, W)
    V = np.stack([x, y, ground(x, y) + 0.01], axis=-1)
    T = np.array([[0, 1, 2], [0, 2, 3]])[None] + 4 * np.arange(len(a))[:, None, None]
    return V.reshape(-1, 3), T.reshape(-1, 3), np.repeat(refl, 2)


def _quads(corner_index_grid_shape, i0, j0, di, dj):
    """Two triangles per quad of a vertex grid (row-major (nx+1, ny+1) indices), quads with lower
    corners (i0, j0) and extents (di, dj) in grid steps."""
    ny1 = corner_index_grid_shape[1]
    a = i0 * ny1 + j0
    b = (i0 + di) * ny1 + j0
    c = (i0 + di) * ny1 + j0 + dj
    d = i0 * ny1 + j0 + dj
    return np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])


def _compact(vertices: np.ndarray, triangles: np.ndarray):
    """Drop the vertices no triangle uses (the ground is cut from full vertex grids)."""
    used, remap = np.unique(triangles, return_inverse=True)
    return vertices[used], remap.reshape(triangles.shape)


def ground_parts(plan: Plan, rng, window: tuple[int, int, int, int] | None = None) -> list[MeshPart]:
    """Road-level ground (2 m quads wherever there is road), the raised level of sidewalks and
    lots (4 m quads where a block is all raised, 0.5 m quads along curbs) and vertical curbs.

    ``window`` (i0, i1, j0, j1): only the cells [i0, i1) × [j0, j1) of the raster (multiples of
    BLOCK_CELLS), with the curbs between the window and its +x and +y neighbours, so that
    windows side by side make the whole ground once (a city's ground is made window by
    window: its full vertex grids would not fit in memory). None: the whole raster."""
    full_raster, ground = plan.raster, plan.ground
    i0, i1, j0, j1 = window if window is not None else (0, full_raster.nx, 0, full_raster.ny)
    raster = Raster(full_raster.x0 + i0 * CELL, full_raster.y0 + j0 * CELL, i1 - i0, j1 - j0)
    road = plan.road[i0:i1, j0:j1]
    nx, ny = raster.shape
    raised = ~road
    parts = []

    # Road level on the height-field nodes.
    X, Y = HeightField.node_coordinates(raster)
    nb = NODE_CELLS
    z = ground.z[i0 // nb : i1 // nb + 1, j0 // nb : j1 // nb + 1]
    node_vertices = np.stack([X.ravel(), Y.ravel(), z.ravel()], axis=1)
    any_road = road.reshape(nx // nb, nb, ny // nb, nb).any(axis=(1, 3))
    qi, qj = np.nonzero(any_road)
    tris = _quads(X.shape, qi, qj, 1, 1)
    parts.append(MeshPart("road", *_compact(node_vertices, tris), rng.uniform(0.12, 0.2, len(tris)).astype(np.float32)))

    # Raised level on the cell-corner grid.
    xc = raster.x0 + np.arange(nx + 1) * CELL
    yc = raster.y0 + np.arange(ny + 1) * CELL
    XC, YC = np.meshgrid(xc, yc, indexing="ij")
    ZC = ground(XC, YC) + CURB
    corner_vertices = np.stack([XC.ravel(), YC.ravel(), ZC.ravel()], axis=1)
    bb = BLOCK_CELLS
    full = raised.reshape(nx // bb, bb, ny // bb, bb).all(axis=(1, 3))
    fi, fj = np.nonzero(full)
    in_full = np.repeat(np.repeat(full, bb, axis=0), bb, axis=1)
    ci, cj = np.nonzero(raised & ~in_full)
    tris = np.concatenate([_quads(XC.shape, fi * bb, fj * bb, bb, bb), _quads(XC.shape, ci, cj, 1, 1)])
    # Sidewalk near the road, grass and soil behind: material by the quad's first cell.
    first_i = np.concatenate([fi * bb, fi * bb, ci, ci])  # _quads gives all first halves, then all second
    first_j = np.concatenate([fj * bb, fj * bb, cj, cj])
    near = plan.dist_road[i0 + first_i, j0 + first_j] <= 3.0
    refl = np.where(near, rng.uniform(0.25, 0.32, len(tris)), rng.uniform(0.3, 0.5, len(tris))).astype(np.float32)
    parts.append(MeshPart("sidewalk_lot", *_compact(corner_vertices, tris), refl))

    # Curbs: a vertical quad on every cell edge between road and raised ground (and on the edges
    # between this window and the next one along +x and +y).
    quads = []
    raised_x = ~plan.road[i0 : min(i1 + 1, full_raster.nx), j0:j1]
    ex_i, ex_j = np.nonzero(raised_x[1:, :] != raised_x[:-1, :])  # edge x = xc[i+1], y from yc[j] to yc[j+1]
    quads.append(np.stack([np.stack([xc[ex_i + 1], yc[ex_j]], 1), np.stack([xc[ex_i + 1], yc[ex_j + 1]], 1)], 1))
    raised_y = ~plan.road[i0:i1, j0 : min(j1 + 1, full_raster.ny)]
    ey_i, ey_j = np.nonzero(raised_y[:, 1:] != raised_y[:, :-1])
    quads.append(np.stack([np.stack([xc[ey_i], yc[ey_j + 1]], 1), np.stack([xc[ey_i + 1], yc[ey_j + 1]], 1)], 1))
    ends = np.concatenate(quads)  # (Q, 2 ends, 2)
    top = ground(ends[..., 0], ends[..., 1]) + CURB
    V = np.empty((len(ends), 4, 3))
    V[:, 0, :2], V[:, 1, :2], V[:, 2, :2], V[:, 3, :2] = ends[:, 0], ends[:, 1], ends[:, 1], ends[:, 0]
    V[:, 0, 2], V[:, 1, 2] = top[:, 0] - CURB - 0.02, top[:, 1] - CURB - 0.02
    V[:, 2, 2], V[:, 3, 2] = top[:, 1], top[:, 0]
    T = np.array([[0, 1, 2], [0, 2, 3]])[None] + 4 * np.arange(len(ends))[:, None, None]
    parts.append(MeshPart("curb", V.reshape(-1, 3), T.reshape(-1, 3), 0.35))
    return parts


# Intensity of each object material is set per object above; these only name the mesh parts.
_PART_ORDER = (
    "building",
    "roof",
    "wall",
    "fence",
    "hedge",
    "trunk",
    "crown",
    "bush",
    "pole",
    "sign",
    "car",
    "glass",
    "wheel",
    "marking",
)


def object_parts(solids: Solids, ground: HeightField, rng, chunk_rows: int | None = None) -> list[MeshPart]:
    """One part per material. ``chunk_rows``: mesh at most this many rows of a store at a time
    (a city's millions of foliage triangles would need GBs of temporaries at once); None: each
    store in one go, as a town does."""
    meshes = defaultdict(list)

    def chunks(rows):
        step = chunk_rows or max(len(rows), 1)
        for k in range(0, max(len(rows), 1), step):
            yield rows[k : k + step]

    def add(name, mesh):
        V, T, R = mesh
        meshes[name].append((V.astype(np.float32) if chunk_rows else V, T, R))

    for name, rows in solids.boxes.items():
        for part in chunks(rows):
            add(name, _boxes_mesh(part))
    for name, rows in solids.prisms.items():
        for part in chunks(rows):
            add(name, _prisms_mesh(part))
    for name, rows in solids.cylinders.items():
        for part in chunks(rows):
            add(name, _cylinders_mesh(part))
    for name, rows in solids.blobs.items():
        for part in chunks(rows):
            add(name, _blobs_mesh(part, rng))
    for name, rows in solids.decals.items():
        for part in chunks(rows):
            add(name, _decals_mesh(part, ground))
    parts = []
    for name in _PART_ORDER + tuple(sorted(set(meshes) - set(_PART_ORDER))):
        if name not in meshes:
            continue
        vs, ts, rs, offset = [], [], [], 0
        for V, T, R in meshes[name]:
            vs.append(V)
            ts.append(T + offset)
            rs.append(R)
            offset += len(V)
        parts.append(MeshPart(name, np.concatenate(vs), np.concatenate(ts), np.concatenate(rs).astype(np.float32)))
    return parts


_STORES = ("boxes", "prisms", "cylinders", "blobs", "decals")  # the order object_parts meshes them in
_TRIANGLES_PER_ROW = {"boxes": len(_BOX_FACES), "prisms": 6, "cylinders": 3 * _CYLINDER_SIDES - 2, "decals": 2}


def row_triangles(solids: Solids) -> dict[tuple[str, str], np.ndarray]:
    """Where each object row's triangles are in the part :func:`object_parts` makes for its
    material: (store, material) → (rows + 1,) triangle offsets, row k's triangles being
    ``offsets[k]:offsets[k + 1]`` of part ``material`` (blobs have ``n`` triangles per row)."""
    out = {}
    names = set()
    for store in _STORES:
        names |= set(getattr(solids, store))
    for name in names:
        start = 0
        for store in _STORES:
            rows = getattr(solids, store).get(name)
            if not rows:
                continue
            if store == "blobs":
                counts = np.asarray(rows, float).reshape(-1, 11)[:, 7].astype(np.int64)
            else:
                counts = np.full(len(rows), _TRIANGLES_PER_ROW[store], np.int64)
            out[(store, name)] = start + np.concatenate([[0], np.cumsum(counts)])
            start = int(out[(store, name)][-1])
    return out

"""What a map file holds, in a few numbers (``lidarloc map info``): points, extent, origin and the
point spacing, which says whether the voxel and lookup resolution suit it."""

from __future__ import annotations

import numpy as np

#: Formats read by :func:`read_map` and written by :func:`write_map`.
from .mapfile import CHUNK_POINTS, MapCloud


def point_spacing(
    points: np.ndarray, rng: np.random.Generator | None = None, tiles: int = 8, half: float = 2.0
) -> float | None:
    """Median nearest-neighbour spacing (m) of a cloud, measured on a sample: every point within
    ``half`` m (∞-norm) of ``tiles`` random points is gathered and the nearest neighbours of
    those in the inner half of each tile are looked up among them (a k-d tree over a large
    map's every point would cost more memory than the map). None when the sample has no pairs."""
    from scipy.spatial import cKDTree

    rng = rng or np.random.default_rng(0)
    if len(points) < 2:
        return None
    centres = points[rng.integers(0, len(points), tiles)].astype(np.float64)
    masks = []
    for i in range(0, len(points), CHUNK_POINTS):
        chunk = points[i : i + CHUNK_POINTS]
        near = np.zeros(len(chunk), bool)
        for c in centres:
            near |= (np.abs(chunk - c) <= half).all(axis=1)
        masks.append(np.flatnonzero(near) + i)
    local = points[np.concatenate(masks)].astype(np.float64)
    inner = np.zeros(len(local), bool)
    for c in centres:
        inner |= (np.abs(local - c) <= half / 2).all(axis=1)
    if inner.sum() == 0 or len(local) < 2:
        return None
    d, _ = cKDTree(local).query(local[inner], k=2)
    d = d[:, 1][np.isfinite(d[:, 1])]
    return float(np.median(d)) if len(d) else None


def describe_map(cloud: MapCloud, rng: np.random.Generator | None = None) -> dict:
    """What ``lidarloc map info`` reports: points, extent and origin in the file's frame,
    density over the x-y bounding box and the median nearest-neighbour spacing (on a sample, see
    :func:`point_spacing`)."""
    lo, hi = cloud.world_bounds()
    area = float((hi[0] - lo[0]) * (hi[1] - lo[1]))
    spacing = point_spacing(cloud.points, rng)
    return {
        "file": str(cloud.path),
        "points": int(len(cloud.points)),
        "points_in_file": int(cloud.n_read),
        "dropped_nonfinite": int(cloud.n_dropped_nonfinite),
        "extent_min_m": [float(v) for v in lo],
        "extent_max_m": [float(v) for v in hi],
        "size_m": [float(v) for v in hi - lo],
        "origin_m": [float(v) for v in cloud.origin],
        "points_per_m2": float(len(cloud.points) / area) if area > 0 else None,
        "median_spacing_m": spacing,
    }


def map_info_lines(info: dict) -> list[str]:
    """:func:`describe_map`'s result for reading, coordinates in full (UTM-sized ones too)."""
    dropped = info["dropped_nonfinite"]
    lines = [f"{info['file']}: {info['points']:,} points" + (f" ({dropped:,} not finite, dropped)" if dropped else "")]
    for axis, lo, hi, size in zip("xyz", info["extent_min_m"], info["extent_max_m"], info["size_m"]):
        lines.append(f"  {axis}: {lo:.3f} … {hi:.3f} m ({size:.3f} m)")
    lines.append(
        "  origin: " + ", ".join(f"{v:.3f}" for v in info["origin_m"]) + " m (the local frame's, in the file's)"
    )
    density = "—" if info["points_per_m2"] is None else f"{info['points_per_m2']:.1f} points/m² over the x-y box"
    spacing = "—" if info["median_spacing_m"] is None else f"{info['median_spacing_m']:.3f} m"
    lines.append(f"  density: {density}; median nearest-neighbour spacing {spacing}")
    return lines

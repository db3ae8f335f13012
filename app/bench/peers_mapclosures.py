"""MapClosures (``pip install map-closures``, in the ``[peers]`` extra) as a global-localization peer
of ``lidarloc bench peers``.

MapClosures detects loop closures between local maps: each is turned into a bird's-eye-view
density image (points per cell, after aligning the map to its ground), ORB features of the image go
into one binary search tree (HBST) over every map added, and a query's features vote for earlier
maps, each candidate checked by a 2D RANSAC on its matches; the pose it gives is 3D. For global
localization the prior map is cut into square tiles, each added as a "local map" of its own, and
the query is matched against them: the pose of the query in the map is the tile's frame composed
with the closure's pose (``pose`` maps the tile's coordinates to the query's).

The query is a local map of the last ``LOCAL_SCANS`` scans up to the scan localized, stitched with
the drive's KISS-ICP odometry (the poses the localizer's own RPE gives, cached beside the map) into
the frame of that scan, in MapClosures' own voxel map (0.5 m, up to 100 m), as its own pipeline
builds its local maps; the single scan alone is measured beside it. Its stitching time is reported
apart (``mapclosures_stitch_ms_median``; reading the scans from disk is not in it).

Settings, tried on the real KITTI drive (the bench's 30 random scans, 10-scan queries, 2 shared
cores, load 10–15, 2026-12-07; within 2 m / 5°; the bench's own run of the chosen setting: 27 / 30):

- tiles of 100 m side by side, MapClosures' defaults (density threshold 0.05, Hamming distance
  50): 8 / 30; the query cropped to the tile's ±50 m: worse (4 / 30 with 50 m tiles overlapping);
- 100 m tiles every 50 m (each place in up to four tiles, so that some tile holds most of what the
  query sees): 14 / 30; every 25 m: 16 / 30 (65 tiles, twice the time);
- the density image at 1 m instead of 0.5 m: 5 / 30;
- Hamming distance 70 (ORB descriptors of a map and of a drive's local map differ more than two
  local maps' do): 25 / 30; 80: 26 / 30; density threshold 0.01 (fainter cells kept): 21 / 30;
  both 70 and 0.01: **28 / 30** with tiles every 50 m (22 / 30 with tiles side by side): the
  bench's setting;
- the tiles' points as the map has them rather than through MapClosures' voxel map: 6 / 30
  against 8 (side by side, defaults); the voxels' means and normals for the ground alignment:
  no change (8 / 30).

MapClosures is not deterministic: the same query of two databases built alike gave 7 and 8 inliers
and poses 0.10 m apart (one scan of three, three times each); its API takes no seed. The bench
asks the first query of a twin database and reports whether the answers agreed.

MapClosures only compares a query with maps added at least four ids before it (a loop closure with
the local map just before is no loop), so the queries' ids start ``ID_GAP`` after the last tile's.
It adds every query to its database too (its API has no query-only call): only the closures with
tiles are read (closures with earlier queries are ignored), and the 10-scan and the single-scan
queries go to two databases so that neither meets the other's.
"""

from __future__ import annotations

import numpy as np

from ...core.geometry import inv_pose

TILE_M = 100.0  # side of a map tile (a "local map" of MapClosures' database)
TILE_STRIDE_M = 50.0  # tiles start every this many metres along x and y (100 m tiles overlap by half)
MIN_TILE_POINTS = 1000  # a tile with fewer map points is left out (an empty corner of the map)
LOCAL_SCANS = 10  # scans stitched into a query's local map, the localized scan the last
VOXEL_MAX_RANGE_M = 100.0  # MapClosures' voxel map keeps points within this of the query's scan
# MapClosures' configuration (its defaults: 0.5, 0.05, 50, 5; why these: the module docstring)
CONFIG = {
    "density_map_resolution": 0.5,
    "density_threshold": 0.01,
    "hamming_distance_threshold": 70,
    "inliers_threshold": 5,
}
ID_GAP = 10  # the first query's id after the last tile's (MapClosures skips maps < 4 ids before)
MODULE, PIP_NAME = "map_closures", "map-closures"


def settings() -> dict:
    """The settings the bench runs MapClosures with, as the JSON reports them."""
    return {
        "tile_m": TILE_M,
        "tile_stride_m": TILE_STRIDE_M,
        "local_scans": LOCAL_SCANS,
        "local_map_poses": "the drive's KISS-ICP odometry",
        **CONFIG,
    }


def tile_origins(points: np.ndarray, tile: float = TILE_M, stride: float = TILE_STRIDE_M) -> list[tuple[float, float]]:
    """The lower corners (x, y) of the tiles that cover the map's points."""
    lo, hi = points[:, :2].min(axis=0), points[:, :2].max(axis=0)
    # the last start at most one stride before the far edge, so the map's edge is inside a tile
    xs = np.arange(lo[0], max(hi[0] - tile + stride, lo[0] + stride), stride)
    ys = np.arange(lo[1], max(hi[1] - tile + stride, lo[1] + stride), stride)
    return [(float(x), float(y)) for x in xs for y in ys]


class MapClosuresDatabase:
    """The prior map's tiles in one MapClosures database, queried by local maps."""

    def __init__(self, map_points: np.ndarray):
        # the optional [peers] extra: absent where it is not installed
        from map_closures.config import MapClosuresConfig  # pyright: ignore[reportMissingImports]
        from map_closures.map_closures import MapClosures  # pyright: ignore[reportMissingImports]
        from map_closures.voxel_map import VoxelMap  # pyright: ignore[reportMissingImports]

        self._voxel_map = VoxelMap
        self._closures = MapClosures(MapClosuresConfig(**CONFIG))
        P = np.asarray(map_points)[:, :3]
        self.tiles: list[np.ndarray] = []  # T_map←tile of each tile id
        for x, y in tile_origins(P):
            inside = (P[:, 0] >= x) & (P[:, 0] < x + TILE_M) & (P[:, 1] >= y) & (P[:, 1] < y + TILE_M)
            if inside.sum() < MIN_TILE_POINTS:
                continue
            # the tile in a frame at its centre, at the map's height: MapClosures aligns each map to
            # its own ground, and a frame far from the points would only cost float precision
            T = np.eye(4)
            T[:2, 3] = (x + TILE_M / 2.0, y + TILE_M / 2.0)
            voxels = VoxelMap(CONFIG["density_map_resolution"], float(np.hypot(TILE_M, TILE_M)))
            voxels.add_points(P[inside].astype(np.float64) - T[:3, 3])
            self._closures.get_closures(len(self.tiles), voxels.point_cloud())  # closures among tiles: none wanted
            self.tiles.append(T)
        self._next_id = len(self.tiles) + ID_GAP

    def local_map(self, scans: list[np.ndarray], poses: list[np.ndarray]) -> np.ndarray:
        """The scans (each with T_query←scan) in MapClosures' voxel map, as one cloud in the query's frame."""
        voxels = self._voxel_map(CONFIG["density_map_resolution"], VOXEL_MAX_RANGE_M)
        for points, T in zip(scans, poses):
            voxels.integrate_frame(np.asarray(points[:, :3], dtype=np.float64), np.asarray(T, dtype=np.float64))
        return voxels.point_cloud()

    def query(self, cloud: np.ndarray) -> tuple[np.ndarray | None, int]:
        """The query's pose in the map (T_map←query) from the tile closure with the most inliers,
        and their count (None, 0: no tile closed)."""
        qid = self._next_id
        self._next_id += 1
        closures = self._closures.get_closures(qid, np.asarray(cloud, dtype=np.float64))
        found = [c for c in closures if c.source_id < len(self.tiles)]  # not earlier queries
        if not found:
            return None, 0
        best = max(found, key=lambda c: c.number_of_inliers)
        T_query_tile = np.asarray(best.pose, dtype=np.float64)
        return self.tiles[best.source_id] @ inv_pose(T_query_tile), int(best.number_of_inliers)


def local_poses(odometry: np.ndarray, k: int, scans: int = LOCAL_SCANS) -> dict[int, np.ndarray]:
    """T_k←i of the scans i stitched into scan k's local map (fewer at the start of the drive),
    from the odometry poses (N, 4, 4) of every scan."""
    inv_k = inv_pose(odometry[k])
    return {i: inv_k @ odometry[i] for i in range(max(0, k - scans + 1), k + 1)}

"""KISS-Matcher (``pip install kiss-matcher``, in the ``[peers]`` extra) as a global-localization peer
of ``lidarloc bench peers``: one scan registered against the whole prior map, no initial guess.

KISS-Matcher voxelizes both clouds, extracts its FasterPFH features, matches them, prunes the
matches with ROBIN's graph and solves with GNC-TLS. Its Python API takes two clouds and does all
of it per call (``KISSMatcher.estimate``): there is no way to hand it the map's features computed
once, so every call extracts the map's features again, and that is inside its time here, as a user
calling it would pay it.

Settings: 1 m voxels (normals from 3 m, FasterPFH from 5 m: its own gains, 3× and 5× the voxel),
the scan range-filtered as every peer's, the map as it is (KISS-Matcher voxelizes it itself).
Tried on five random scans of the real KITTI drive (2 shared cores, load ~10, 2026-12-07): 1 m
voxels with its 6-DoF solver, 0 / 5 within 2 m / 5°, ~3 s a scan (the poses 10–88 m off, four of
five flagged invalid); with Quatro (``use_quatro``, its 4-DoF solver for ground vehicles) 0 / 5,
the yaw nearer (2–18° off) but the position 19–84 m off; the map down-sampled to 1 m centroids
before the call, 0 / 5 at the same time. The bench keeps the 6-DoF default; on the bench's 30
scans it put 5 within 2 m / 5° (BENCHMARKS.md, "Beside its peers"). Finer voxels were not tried:
at 0.5 m the map has about four times the features, extracted again on every call.

Determinism: KISS-Matcher's pruning and solver run on several threads, and the same scan
registered twice need not give the same pose; its API has no seed. The bench registers its first
scan twice before timing and reports whether the two poses agreed (``kiss_matcher_repeatable``).
"""

from __future__ import annotations

import numpy as np

VOXEL_M = 1.0  # the voxel both clouds are sampled at (its normal and FPFH radii scale with it)
USE_QUATRO = False  # KISS-Matcher's 6-DoF solver (Quatro, 4-DoF, did no better: module docstring)
MODULE, PIP_NAME = "kiss_matcher", "kiss-matcher"


def settings() -> dict:
    """The settings the bench runs KISS-Matcher with, as the JSON reports them."""
    return {"voxel_m": VOXEL_M, "use_quatro": USE_QUATRO, "query": "one scan", "target": "the whole map"}


class KissMatcherPeer:
    """KISS-Matcher registering scans against one map."""

    def __init__(self, map_points: np.ndarray):
        import kiss_matcher  # pyright: ignore[reportMissingImports]  (the optional [peers] extra)

        self._km = kiss_matcher
        # float32 rows: the layout its binding takes (a sequence of 3-vectors of float)
        self._map = np.ascontiguousarray(np.asarray(map_points)[:, :3], dtype=np.float32)

    def register(self, scan: np.ndarray) -> tuple[np.ndarray, bool]:
        """The scan's pose in the map (T_map←scan) and whether KISS-Matcher called its solution valid."""
        km = self._km
        # a fresh matcher a call: its state (clouds, correspondences) is per registration
        matcher = km.KISSMatcher(km.KISSMatcherConfig(VOXEL_M, use_quatro=USE_QUATRO))
        res = matcher.estimate(np.ascontiguousarray(scan[:, :3], dtype=np.float32), self._map)
        T = np.eye(4)
        T[:3, :3] = np.asarray(res.rotation, dtype=np.float64)
        T[:3, 3] = np.asarray(res.translation, dtype=np.float64).ravel()
        return T, bool(res.valid)

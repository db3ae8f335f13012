"""``lidarloc bench surface``: the cost of the viewer's likelihood surface (target: an 81 × 81 grid
at one yaw ≤ 150 ms on the real drive's scan) and where its maximum lands.

For ``scans`` scans spread over the sequence (by default the real KITTI raw drive), each prepared
as the localizer prepares it (one random point per ``pf.scan_voxel`` voxel, the run's seed), the
surface (:meth:`~lidarloc.core.filter.surface.LikelihoodModel.surface`, the filter's kernel with the
configuration's d_max, σ, temperature and unexplained share) is computed ``repeats`` times around
the true pose moved by a random offset of up to ±5 m and ±3° (a filter a few metres off), at one
yaw and best over the yaw window. What is measured (the keys of the dict :func:`run` returns):

- ``ms_median`` / ``ms_max``: one 81 × 81 surface at one yaw; ``target_ms``, ``met``;
- ``ms_median_over_yaw``: best over ±10° in 2° steps (11 yaws);
- ``argmax_error_m_median`` / ``_max``: the one-yaw surface's maximum to the truth (the offset
  centre's yaw is off too, so this is what a user sees a few metres and degrees off);
- ``points_median``: prepared scan points; ``threads``: numba's thread count.

Numba compilation is excluded (one warm-up surface first); the machine may be shared, so the
load average before and after is recorded.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ...core.config import Config
from ...core.filter.scanprep import prepare_scan
from ...core.filter.surface import CELL, HALF_WIDTH, YAW_STEP, YAW_WINDOW, LikelihoodModel
from ...core.geometry import pose_to_xyz_ypr
from ...core.maps.world import open_world
from ...core.sequences.factory import SourceSpec
from .common import load_avg, machine, open_source

TARGET_MS = 150.0
OFFSET_M = 5.0
OFFSET_YAW = 3.0 * math.pi / 180.0


def run(spec: SourceSpec, cfg: Config, scans: int = 10, repeats: int = 3, cache_root: Path | None = None) -> dict:
    import numba

    seq = open_source(spec, cfg, "surface", need_poses=True)
    load_before = load_avg()
    world = open_world(seq.map_source, cfg, cache_root, pyramid=False)
    _prior, lookup = world.prior_map, world.lookup
    model = LikelihoodModel(
        lookup, lookup.capped(cfg.pf.d_max), cfg.pf.sigma, cfg.pf.temperature, cfg.pf.unexplained_share
    )
    picks = np.unique(np.linspace(0, len(seq) - 1, max(1, min(scans, len(seq)))).round().astype(int))
    rng = np.random.default_rng(cfg.seed)
    one, over_yaw, errors, points = [], [], [], []
    warmed = False
    for k in picks:
        # prepared as the localizer prepares scan k (same voxel, same random stream)
        rng_k = np.random.default_rng([cfg.seed, int(k), 1])
        pts = prepare_scan(seq.scan(int(k)), cfg.pf, rng_k)
        truth = pose_to_xyz_ypr(seq.pose(int(k)))
        points.append(len(pts))
        if not warmed:  # numba compiles (or loads its cache) at the first call
            model.surface(pts, truth, HALF_WIDTH, CELL)
            warmed = True
        for _ in range(repeats):
            centre = truth.copy()
            centre[:2] += rng.uniform(-OFFSET_M, OFFSET_M, 2)
            centre[3] += rng.uniform(-OFFSET_YAW, OFFSET_YAW)
            s = model.surface(pts, centre, HALF_WIDTH, CELL, 0.0, YAW_STEP)
            one.append(s.ms)
            errors.append(float(np.linalg.norm(s.argmax_xy - truth[:2])))
        over_yaw.append(model.surface(pts, truth, HALF_WIDTH, CELL, YAW_WINDOW, YAW_STEP).ms)
    n = 2 * int(round(HALF_WIDTH / CELL)) + 1
    ms = float(np.median(one))
    return {
        "source": seq.name,
        "grid": f"{n}x{n}",
        "cell_m": CELL,
        "scans": int(len(picks)),
        "repeats": repeats,
        "points_median": int(np.median(points)),
        "ms_median": round(ms, 1),
        "ms_max": round(float(np.max(one)), 1),
        "target_ms": TARGET_MS,
        "met": bool(ms <= TARGET_MS),
        "ms_median_over_yaw": round(float(np.median(over_yaw)), 1),
        "yaw_window_deg": round(math.degrees(YAW_WINDOW), 1),
        "yaw_step_deg": round(math.degrees(YAW_STEP), 1),
        "argmax_error_m_median": round(float(np.median(errors)), 3),
        "argmax_error_m_max": round(float(np.max(errors)), 3),
        "threads": int(numba.get_num_threads()),
        "machine": machine(),
        "load_avg_1m_before": round(load_before, 2),
        "load_avg_1m_after": round(load_avg(), 2),
    }

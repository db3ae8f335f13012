"""``lidarloc bench s2m``: scan-to-map matching, the paper's experiment ("Scan-to-map matching",
RMSE histogram) plus the latencies the localizer depends on.

* Global M3RSM: random scans matched against the whole BEV map, d_m = 1 m, d_θ = 2.5° over
  [−π, π). RMSE (2D) between the scan's road-removed points placed by the found pose and by the
  true pose; success = RMSE ≤ 1 m. The 2D match is then refined by GICP (the paper's second
  stage) and the same RMSE is reported for the refined pose.
* Local M3RSM: from the true pose shifted up to ±10 m and turned by any yaw, search ±25 m with
  the full circle of yaws (no acceptance pruning: the worst case of the search itself), and the
  whole S2M local step (road removal, acceptance-pruned search, GICP).
* KISS-ICP odometry drift against the ground truth over the first scans.
* small_gicp vs open3d GICP (time, accuracy) and how long each library holds the GIL.

Timings are medians; the machine's load average is recorded with them (other jobs share the
cores). The source needs ground-truth poses: they are what the matches are scored against.
"""

from __future__ import annotations

import json
import math
import os
import threading
import time
from pathlib import Path

import numpy as np

from ...core.config import Config, MapConfig, S2MConfig
from ...core.geometry import inv_pose, pose_matrix, pose_to_xyz_ypr
from ...core.maps.bev import BEVPyramid
from ...core.maps.mapping import range_filter
from ...core.maps.world import open_world
from ...core.matching import m3rsm
from ...core.matching.gicp import GICPRefiner
from ...core.matching.s2m import ScanToMapMatcher
from ...core.odometry.rpe import RelativePoseEstimator
from ...core.runs.results import world_of
from ...core.sequences.factory import SourceSpec
from .common import median, open_source, pose_error

SUCCESS_RMSE = 1.0  # m, the paper's "within the matching resolution"


# ------------------------------------------------------------------------------------- helpers
def rmse_2d(points_xy: np.ndarray, a: tuple, b: tuple) -> float:
    """RMS distance between 2D points placed by pose a = (x, y, yaw) and by pose b."""

    def place(p):
        c, s = math.cos(p[2]), math.sin(p[2])
        return points_xy @ np.array([[c, s], [-s, c]]) + [p[0], p[1]]

    return float(np.sqrt(((place(a) - place(b)) ** 2).sum(axis=1).mean()))


def _xy_yaw(T: np.ndarray) -> tuple[float, float, float]:
    x, y, _, yaw, _, _ = pose_to_xyz_ypr(T)
    return float(x), float(y), float(yaw)


def gil_hold_ms(work, poll_s: float = 0.001) -> dict:
    """How long ``work()`` (run on a second thread) keeps a Python thread that sleeps ``poll_s`` in a
    loop from waking up: ~poll_s if the work releases the GIL, the length of its calls if not."""
    done = threading.Event()
    failure: list[BaseException] = []

    def run() -> None:
        try:
            work()
        except BaseException as e:  # handed to the caller: a failed work must not leave it polling
            failure.append(e)
        finally:
            done.set()

    worker = threading.Thread(target=run)
    gaps = []
    worker.start()
    t = time.perf_counter()
    while not done.is_set():
        time.sleep(poll_s)
        t2 = time.perf_counter()
        gaps.append(t2 - t)
        t = t2
    worker.join()
    if failure:
        raise failure[0]
    g = np.asarray(gaps) * 1e3
    return {"median": float(np.median(g)), "p95": float(np.percentile(g, 95)), "max": float(g.max())}


# ----------------------------------------------------------------------------------- sub-benches
def kiss_icp_drift(seq, n: int = 100) -> dict:
    """KISS-ICP over the first n scans: end-point translation error relative to the distance
    driven (%), mean per-step translation error, registration time, GIL hold."""
    n = min(n, len(seq))
    G = seq.poses
    rpe = RelativePoseEstimator(max_buffer=max(n, 2))
    scans = [seq.scan(k) for k in range(n)]
    ms = []
    hold = {}

    def register(ks):
        for k in ks:
            t0 = time.perf_counter()
            rpe.add(k, scans[k], seq.timestamp(k))
            ms.append((time.perf_counter() - t0) * 1e3)

    register(range(0, n // 2))
    hold = gil_hold_ms(lambda: register(range(n // 2, n)))
    path = float(sum(np.linalg.norm(G[i + 1][:3, 3] - G[i][:3, 3]) for i in range(n - 1)))
    est = rpe.relative(0, n - 1)
    gt = inv_pose(G[0]) @ G[n - 1]
    step_err = [
        np.linalg.norm(rpe.relative(k, k + 1)[:3, 3] - (inv_pose(G[k]) @ G[k + 1])[:3, 3]) for k in range(n - 1)
    ]
    step_len = [np.linalg.norm(G[k + 1][:3, 3] - G[k][:3, 3]) for k in range(n - 1)]
    _, rot_deg = pose_error(est, gt)
    return {
        "scans": n,
        "path_m": path,
        "drift_pct": 100.0 * float(np.linalg.norm(est[:3, 3] - gt[:3, 3])) / max(path, 1e-9),
        "end_rotation_error_deg": rot_deg,
        "step_error_pct": 100.0 * float(np.sum(step_err)) / max(float(np.sum(step_len)), 1e-9),
        "ms_median": median(ms),
        "gil_hold_ms": hold,
    }


def gicp_comparison(
    seq,
    prior,
    cfg: S2MConfig,
    map_cfg: MapConfig,
    n: int = 25,
    seed: int = 0,
    variants=(("small_gicp", None), ("small_gicp", "equal"), ("open3d", None)),
) -> dict:
    """small_gicp (prebuilt target) vs open3d (cropped target) from ground truth perturbed by the
    2D lattice error (±d_m/2 in x, y, ±d_θ/2 in yaw): time, error against the ground truth, GIL.
    A variant's second item is the map voxel: None = S2M's choice (gicp_voxel / 2, at least the
    map's voxel), "equal" = gicp_voxel (as coarse as the scan)."""
    rng = np.random.default_rng(seed)
    idx = np.linspace(0, len(seq) - 1, n).astype(int)
    out = {}
    for backend, target in variants:
        target_voxel = cfg.gicp_voxel if target == "equal" else max(float(prior.voxel_size), cfg.gicp_voxel / 2.0)
        t0 = time.perf_counter()
        ref = GICPRefiner(
            prior.points, voxel=cfg.gicp_voxel, max_corr=cfg.gicp_max_corr, backend=backend, target_voxel=target_voxel
        )
        build_s = time.perf_counter() - t0
        rows = []
        for k in idx:
            x, y, z, yaw, pitch, roll = pose_to_xyz_ypr(seq.pose(k))
            r = np.random.default_rng(rng.integers(1 << 31))
            init = pose_matrix(
                x + r.uniform(-0.5, 0.5) * cfg.match_resolution,
                y + r.uniform(-0.5, 0.5) * cfg.match_resolution,
                z,
                yaw + r.uniform(-0.5, 0.5) * cfg.angle_step,
                pitch,
                roll,
            )
            res = ref.refine(range_filter(seq.scan(k), map_cfg), init)
            rows.append((res.ms,) + pose_error(res.pose, seq.pose(k)))
        rows = np.asarray(rows)
        scan = range_filter(seq.scan(int(idx[len(idx) // 2])), map_cfg)
        init = seq.pose(int(idx[len(idx) // 2]))
        hold = gil_hold_ms(lambda: [ref.refine(scan, init) for _ in range(3)])
        out[f"{backend}/target{target_voxel:g}"] = {
            "map_build_s": build_s,
            "ms_median": float(np.median(rows[:, 0])),
            "err_m_median": float(np.median(rows[:, 1])),
            "err_m_max": float(rows[:, 1].max()),
            "err_deg_median": float(np.median(rows[:, 2])),
            "err_deg_max": float(rows[:, 2].max()),
            "gil_hold_ms": hold,
            "target_points": ref.n_target,
        }
    return out


def cell_value_study(
    seq,
    prior,
    cfg: S2MConfig,
    values=("binary", "sat4", "sat8", "sat16", "sat32", "log", "count"),
    n: int = 50,
    seed: int = 0,
) -> dict:
    """Global 2D matching with each BEV cell value: success (RMSE ≤ 1 m), median time."""
    matcher = None
    rng = np.random.default_rng(seed)
    idx = rng.choice(len(seq), min(n, len(seq)), replace=False)
    scans = []
    for k in idx:
        if matcher is None:
            matcher = ScanToMapMatcher(prior, BEVPyramid.build(prior.points_bev, cfg.match_resolution), cfg)
        scans.append((k, matcher.prepare(seq.scan(k)).road_removed[:, :2]))
    out = {}
    for value in values:
        pyr = BEVPyramid.build(prior.points_bev, cfg.match_resolution, cell_value=value)
        m3rsm.match_global(pyr, scans[0][1], cfg.angle_step)  # prepare the bound grids off the clock
        rm, ms = [], []
        for k, B in scans:
            r = m3rsm.match_global(pyr, B, cfg.angle_step)
            rm.append(rmse_2d(B, (r.x, r.y, r.yaw), _xy_yaw(seq.pose(k))))
            ms.append(r.ms)
        out[value] = {
            "success_rate": float(np.mean(np.asarray(rm) <= SUCCESS_RMSE)),
            "rmse_median_m": float(np.median(rm)),
            "ms_median": float(np.median(ms)),
        }
    return out


# ------------------------------------------------------------------------------------------ run
def run(
    spec: SourceSpec,
    config: Config,
    matches: int = 350,
    out_dir: Path | None = None,
    compare_gicp: bool = True,
    cell_study: bool = False,
    odometry_scans: int = 100,
    cache_root: Path | None = None,
) -> dict:
    """Match ``matches`` random scans of the sequence (``config.seed`` draws them and the local
    search's starts) with ``config.s2m`` against its prior map (``config.map``); ``out_dir``: write
    the result, the per-scan rows and the RMSE histogram there."""
    load_start = os.getloadavg()
    t_start = time.perf_counter()
    seed, cfg = config.seed, config.s2m
    seq = open_source(spec, config, "s2m", need_poses=True)
    world = open_world(seq.map_source, config, cache_root, lookup=False)
    prior, pyramid = world.prior_map, world.pyramid
    matcher = ScanToMapMatcher(prior, pyramid, cfg)
    rng = np.random.default_rng(seed)
    n = min(int(matches), len(seq))
    idx = rng.choice(len(seq), n, replace=False)

    # first call off the clock: numba loads its cached kernels, the bound grids are built
    warm = matcher.prepare(seq.scan(int(idx[0])))
    m3rsm.match_global(pyramid, warm.road_removed[:, :2], cfg.angle_step)

    rows = []
    for k in idx:
        k = int(k)
        truth = seq.pose(k)
        true2d = _xy_yaw(truth)
        scan = seq.scan(k)
        prep = matcher.prepare(scan)
        B = prep.road_removed[:, :2]
        g = matcher.match_global(scan, prepared=prep)
        mr = g.match
        row = {
            "scan": k,
            "prepare_ms": prep.ms,
            "global_ms": mr.ms,
            "nodes": mr.nodes_expanded,
            "points": mr.n_points,
            "rmse": rmse_2d(B, (mr.x, mr.y, mr.yaw), true2d),
            "rmse_cells": rmse_2d(m3rsm.scan_cells(B, cfg.match_resolution), (mr.x, mr.y, mr.yaw), true2d),
            "gicp_ms": g.timings.get("gicp"),
            "global_accepted": g.accepted,
            "rmse_gicp": rmse_2d(B, _xy_yaw(g.pose), true2d) if g.accepted else math.inf,
        }
        row["gicp_err_m"], row["gicp_err_deg"] = pose_error(g.pose, truth)
        # local: ±25 m, full circle, from a start up to ±10 m and any yaw away from the truth
        r = np.random.default_rng(rng.integers(1 << 31))
        x, y, z, yaw, pitch, roll = pose_to_xyz_ypr(truth)
        sx, sy, syaw = x + r.uniform(-10, 10), y + r.uniform(-10, 10), yaw + r.uniform(-math.pi, math.pi)
        loc = m3rsm.match(pyramid, B, (sx, sy), (cfg.region_x, cfg.region_y), syaw, math.pi, cfg.angle_step)
        row["local_ms"] = loc.ms
        row["local_rmse"] = rmse_2d(B, (loc.x, loc.y, loc.yaw), true2d)
        s2m = matcher.match_local(scan, pose_matrix(sx, sy, z, syaw, pitch, roll), prepared=prep)
        row["s2m_local_ms"] = s2m.ms
        row["s2m_local_accepted"] = s2m.accepted
        row["s2m_local_err_m"] = pose_error(s2m.pose, truth)[0]
        rows.append(row)

    rm = np.array([r["rmse"] for r in rows])
    rm_gicp = np.array([r["rmse_gicp"] for r in rows])
    result = {
        "source": seq.name,
        "scans": n,
        "seed": seed,
        "world": world_of(seq),
        "map_points": int(len(prior.points)),
        "map_points_bev": int(len(prior.points_bev)),
        "pyramid_shape": list(pyramid.shape),
        "pyramid_levels": pyramid.n_levels,
        "cell_value": pyramid.cell_value,
        "match_resolution_m": cfg.match_resolution,
        "angle_step_deg": math.degrees(cfg.angle_step),
        # the paper's experiment: the 2D M3RSM pose
        "success_rate": float(np.mean(rm <= SUCCESS_RMSE)),
        "rmse_median_m": float(np.median(rm)),
        "rmse_p90_m": float(np.percentile(rm, 90)),
        "rmse_max_m": float(rm.max()),
        "success_rate_cells": float(np.mean(np.array([r["rmse_cells"] for r in rows]) <= SUCCESS_RMSE)),
        "rmse_cells_median_m": median(r["rmse_cells"] for r in rows),
        # the S2M output: the 2D match refined by GICP
        "success_rate_gicp": float(np.mean(rm_gicp <= SUCCESS_RMSE)),
        "rmse_gicp_median_m": median(rm_gicp),
        "gicp_err_m_median": median(r["gicp_err_m"] for r in rows),
        "gicp_err_deg_median": median(r["gicp_err_deg"] for r in rows),
        "global_accept_rate": float(np.mean([r["global_accepted"] for r in rows])),
        "global_ms_median": median(r["global_ms"] for r in rows),
        "global_ms_p90": float(np.percentile([r["global_ms"] for r in rows], 90)),
        "global_nodes_median": median(r["nodes"] for r in rows),
        "scan_cells_median": median(r["points"] for r in rows),
        "prepare_ms_median": median(r["prepare_ms"] for r in rows),
        "gicp_ms_median": median(r["gicp_ms"] for r in rows),
        "local_ms_median": median(r["local_ms"] for r in rows),
        "local_ms_p90": float(np.percentile([r["local_ms"] for r in rows], 90)),
        "local_success_rate": float(np.mean([r["local_rmse"] <= SUCCESS_RMSE for r in rows])),
        "s2m_local_ms_median": median(r["s2m_local_ms"] for r in rows),
        "s2m_local_accept_rate": float(np.mean([r["s2m_local_accepted"] for r in rows])),
        "s2m_local_err_m_median": median(r["s2m_local_err_m"] for r in rows if r["s2m_local_accepted"]),
    }
    if seq.has_poses:
        odo = kiss_icp_drift(seq, odometry_scans)
        result["kiss_icp_drift_pct"] = odo["drift_pct"]
        result["kiss_icp"] = odo
    if compare_gicp:
        result["gicp_comparison"] = gicp_comparison(seq, prior, cfg, config.map, seed=seed)
    if cell_study:
        result["cell_value_study"] = cell_value_study(seq, prior, cfg, seed=seed)
    result["cpu_count"] = os.cpu_count()
    result["loadavg_start"] = [round(v, 2) for v in load_start]
    result["loadavg_end"] = [round(v, 2) for v in os.getloadavg()]
    result["wall_s"] = time.perf_counter() - t_start
    if out_dir is not None:
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / "bench_s2m.json").write_text(json.dumps(result, indent=2))
        (out_dir / "bench_s2m_scans.json").write_text(json.dumps(rows, indent=1, default=float))
        _histogram(rm, rm_gicp, result, out_dir / "s2m_rmse_hist.png")
    return result


def _histogram(rm: np.ndarray, rm_gicp: np.ndarray, result: dict, path: Path) -> None:
    """The paper's figure: RMSE histogram over all scans, and zoomed to [0, 2.5] m."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    finite = rm[np.isfinite(rm)]
    axes[0].hist(finite, bins=50, color="tab:blue")
    axes[0].set_title(f"{result['source']}: global M3RSM, {result['scans']} scans")
    axes[0].set_xlabel("RMSE (m)")
    axes[0].set_ylabel("scans")
    bins = np.linspace(0, 2.5, 26)
    axes[1].hist(
        np.clip(finite, 0, 2.5), bins=bins, color="tab:blue", alpha=0.7, label="2D match (d_m = 1 m, d_θ = 2.5°)"
    )
    axes[1].hist(
        np.clip(rm_gicp[np.isfinite(rm_gicp)], 0, 2.5), bins=bins, color="tab:orange", alpha=0.7, label="after GICP"
    )
    axes[1].axvline(SUCCESS_RMSE, color="k", ls="--", lw=1)
    axes[1].set_title(
        f"zoom [0, 2.5] m — success {100 * result['success_rate']:.0f}% (GICP {100 * result['success_rate_gicp']:.0f}%)"
    )
    axes[1].set_xlabel("RMSE (m)")
    axes[1].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)

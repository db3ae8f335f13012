"""``lidarloc bench pf``: the particle-filter core. Filter step times on a sequence's scans (by
default the real KITTI raw drive), and the lookup table's build time, memory and load time for a
KITTI-05-sized map. What is measured (the keys of the dict :func:`run` returns):

- ``step_ms_median``: one ParticleFilter.step (predict + likelihood + estimate + resampling when
  due) with N particles spread over the whole map, re-spread (untimed) before every timed step,
  so every step sees a fresh global spread; per init mode in ``step_ms_median_by_mode``.
- ``step_ms_median_converged``: the same N particles drawn around the true pose of the previous
  scan (σ 2 m in x, y: within 5 m of the truth), then one step on the next scan.
- ``step_ms_median_10k``: as the spread case with 10 000 particles.
- ``likelihood_ms_median``: the weight update alone (log_likelihood_floored) for the spread case;
  ``likelihood_full_ms_median``: the plain per-particle sum without the early stop, for reference.
- ``lookup_*``: a KITTI-05-sized synthetic map (480 × 430 m, ~40 m of height: hilly ground
  everywhere, building walls, tree crowns; ~8M points) at δ = 0.25 m, d_max = 5 m, built and
  loaded in fresh child processes (so ``lookup_build_peak_rss_mb`` is that build's own peak).
  The built-in town's cached or built prior map is measured too (``town_lookup_*``).
- ``kitti_*``: the source's own prior map and lookup table (cached or built).

Numba compilation is excluded (everything is warmed up first). The machine may be shared:
``load_avg_1m_before``/``_after`` record the load the numbers were taken under; all times are
medians over ``scans`` scans spread over the sequence. The builds run in spawned child processes
(multiprocessing) so that each one's peak memory is its own.
"""

from __future__ import annotations

import math
import multiprocessing as mp
import os
import shutil
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from ...core.config import Config
from ...core.sequences.factory import SourceSpec
from ..console import peak_rss_mb
from .common import child_result, end_child, load_avg, median_ms, open_source, rss_mb

DEG = math.pi / 180.0


def synthetic_kitti05_map(
    size_x: float = 480.0, size_y: float = 430.0, spacing: float = 0.2, seed: int = 0
) -> np.ndarray:
    """A point cloud the size of KITTI 05's map (≈ 480 × 430 × 40 m): hilly ground sampled over
    the whole box (a pessimistic case: a real drive's map only covers the streets), walls of
    buildings on a block grid and spherical tree crowns. About 8M float32 points."""
    rng = np.random.default_rng(seed)

    def terrain(x, y):
        return 7.0 * np.sin(x / 90.0) * np.cos(y / 70.0) + 0.02 * x

    n = int(size_x * size_y / spacing**2)
    gx, gy = rng.random(n) * size_x, rng.random(n) * size_y
    parts = [np.stack([gx, gy, terrain(gx, gy) + rng.normal(0, 0.03, n)], axis=1)]
    for bx in np.arange(10.0, size_x - 30.0, 45.0):
        for by in np.arange(10.0, size_y - 30.0, 45.0):
            if rng.random() < 0.3:
                continue
            w, d, h = rng.uniform(12, 30), rng.uniform(12, 30), rng.uniform(6, 28)
            x0, y0 = bx + rng.uniform(0, 5), by + rng.uniform(0, 5)
            z0 = terrain(x0, y0) - 1.0
            perimeter = 2 * (w + d)
            m = int(perimeter * h / spacing**2)
            s, z = rng.random(m) * perimeter, z0 + rng.random(m) * h
            x = np.where(s < w, x0 + s, np.where(s < w + d, x0 + w, np.where(s < 2 * w + d, x0 + (s - w - d), x0)))
            y = np.where(
                s < w, y0, np.where(s < w + d, y0 + (s - w), np.where(s < 2 * w + d, y0 + d, y0 + (s - 2 * w - d)))
            )
            parts.append(np.stack([x, y, z], axis=1))
    for _ in range(300):
        cx, cy = rng.random() * size_x, rng.random() * size_y
        r = rng.uniform(1.5, 3.5)
        v = rng.normal(size=(3000, 3))
        v /= np.linalg.norm(v, axis=1, keepdims=True)
        centre = np.array([cx, cy, terrain(cx, cy) + r + 3.0])
        parts.append(centre + v * r * rng.random((3000, 1)) ** 0.3)
    return np.concatenate(parts).astype(np.float32)


def _child_build(points_path: str, out_dir: str, resolution: float, d_max: float, queue) -> None:
    from ...core.maps.lookup import LookupTable

    LookupTable.build(np.random.default_rng(0).random((2000, 3)).astype(np.float32) * 10, resolution, d_max)  # JIT
    points = np.load(points_path)
    rss_before = rss_mb()
    t0 = time.perf_counter()
    table = LookupTable.build(points, resolution, d_max)
    build_s = time.perf_counter() - t0
    table.save(Path(out_dir))
    queue.put(
        {
            "build_s": build_s,
            "mb": table.nbytes / 1e6,
            "bricks": table.n_bricks,
            "cells": list(table.shape),
            "peak_rss_mb": peak_rss_mb(),
            "rss_before_build_mb": rss_before,
            "points": int(len(points)),
            "extent_m": [float(v) for v in (points.max(axis=0) - points.min(axis=0))],
            "dense_uint8_mb": float(np.prod(table.shape)) / 1e6,
        }
    )


def _child_load(out_dir: str, queue) -> None:
    from ...core.maps.lookup import LookupTable

    t0 = time.perf_counter()
    table = LookupTable.load(Path(out_dir))
    queue.put({"load_s": time.perf_counter() - t0, "mb": table.nbytes / 1e6})


def measure_lookup(points: np.ndarray, resolution: float = 0.25, d_max: float = 5.0) -> dict:
    """Build (in a child process), save, and load (in another child) a lookup table."""
    ctx = mp.get_context("spawn")
    work = Path(tempfile.mkdtemp(prefix="lidarloc-bench-lookup-"))
    try:
        np.save(work / "points.npy", points)
        results = {}
        for target, args in (
            (_child_build, (str(work / "points.npy"), str(work / "L"), resolution, d_max)),
            (_child_load, (str(work / "L"),)),
        ):
            queue = ctx.Queue()
            proc = ctx.Process(target=target, args=(*args, queue), daemon=True)
            proc.start()
            try:
                results.update(child_result(queue, proc, "pf"))
            finally:
                end_child(proc)
        return results
    finally:
        shutil.rmtree(work, ignore_errors=True)


def run(spec: SourceSpec, cfg: Config, n_scans_timed: int = 20, big_map: bool = True, town: bool = True) -> dict:
    """Step times with ``cfg.pf`` on ``n_scans_timed`` scans spread over the sequence of ``spec``
    (against its prior map from the cache), then the lookup-table builds; ``cfg.seed`` seeds the
    filters and the synthetic map."""
    from ...core.filter.likelihood import log_likelihood, log_likelihood_floored
    from ...core.filter.pf import ParticleFilter
    from ...core.filter.scanprep import prepare_scan
    from ...core.geometry import pose_to_xyz_ypr
    from ...core.maps.lookup import load_or_build_lookup
    from ...core.maps.mapping import load_or_build_map

    n_particles, seed, scans = cfg.pf.n_particles, cfg.seed, n_scans_timed
    out: dict = {
        "particles": n_particles,
        "scans": scans,
        "seed": seed,
        "cpus": os.cpu_count(),
        "load_avg_1m_before": load_avg(),
    }
    seq = open_source(spec, cfg, "pf", need_poses=True)
    out["source"] = seq.name
    prior, map_dir, _ = load_or_build_map(seq.map_source, cfg.map)
    t0 = time.perf_counter()
    lookup, _, cached = load_or_build_lookup(prior, map_dir, cfg.pf.lookup_resolution, cfg.pf.d_max)
    out.update(
        kitti_map_points=int(len(prior.points)),
        kitti_lookup_mb=lookup.nbytes / 1e6,
        kitti_lookup_cached=cached,
        kitti_lookup_s=time.perf_counter() - t0,
    )
    lo, hi = prior.bounds

    idx = np.unique(np.linspace(1, len(seq) - 1, scans).round().astype(int))
    prep_t, prepared = [], {}
    for k in idx:
        raw = seq.scan(int(k))
        t0 = time.perf_counter()
        prepared[int(k)] = prepare_scan(raw, cfg.pf, int(k))
        prep_t.append(time.perf_counter() - t0)
    out["scan_points"] = int(np.median([len(p) for p in prepared.values()]))
    out["scanprep_ms_median"] = median_ms(prep_t)

    def make(n, mode):
        return ParticleFilter(
            replace(cfg.pf, n_particles=n, init_mode=mode), lookup, lo, hi, seed=seed, map_points=prior.points
        )

    # warm-up: compile every kernel once (cache=True makes later runs load them from disk)
    warm = make(64, "uniform_box")
    first = prepared[int(idx[0])]
    warm.step(first, 0.1)
    warm.reweight(0)
    log_likelihood(warm.states, first, lookup, 5.0, 0.5)

    def spread_steps(n, mode):
        pf = make(n, mode)
        times, ll_times, ll_full = [], [], []
        for k in idx:
            scan = prepared[int(k)]
            pf.initialize()
            t0 = time.perf_counter()
            pf.step(scan, float(seq.timestamp(int(k)) - seq.timestamp(int(k) - 1)))
            times.append(time.perf_counter() - t0)
            if n == n_particles and mode == "uniform_box":
                pf.initialize()
                prior_lw = pf.log_weights.copy()
                t0 = time.perf_counter()
                log_likelihood_floored(pf.states, scan, lookup, pf.d_max, pf.sigma, prior_lw)
                ll_times.append(time.perf_counter() - t0)
                t0 = time.perf_counter()
                log_likelihood(pf.states, scan, lookup, pf.d_max, pf.sigma)
                ll_full.append(time.perf_counter() - t0)
        return times, ll_times, ll_full

    by_mode = {}
    for mode in ("uniform_box", "map_support"):
        times, ll_times, ll_full = spread_steps(n_particles, mode)
        by_mode[mode] = median_ms(times)
        if ll_times:
            out["likelihood_ms_median"] = median_ms(ll_times)
            out["likelihood_full_ms_median"] = median_ms(ll_full)
    out["init_mode"] = "uniform_box"
    out["step_ms_median"] = by_mode["uniform_box"]
    out["step_ms_median_by_mode"] = by_mode

    pf = make(n_particles, "uniform_box")
    conv, conv_err = [], []
    for k in idx:
        k = int(k)
        pf.initialize(pose=seq.pose(k - 1), pose_std=(2.0, 2.0, 0.2, 3 * DEG, 1 * DEG, 1 * DEG))
        dt = float(seq.timestamp(k) - seq.timestamp(k - 1))
        t0 = time.perf_counter()
        est = pf.step(prepared[k], dt)
        conv.append(time.perf_counter() - t0)
        conv_err.append(float(np.linalg.norm(est.state[:3] - seq.pose(k)[:3, 3])))
    out["step_ms_median_converged"] = median_ms(conv)
    out["converged_error_m_median"] = float(np.median(conv_err))

    by_mode_10k = {}
    for mode in ("uniform_box", "map_support"):
        by_mode_10k[mode] = median_ms(spread_steps(10_000, mode)[0])
    out["step_ms_median_10k"] = by_mode_10k["uniform_box"]
    out["step_ms_median_10k_by_mode"] = by_mode_10k
    out["truth_pose_check"] = pose_to_xyz_ypr(seq.pose(int(idx[0]))).round(3).tolist()
    out["peak_rss_mb"] = peak_rss_mb()
    out["load_avg_1m_after_pf"] = load_avg()

    if big_map:
        points = synthetic_kitti05_map(seed=seed)
        res = measure_lookup(points)
        del points
        out.update(
            lookup_build_s=res["build_s"],
            lookup_mb=res["mb"],
            lookup_load_s=res["load_s"],
            lookup_bricks=res["bricks"],
            lookup_cells=res["cells"],
            lookup_map_points=res["points"],
            lookup_map_extent_m=res["extent_m"],
            lookup_build_peak_rss_mb=res["peak_rss_mb"],
            lookup_rss_before_build_mb=res["rss_before_build_mb"],
            lookup_dense_uint8_mb=res["dense_uint8_mb"],
            lookup_source="synthetic KITTI-05-sized map",
        )
    if town:
        from ...core.sim.town import TownSequence

        town_map = load_or_build_map(TownSequence.from_config(cfg.town).map_source, cfg.map).value  # the default town
        res = measure_lookup(town_map.points)
        out.update(
            town_lookup_build_s=res["build_s"],
            town_lookup_mb=res["mb"],
            town_lookup_load_s=res["load_s"],
            town_lookup_build_peak_rss_mb=res["peak_rss_mb"],
            town_map_points=res["points"],
            town_map_extent_m=res["extent_m"],
        )
    out["load_avg_1m_after"] = load_avg()
    return out

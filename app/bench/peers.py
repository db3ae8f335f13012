"""``lidarloc bench peers``: lidarloc beside what a user would run instead, on the same scans, map
and machine, in one run, with the ratios.

**Global localization** (the built-in town and the real KITTI drive): a scan registered against
the whole map with no initial guess. lidarloc's S2M (M3RSM on the bird's-eye view, then GICP)
against open3d's FPFH features with RANSAC, and with Fast Global Registration (FGR) — the
feature-based alternative hdl_global_localization offers beside its branch-and-bound search.
Success: the returned pose within 2 m and 5° of the truth. Times are wall medians per scan, the
scan's own preparation included (lidarloc: road removal; the peers: down-sampling, normals,
FPFH); what is built once per map (lidarloc's pyramid, the map's FPFH) is not, and is reported
beside. Both peers get the map and the scan at 1 m voxels, normals from 2 m, FPFH from 5 m (the
settings of open3d's global registration tutorial, scaled to a street). Tried on three scans of
the real drive and no better (no scan within 2 m / 5° either): 0.5 m voxels (40–60 s a scan), the
mutual filter on and off, 10⁶ RANSAC iterations, the road-removed map and scan.

Beside them, where ``pip install 'lidarloc[peers]'`` put them (each skipped with a one-line
reason where not; :mod:`.peers_optional`): **KISS-Matcher** (scan to the whole map, 1 m voxels)
and **MapClosures** (the map in 100 m tiles every 50 m, a 10-scan local map stitched with the
drive's odometry as the query, and the scan alone beside it). Their settings, and the others tried,
are in :mod:`.peers_kiss_matcher` and :mod:`.peers_mapclosures`. The global target's "best peer" is
the best of all that ran; MapClosures' time there is its query's with the stitching of its local
map.

**Tracking** (the town): lidarloc from a global start against scan-to-map GICP (small_gicp, scan
0.5 m, map 0.25 m, 2 m correspondences: the matcher lidarloc's own S2M refines with) started at
the true pose and predicted with constant velocity at 10 Hz — the scan-matching localizer
hdl_localization is (with NDT). RMSE of the position against the truth (lidarloc: from the
scan the rule first fired on), median latency and CPU per scan (lidarloc: every process, the
KISS-ICP and S2M children included, over the scans after it localized; GICP: its thread's CPU).
Then a kidnap: the vehicle is moved ~50 m ahead along the drive without telling either. Who
recovers (error ≤ 2 m from some scan to the end of the window and stays so), and after how many
scans.

**The paper** (:mod:`.peers_paper`): its own figures beside lidarloc's on the town laid along
KITTI 05.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from ...core.config import Config
from ...core.maps.mapping import load_or_build_map, range_filter
from ...core.sequences.factory import SourceSpec
from .common import median, open_source, real_drive
from .peers_global import global_localization
from .peers_optional import PACKAGES, add_optional_peers

RECOVERED_M = 2.0  # a tracker has recovered from a kidnap once its error stays within this
KIDNAP_M = 50.0  # how far ahead along the drive the vehicle is moved


def kidnap_target(seq, at: int, metres: float = KIDNAP_M) -> int:
    """The first scan at least ``metres`` along the drive after scan ``at`` (the last scan if the
    drive ends before)."""
    G = np.asarray(seq.poses)[:, :3, 3]
    steps = np.linalg.norm(np.diff(G[at:], axis=0), axis=1)
    along = np.cumsum(steps)
    hit = np.flatnonzero(along >= metres)
    return at + 1 + int(hit[0]) if hit.size else len(G) - 1


def recovery(errors: list[float], limit: float = RECOVERED_M) -> int | None:
    """Scans from the first after a kidnap to the one from which every error to the end is within
    ``limit`` (None: not recovered by the end of the window)."""
    err = np.asarray(errors, float)
    bad = np.flatnonzero(~(err <= limit))
    if not bad.size:
        return 0
    return None if bad[-1] + 1 >= len(err) else int(bad[-1] + 1)


def gicp_tracking(seq, prior, cfg: Config, before: int, kidnap_to: int, after: int) -> dict:
    """small_gicp scan-to-map tracking from the true first pose, constant-velocity prediction;
    the scans 0…before−1, then from ``kidnap_to`` on for ``after`` scans."""
    from ...core.matching.gicp import GICPRefiner

    ref = GICPRefiner(
        prior.points,
        voxel=cfg.s2m.gicp_voxel,
        max_corr=cfg.s2m.gicp_max_corr,
        target_voxel=max(float(prior.voxel_size), cfg.s2m.gicp_voxel / 2.0),
    )
    ks = list(range(before)) + list(range(kidnap_to, min(kidnap_to + after, len(seq))))
    prev = prev2 = None
    errors, ms, cpu_ms = [], [], []
    for k in ks:
        if prev is None:
            guess = seq.pose(k)  # the true initial pose
        else:
            guess = prev if prev2 is None else prev @ np.linalg.inv(prev2) @ prev
        scan = range_filter(seq.scan(k), cfg.map)
        c0, t0 = time.thread_time(), time.perf_counter()
        res = ref.refine(scan, guess)
        ms.append((time.perf_counter() - t0) * 1e3)
        cpu_ms.append((time.thread_time() - c0) * 1e3)
        pose = res.pose if np.isfinite(res.pose).all() else guess
        prev2, prev = prev, pose
        errors.append(float(np.linalg.norm(pose[:3, 3] - seq.pose(k)[:3, 3])))
    tracked = np.asarray(errors[:before])
    rec = recovery(errors[before:])
    return {
        "rmse_m": float(np.sqrt(np.mean(tracked**2))),
        "ms_median": median(ms[:before]),
        "cpu_ms_per_scan": float(np.mean(cpu_ms[:before])),
        "recovered_after_kidnap": rec is not None,
        "recovery_scans": rec,
        "error_after_kidnap_end_m": errors[-1] if len(errors) > before else None,
    }


def lidarloc_tracking(
    seq, cfg: Config, before: int, kidnap_to: int, after: int, cache_root: Path | None, progress=None
) -> dict:
    """lidarloc from a global start over scans 0…before−1, then kidnapped to ``kidnap_to``
    (:meth:`Localizer.kidnap`: the viewer's Kidnap) for ``after`` scans."""
    from ...core.localizer import Localizer

    def cpu_total(reading: dict) -> float:
        return sum(v for v in reading.values() if v is not None)

    with Localizer(seq, cfg, cache_root) as loc:
        loc.wait_ready()  # the blocks' start-up is not per-scan cost
        cpu_at_loc = None
        blocks_at_loc: dict = {}
        first_loc = None
        while loc.k < before and not loc.done:
            snap = loc.step()
            if first_loc is None and snap.localized:
                blocks_at_loc = dict(loc.cpu_seconds())
                first_loc, cpu_at_loc = len(loc.records), cpu_total(blocks_at_loc)
            if progress is not None:
                progress(len(loc.records), before + after)
        blocks_end = dict(loc.cpu_seconds())
        cpu_end = cpu_total(blocks_end)
        n_before = len(loc.records)
        loc.kidnap(kidnap_to - loc.k)
        while len(loc.records) < n_before + after and not loc.done:
            loc.step()
            if progress is not None:
                progress(len(loc.records), before + after)
        recs = list(loc.records)
    tracked = [r for r in recs[:n_before][first_loc - 1 :] if r.error_m is not None] if first_loc else []
    err = np.array([r.error_m for r in tracked], float)
    rec = recovery([r.error_m if r.error_m is not None else math.inf for r in recs[n_before:]])
    return {
        "localized_at_scan": None if first_loc is None else first_loc - 1,
        "rmse_m": float(np.sqrt(np.mean(err**2))) if err.size else None,
        "pf_ms_median": median(r.pf_ms for r in recs[:n_before]),
        "cpu_ms_per_scan": (
            1000.0 * (cpu_end - cpu_at_loc) / max(n_before - first_loc, 1)
            if first_loc is not None and n_before > first_loc
            else None
        ),
        # per block (``main``: the PF and the threads feeding the children; ``rpe``: KISS-ICP;
        # ``s2m``: road removal, M3RSM and GICP): the RPE alone is the method's floor per scan
        "cpu_ms_per_scan_by_block": (
            {
                name: 1000.0 * (blocks_end[name] - blocks_at_loc[name]) / (n_before - first_loc)
                for name in blocks_end
                if blocks_end[name] is not None and blocks_at_loc.get(name) is not None
            }
            if first_loc is not None and n_before > first_loc
            else None
        ),
        "recovered_after_kidnap": rec is not None,
        "recovery_scans": rec,
        "error_after_kidnap_end_m": recs[-1].error_m if len(recs) > n_before else None,
    }


def tracking(
    spec: SourceSpec, cfg: Config, before: int, after: int, cache_root: Path | None = None, progress=None
) -> dict:
    seq = open_source(spec, cfg, "peers", need_poses=True)
    before = min(before, len(seq) - 2)
    to = kidnap_target(seq, before - 1)
    prior = load_or_build_map(seq.map_source, cfg.map, cache_root).value
    g = gicp_tracking(seq, prior, cfg, before, to, after)
    lo = lidarloc_tracking(seq, cfg, before, to, after, cache_root, progress)
    G = np.asarray(seq.poses)
    return {
        "source": seq.name,
        "scans_tracked": before,
        "kidnap_from_scan": before - 1,
        "kidnap_to_scan": to,
        "kidnap_m": float(np.linalg.norm(G[to, :3, 3] - G[before - 1, :3, 3])),
        "scans_after_kidnap": after,
        "lidarloc": lo,
        "gicp": g,
        "rmse_ratio_lidarloc_over_gicp": (
            lo["rmse_m"] / g["rmse_m"] if lo["rmse_m"] is not None and g["rmse_m"] > 0 else None
        ),
        "cpu_ratio_lidarloc_over_gicp": (
            lo["cpu_ms_per_scan"] / g["cpu_ms_per_scan"] if lo["cpu_ms_per_scan"] is not None else None
        ),
    }


# ------------------------------------------------------------------------------------------ run
def run(
    spec: SourceSpec,
    cfg: Config,
    global_scans: int = 20,
    track_scans: int = 250,
    after_kidnap: int = 150,
    real: bool | None = None,
    paper: bool | None = None,
    paper_scans: int = 300,
    cache_root: Path | None = None,
    progress=None,
) -> dict:
    """Every part (see the module docstring); ``real``/``paper``: the real drive's global part and
    the KITTI 05 town (default: where their data is present)."""
    from . import peers_paper

    load_start = os.getloadavg()
    t_start = time.perf_counter()
    say = progress or (lambda what, i, n: None)
    result: dict = {
        "target_global": "success ≥ the best peer's at ≤ 1/5 of its median time",
        "target_tracking": "RMSE within 10 % of GICP tracking at ≤ its CPU per scan",
        "target_kidnap": "lidarloc recovers where GICP tracking cannot",
    }
    town = global_localization(spec, cfg, global_scans, cache_root, lambda i, n: say("global: town", i, n))
    result["skipped"] = add_optional_peers(town, spec, cfg, cache_root, lambda w, i, n: say(f"global: town, {w}", i, n))
    result["global_town"] = town
    real_spec = real_drive() if real is not False else None
    if real and real_spec is None:
        from ...core.errors import LidarlocError

        raise LidarlocError("bench peers --real: the real KITTI drive is not in the data directory")
    if real_spec is not None:
        real_part = global_localization(
            real_spec, replace(cfg), global_scans, cache_root, lambda i, n: say("global: real drive", i, n)
        )
        add_optional_peers(
            real_part, real_spec, replace(cfg), cache_root, lambda w, i, n: say(f"global: real drive, {w}", i, n)
        )
        result["global_real"] = real_part
    result["tracking"] = tracking(spec, cfg, track_scans, after_kidnap, cache_root, lambda i, n: say("tracking", i, n))
    if paper is not False:
        part = peers_paper.run(
            cfg, paper_scans, cache_root, lambda i, n: say("the paper's KITTI 05", i, n), required=bool(paper)
        )
        if part is not None:
            result["paper"] = part
    result.update(headline(result))
    result["cpu_count"] = os.cpu_count()
    result["loadavg_start"] = [round(v, 2) for v in load_start]
    result["loadavg_end"] = [round(v, 2) for v in os.getloadavg()]
    result["wall_s"] = time.perf_counter() - t_start
    return result


def headline(r: dict) -> dict:
    """The flat figures ``--json`` promises, the global ones over the town and the real drive
    together (each source's own are in ``global_town`` / ``global_real``), and the targets' verdicts."""
    parts = [r[k] for k in ("global_town", "global_real") if k in r]
    rows = [row for p in parts for row in p["rows"]]
    out = {}
    # the optional peers where they ran (on every scan of both parts: one process, one set of packages)
    optional = [p for p in PACKAGES if rows and all(f"{p}_success" in row for row in rows)]
    if "mapclosures" in optional:
        optional.append("mapclosures_single")
    for name in ("m3rsm", "fpfh_ransac", "fgr", *optional):
        out[f"{name}_success"] = float(np.mean([row[f"{name}_success"] for row in rows]))
        out[f"{name}_success_count"] = int(sum(bool(row[f"{name}_success"]) for row in rows))
        out[f"{name}_ms_median"] = median(row[f"{name}_ms"] for row in rows)
    if "mapclosures" in optional:
        out["mapclosures_stitch_ms_median"] = median(row["mapclosures_stitch_ms"] for row in rows)
    # what a query costs a user: MapClosures' stitching of its local map is part of it
    cost = {name: out[f"{name}_ms_median"] for name in ("fpfh_ransac", "fgr", *optional)}
    if "mapclosures" in optional:
        cost["mapclosures"] = median(row["mapclosures_ms"] + row["mapclosures_stitch_ms"] for row in rows)
    t = r["tracking"]
    out.update(
        lidarloc_tracking_rmse_m=t["lidarloc"]["rmse_m"],
        gicp_tracking_rmse_m=t["gicp"]["rmse_m"],
        lidarloc_cpu_ms_per_scan=t["lidarloc"]["cpu_ms_per_scan"],
        gicp_cpu_ms_per_scan=t["gicp"]["cpu_ms_per_scan"],
        # KISS-ICP alone: the relative pose estimation the method runs on every scan
        lidarloc_rpe_cpu_ms_per_scan=(t["lidarloc"].get("cpu_ms_per_scan_by_block") or {}).get("rpe"),
        lidarloc_ms_median=t["lidarloc"]["pf_ms_median"],
        gicp_ms_median=t["gicp"]["ms_median"],
        lidarloc_recovered_after_kidnap=t["lidarloc"]["recovered_after_kidnap"],
        gicp_recovered_after_kidnap=t["gicp"]["recovered_after_kidnap"],
        lidarloc_recovery_scans=t["lidarloc"]["recovery_scans"],
        gicp_recovery_scans=t["gicp"]["recovery_scans"],
    )
    best = max(cost, key=lambda n: (out[f"{n}_success"], -cost[n]))
    out["best_global_peer"] = best
    out["best_global_peer_ms_median"] = cost[best]
    out["global_target_met"] = bool(
        out["m3rsm_success"] >= out[f"{best}_success"] and out["m3rsm_ms_median"] <= cost[best] / 5
    )
    lr, gr = out["lidarloc_tracking_rmse_m"], out["gicp_tracking_rmse_m"]
    lc, gc = out["lidarloc_cpu_ms_per_scan"], out["gicp_cpu_ms_per_scan"]
    out["tracking_target_met"] = bool(lr is not None and lc is not None and lr <= 1.1 * gr and lc <= gc)
    out["kidnap_target_met"] = bool(out["lidarloc_recovered_after_kidnap"] and not out["gicp_recovered_after_kidnap"])
    return out

"""``lidarloc inspect``: replay a run up to one scan and write why the filter is where it is, as
files for scripts and papers.

The run is ``lidarloc run``'s (same source, configuration and seed), in the replay clock so the
scan's state is reproducible. At scan K it writes, into ``--out``:

- ``surface_estimate.png`` / ``.npy``: the scan's log-likelihood on the x–y grid around the
  estimate (:meth:`~lidarloc.core.filter.surface.LikelihoodModel.surface`, the filter's kernel and
  options at that scan), with a colour bar and the truth, the estimate and the maximum marked;
- ``surface_truth.png`` / ``.npy``: the same around the truth (where the source has it);
- ``residuals.png``: the scan at the estimate seen from above, each point coloured by its
  distance to the map (green ≤ σ, red ≥ d_max, the viewer's ramp), over the map in grey;
- ``inspect.json``: ``scan``, ``estimate``, ``truth`` (x, y, z in m; yaw, pitch, roll in
  degrees), ``surface_argmax_xy``, ``surface_argmax_error_m`` (the maximum around the estimate to
  the truth), ``residual_share_beyond_dmax`` (at the estimate), ``surface_ms``, and the surface
  grids' geometry (an ``.npy`` holds ``ll[i, k]`` at x = x0 + i·cell, y = y0 + k·cell).
"""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
from rich.console import Console

from ..core.config import Config
from ..core.errors import LidarlocError
from ..core.filter.residuals import scan_residuals
from ..core.filter.surface import CELL, HALF_WIDTH, YAW_STEP, YAW_WINDOW, LikelihoodModel, Surface
from ..core.geometry import pose_to_xyz_ypr
from ..core.localizer import Localizer
from ..core.runs.results import make_out_dir
from ..core.sequences.factory import SourceSpec
from .console import preparing, progress_bar
from .options import open_source
from .viewer.why_style import RESIDUAL_LUT, residual_colors, surface_scale
from .viewer.why_surface import scan_in_sensor_frame

FILES = (
    "surface_estimate.png",
    "surface_estimate.npy",
    "surface_truth.png",
    "surface_truth.npy",
    "residuals.png",
    "inspect.json",
)
MAP_POINTS_SHOWN = 200_000  # grey map points under the residual image (random subset)


def _pose_json(T) -> dict | None:
    if T is None:
        return None
    x, y, z, yaw, pitch, roll = (float(v) for v in pose_to_xyz_ypr(np.asarray(T, float)))
    return {
        "x": x,
        "y": y,
        "z": z,
        "yaw_deg": math.degrees(yaw),
        "pitch_deg": math.degrees(pitch),
        "roll_deg": math.degrees(roll),
    }


def _grid_json(s: Surface) -> dict:
    return {
        "x0": float(s.xs[0]),
        "y0": float(s.ys[0]),
        "cell": s.cell,
        "shape": list(s.ll.shape),
        "yaw_window_deg": math.degrees(s.yaw_window),
        "ms": round(s.ms, 1),
    }


def run_inspect(
    spec: SourceSpec,
    cfg: Config,
    scan: int,
    out: Path,
    cache_root: Path | None = None,
    console: Console | None = None,
    best_over_yaw: bool = False,
) -> dict:
    """Replay to ``scan``, write the files (module docstring) and return the JSON's content."""
    console = console or Console(stderr=True)
    seq = open_source(spec, cfg, console)
    if not 0 <= int(scan) < len(seq):
        raise LidarlocError(f"--scan {scan} is beyond {seq.name}'s {len(seq)} scans (0…{len(seq) - 1})")
    make_out_dir(out)
    cfg = replace(cfg, localize=replace(cfg.localize, clock="replay"))
    loc = preparing(lambda progress: Localizer(seq, cfg, cache_root, progress=progress))
    try:
        with progress_bar() as bar:
            task = bar.add_task(f"replaying {seq.name} to scan {scan}", total=scan + 1)
            snap = loc.snapshot()
            while snap.scan_index < scan and not loc.done:
                snap = loc.step()
                bar.update(task, completed=snap.scan_index + 1)
        if snap.scan_index != scan:  # a kidnap cannot happen here; the sequence ended early
            raise LidarlocError(f"the run ended at scan {snap.scan_index} before scan {scan}")
        model = LikelihoodModel.of(loc)
        result = _write(snap, model, loc.prior_map.points, out, best_over_yaw, origin=loc.prior_map.origin)
    finally:
        loc.close()
    err_m = result["surface_argmax_error_m"]
    console.print(
        f"scan {scan} of {seq.name}: "
        + ("" if err_m is None else f"the surface's maximum {err_m:.2f} m from the truth, ")
        + f"{result['residual_share_beyond_dmax']:.1%} of the scan beyond d_max → {out}"
    )
    return result


def _write(
    snap, model: LikelihoodModel, map_points: np.ndarray, out: Path, best_over_yaw: bool, origin=(0.0, 0.0, 0.0)
) -> dict:
    pts = scan_in_sensor_frame(snap)
    if len(pts) == 0:
        raise LidarlocError(f"scan {snap.scan_index} has no points left after preparation")
    window = YAW_WINDOW if best_over_yaw else 0.0
    est = pose_to_xyz_ypr(np.asarray(snap.mean_pose, float))
    around_est = model.surface(pts, est, HALF_WIDTH, CELL, window, YAW_STEP)
    gt = None if snap.gt_pose is None else np.asarray(snap.gt_pose, float)
    around_gt = None if gt is None else model.surface(pts, pose_to_xyz_ypr(gt), HALF_WIDTH, CELL, window, YAW_STEP)
    res = scan_residuals(snap.scan_world, model.lookup, model.d_max)

    files = []
    for name, surf in (("surface_estimate", around_est), ("surface_truth", around_gt)):
        if surf is None:
            continue
        np.save(out / f"{name}.npy", surf.ll)
        _surface_png(out / f"{name}.png", surf, snap, "estimate" if name == "surface_estimate" else "truth")
        files += [f"{name}.png", f"{name}.npy"]
    _residual_png(out / "residuals.png", res, snap, model, map_points)
    files.append("residuals.png")

    best = around_est.argmax_xy
    result = {
        "scan": int(snap.scan_index),
        "estimate": _pose_json(snap.mean_pose),
        "truth": _pose_json(gt),
        "error_m": snap.error_m,
        "localized": bool(snap.localized),
        "surface_argmax_xy": [float(best[0]), float(best[1])],
        "surface_argmax_error_m": None if gt is None else float(np.linalg.norm(best - gt[:2, 3])),
        "residual_share_beyond_dmax": res.share_beyond,
        "surface_ms": round(around_est.ms, 1),
        "surface_estimate": _grid_json(around_est),
        "surface_truth": None
        if around_gt is None
        else {
            **_grid_json(around_gt),
            "argmax_xy": [float(v) for v in around_gt.argmax_xy],
            "argmax_error_m": float(np.linalg.norm(around_gt.argmax_xy - gt[:2, 3])),
        },
        "d_max_m": model.d_max,
        "sigma_m": model.sigma,
        "scan_points": int(len(pts)),
        # poses and grids are in the map's local frame: add this for a georeferenced map file's own
        "map_origin_m": [float(v) for v in origin],
        "files": files + ["inspect.json"],
    }
    (out / "inspect.json").write_text(json.dumps(result, indent=2) + "\n")
    return result


# ------------------------------------------------------------------------------------ images
def _figure():
    import matplotlib

    matplotlib.use("Agg")  # files only, no display
    import matplotlib.pyplot as plt

    return plt


def _marks(ax, snap, best_xy=None) -> None:
    est = np.asarray(snap.mean_pose, float)[:2, 3]
    if snap.gt_pose is not None:
        gt = np.asarray(snap.gt_pose, float)[:2, 3]
        ax.plot(gt[0], gt[1], "x", color="white", ms=11, mew=2.5, label="truth")
    ax.plot(est[0], est[1], "x", color="#ff961e", ms=11, mew=2.5, label="estimate")
    if best_xy is not None:
        ax.plot(best_xy[0], best_xy[1], "o", mfc="none", color="#ff3cff", ms=13, mew=2, label="maximum")
    ax.legend(loc="upper right", fontsize=8, facecolor="#444444", labelcolor="white", framealpha=0.8)


def _surface_png(path: Path, s: Surface, snap, around: str) -> None:
    plt = _figure()
    lo, hi = surface_scale(s.ll)
    fig, ax = plt.subplots(figsize=(7, 6), dpi=110)
    x0, y0, x1, y1 = s.extent
    im = ax.imshow(
        s.ll.T, origin="lower", extent=(x0, x1, y0, y1), cmap="viridis", vmin=lo, vmax=hi, interpolation="nearest"
    )
    fig.colorbar(im, ax=ax, label="log-likelihood (nats)")
    _marks(ax, snap, s.argmax_xy)
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    yaws = "at its yaw" if s.yaw_window == 0 else f"best over ±{math.degrees(s.yaw_window):.0f}°"
    ax.set_title(f"scan {snap.scan_index}: log-likelihood around the {around} ({yaws})", fontsize=10)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_aspect("equal")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _residual_png(path: Path, res, snap, model: LikelihoodModel, map_points: np.ndarray) -> None:
    plt = _figure()
    from matplotlib.colors import ListedColormap, Normalize

    pts = res.points
    lo, hi = pts[:, :2].min(axis=0) - 5.0, pts[:, :2].max(axis=0) + 5.0
    mp = np.asarray(map_points)
    near = mp[np.all((mp[:, :2] >= lo) & (mp[:, :2] <= hi), axis=1)]
    if len(near) > MAP_POINTS_SHOWN:
        near = near[np.random.default_rng(0).choice(len(near), MAP_POINTS_SHOWN, replace=False)]
    fig, ax = plt.subplots(figsize=(8, 7), dpi=110)
    ax.set_facecolor("#202020")
    ax.scatter(near[:, 0], near[:, 1], s=0.3, c="#6a6a6a", linewidths=0, rasterized=True)
    order = np.argsort(res.distance)  # red on top: the points to look at
    colors = residual_colors(res.distance, model.sigma, res.d_max)[order] / 255.0
    ax.scatter(pts[order, 0], pts[order, 1], s=1.5, c=colors, linewidths=0, rasterized=True)
    cmap = ListedColormap(RESIDUAL_LUT / 255.0)
    sm = plt.cm.ScalarMappable(norm=Normalize(model.sigma, res.d_max), cmap=cmap)
    fig.colorbar(sm, ax=ax, label=f"distance to the map (m): green ≤ σ = {model.sigma:g}, red ≥ d_max = {res.d_max:g}")
    _marks(ax, snap)
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    ax.set_title(
        f"scan {snap.scan_index} at the estimate: {res.share_beyond:.1%} of {len(pts):,} points beyond d_max",
        fontsize=10,
    )
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)

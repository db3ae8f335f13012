"""What ``lidarloc corpus staleness`` writes, per map: ``MAP/staleness.npz`` (the grid: origin,
resolution, counts, the stale mask), ``MAP/staleness.png`` (the heat map over the map's top view)
and ``MAP/stale.ply`` (the stale places' points, map frame); and ``staleness.json`` (the
summary). :func:`read_grid` reads a grid back (the viewer's layer)."""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import numpy as np

from ...core.errors import LidarlocError
from ...core.runs.results import make_out_dir, write_json
from .staleness import MapGrid, Settings, stale_points

COUNTS = ("scans_observed", "scans_disagree", "drives_observed", "drives_disagree")
GRID_FILE, HEAT_FILE, POINTS_FILE, SUMMARY_FILE = "staleness.npz", "staleness.png", "stale.ply", "staleness.json"


def write_outputs(results: list[dict], s: Settings, out: Path, run_dir: Path) -> dict:
    """Write every map's files and the summary into ``out``; returns the summary."""
    from ...core.maps.mapfile_write import write_map

    make_out_dir(out)
    maps = []
    for r in results:
        grid: MapGrid = r["grid"]
        folder = out / r["name"]
        make_out_dir(folder)
        stale = grid.stale(s)
        counts = {k: getattr(grid, k) for k in COUNTS}
        np.savez_compressed(
            folder / GRID_FILE, origin=grid.origin, resolution=grid.cell_m, stale=stale, places=r["labels"], **counts
        )
        points = stale_points(grid, s)
        write_map(folder / POINTS_FILE, points.astype(np.float32))
        heat_map(grid, stale, r["places"], folder / HEAT_FILE, r.get("truth"), r.get("known"))
        entry = {
            "map": r["name"],
            "drives": grid.drives,
            "cells_observed": int((grid.drives_observed > 0).sum()),
            "cells_stale": int(stale.sum()),
            "stale_points": len(points),
            "places": r["places"],
            "files": [str(folder / n) for n in (GRID_FILE, HEAT_FILE, POINTS_FILE)],
        }
        if r.get("truth") is not None:
            entry["known_changes"] = r["truth"]
        maps.append(entry)
    summary = {"run": str(run_dir), "settings": asdict(s), "maps": maps}
    for key in ("recall", "precision", "traffic_flagged"):  # the one map's score, at the top
        known = [m["known_changes"][key] for m in maps if "known_changes" in m]
        if len(known) == 1:
            summary[key] = known[0]
    write_json(out / SUMMARY_FILE, summary)
    return summary


def heat_map(
    grid: MapGrid, stale: np.ndarray, places: list[dict], path: Path, truth: dict | None, known: np.ndarray | None
) -> None:
    """The map's top view: where it was observed (grey), the share of the drives that saw it
    that disagreed (colour), the stale places circled and the known changes (where the world
    knows them) marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Circle

    share = np.where(grid.drives_observed > 0, grid.drives_disagree / np.maximum(grid.drives_observed, 1), np.nan)
    share[grid.drives_disagree == 0] = np.nan
    extent = (
        grid.origin[0],
        grid.origin[0] + grid.shape[0] * grid.cell_m,
        grid.origin[1],
        grid.origin[1] + grid.shape[1] * grid.cell_m,
    )
    fig, ax = plt.subplots(figsize=(9, 9 * grid.shape[1] / max(grid.shape[0], 1) + 0.5), dpi=110)
    ax.imshow((grid.drives_observed > 0).T, origin="lower", extent=extent, cmap="Greys", vmin=0, vmax=4, alpha=0.8)
    im = ax.imshow(share.T, origin="lower", extent=extent, cmap="inferno_r", vmin=0, vmax=1)
    for p in places:
        ax.add_patch(Circle((p["x"], p["y"]), 3 + p["cells"] ** 0.5, fill=False, color="tab:cyan", lw=1.2))
    if known is not None and len(known):
        ax.plot(known[:, 0], known[:, 1], "x", color="tab:green", ms=5, label="known changes")
        ax.legend(loc="upper right", fontsize=8)
    ax.set_xlim(extent[0], extent[1])
    ax.set_ylim(extent[2], extent[3])
    fig.colorbar(im, ax=ax, shrink=0.7, label="share of the drives that saw the cell and disagreed")
    title = f"{len(grid.drives)} drives, {int(stale.sum())} stale cells, {len(places)} stale places (circled)"
    if truth is not None:
        title += f"\nknown changes: recall {truth['recall']}, precision {truth['precision']}"
    ax.set(title=title, xlabel="x (m)", ylabel="y (m)", aspect="equal")
    ax.title.set_fontsize(10)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def read_grid(folder: Path) -> dict:
    """A staleness grid written by :func:`write_outputs` (``folder``: the output folder or one
    map's folder in it, with one map): origin, resolution, stale mask, counts, and the stale
    points (None without the point file)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise LidarlocError(f"{folder}: no such folder (the --out folder of lidarloc corpus staleness)")
    found = [folder / GRID_FILE] if (folder / GRID_FILE).is_file() else sorted(folder.glob(f"*/{GRID_FILE}"))
    if not found:
        raise LidarlocError(f"{folder}: no {GRID_FILE} (the --out folder of lidarloc corpus staleness)")
    if len(found) > 1:
        raise LidarlocError(f"{folder}: staleness of {len(found)} maps; name one map's folder in it")
    try:
        with np.load(found[0]) as z:
            grid = {k: z[k] for k in z.files}
    except (OSError, ValueError) as exc:
        raise LidarlocError(f"{found[0]}: unreadable ({type(exc).__name__})") from None
    ply = found[0].parent / POINTS_FILE
    grid["points"] = None
    if ply.is_file() and int(grid["stale"].sum()):
        from ...core.maps.mapfile import read_map

        cloud = read_map(ply)
        grid["points"] = np.asarray(cloud.points, np.float64) + np.asarray(cloud.origin)
    return grid

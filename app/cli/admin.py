"""``lidarloc runs list`` and ``lidarloc runs prune``: the viewer's recorded runs on disk, and
keeping them under a budget (what ``view`` / ``demo`` do by themselves with ``--keep-runs`` and
``--max-record-gb``)."""

from __future__ import annotations

import datetime as _dt
from pathlib import Path
from typing import Annotated

import typer

from ...core.cache import default_cache_root
from ...core.errors import LidarlocError
from ..console import emit_json, err
from ..options import CacheOpt, JsonOpt
from ..viewer.budget import LIVE_S, RunFolder, find_runs, plan_prune, remove_runs, total_bytes
from .groups import app

runs_app = typer.Typer(no_args_is_help=True, help="The viewer's recorded runs: list them, prune them to a budget.")
app.add_typer(runs_app, name="runs")

DirOpt = Annotated[
    Path | None,
    typer.Option(
        "--dir", help="The runs folder (default: runs/ under the cache directory; or a viewer's --record-dir)."
    ),
]


def _root(folder: Path | None, cache: Path | None) -> Path:
    root = folder if folder is not None else (cache if cache is not None else default_cache_root()) / "runs"
    if folder is not None and not folder.is_dir():
        raise LidarlocError(f"{folder}: no such folder")
    return root


def _row(r: RunFolder) -> dict:
    return {
        "run": str(r.path),
        "steps": r.steps,
        "mb": round(r.mb, 1),
        "written": _dt.datetime.fromtimestamp(r.written).isoformat(timespec="seconds"),
        "branch_of": None if r.branch_of is None else str(r.branch_of),
        "window": None if r.window is None else list(r.window),
    }


@runs_app.command("list")
def list_runs(dir_: DirOpt = None, cache: CacheOpt = None, as_json: JsonOpt = False):
    """The recorded runs, oldest first: folder, steps, size, when last written; a run that kept a
    rolling window of its newest steps under the recording budget says which steps it holds."""
    root = _root(dir_, cache)
    runs = find_runs(root)
    if as_json:
        emit_json({"root": str(root), "runs": [_row(r) for r in runs], "total_mb": round(total_bytes(runs) / 1e6, 1)})
        return
    if not runs:
        err.print(f"no recorded runs under {root}", markup=False, highlight=False)
        return
    for r in runs:
        row = _row(r)
        window = "" if r.window is None else f"  (rolling window: steps {r.window[0]}–{r.window[1]})"
        typer.echo(f"{row['written']}  {r.steps:6d} steps  {r.mb:9.1f} MB  {r.path}{window}")
    typer.echo(f"{len(runs)} runs, {total_bytes(runs) / 1e6:.1f} MB under {root}")


@runs_app.command("prune")
def prune(
    keep_runs: Annotated[
        int | None, typer.Option("--keep-runs", min=0, help="Keep at most this many runs (the newest).")
    ] = None,
    max_gb: Annotated[
        float | None, typer.Option("--max-gb", min=0.0, help="Keep the runs under this many GB in all.")
    ] = None,
    dry_run: Annotated[bool, typer.Option("--dry-run", help="Say what would be removed; remove nothing.")] = False,
    dir_: DirOpt = None,
    cache: CacheOpt = None,
    as_json: JsonOpt = False,
):
    """Remove the oldest recorded runs until at most --keep-runs are left and they take at most
    --max-gb. Runs written in the last two minutes (a viewer may be recording them) and the runs
    a kept branch starts from are never removed."""
    if keep_runs is None and max_gb is None:
        raise LidarlocError("say how much to keep: --keep-runs N and/or --max-gb G")
    root = _root(dir_, cache)
    runs = find_runs(root)
    plan = plan_prune(runs, keep_runs, None if max_gb is None else max_gb * 1e9)
    removed = plan if dry_run else remove_runs(plan, root)
    left = [r for r in runs if r not in removed]
    if as_json:
        emit_json(
            {
                "root": str(root),
                "dry_run": dry_run,
                "removed": [_row(r) for r in removed],
                "kept": len(left),
                "kept_mb": round(total_bytes(left) / 1e6, 1),
                "live_s": LIVE_S,
            }
        )
        return
    verb = "would remove" if dry_run else "removed"
    for r in removed:
        typer.echo(f"{verb} {r.path} ({r.steps} steps, {r.mb:.1f} MB)")
    typer.echo(
        f"{verb} {len(removed)} runs ({total_bytes(removed) / 1e6:.1f} MB); {len(left)} runs left, "
        f"{total_bytes(left) / 1e6:.1f} MB"
    )

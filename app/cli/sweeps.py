"""``lidarloc sweep`` and ``lidarloc tune``: many runs of one source, on this machine or on Ray."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from ..console import emit_json, err
from ..options import CacheOpt, ConfigOpt, JsonOpt, PresetOpt, SetOpt, WorldOpt, with_source
from ..sweep.cluster import RAY_HELP
from .groups import app

_KEYS = (
    "The keys are the configuration's (docs/configuration.md), e.g. pf.sigma, pf.d_max, pf.n_particles, s2m.region_x."
)
RayOpt = Annotated[
    str | None, typer.Option("--ray", metavar="local|auto|ray://HOST:PORT", help=f"Run on Ray: {RAY_HELP}.")
]
WorkersOpt = Annotated[
    int | None, typer.Option("--workers", help="Runs at a time (default: this machine's CPUs, or the Ray cluster's).")
]
NoRecordOpt = Annotated[
    bool,
    typer.Option(
        "--no-record", help="Do not keep each run's recording (by default `lidarloc view --run` opens any run)."
    ),
]


def _workers(workers: int | None, ray: str | None) -> int:
    from ..sweep.executor import default_workers

    if workers is not None:
        return workers
    if ray not in (None, "local"):
        from ..sweep.cluster import cluster_cpus, connect

        connect(ray, 1)
        return cluster_cpus()
    return default_workers()


@app.command("sweep")
@with_source()
def sweep(
    grid: Annotated[
        list[str] | None,
        typer.Option(
            "--grid",
            metavar="KEY=V1,V2,…",
            help=f"A swept entry and its values (repeatable; every combination). {_KEYS}",
        ),
    ] = None,
    runs: Annotated[int, typer.Option("--runs", help="Seeded runs per combination (seeds 0…N−1).")] = 5,
    out: Annotated[
        Path, typer.Option("--out", help="Folder of the runs and the results (resumed if it exists).")
    ] = Path("out/sweep"),
    ray: RayOpt = None,
    workers: WorkersOpt = None,
    no_record: NoRecordOpt = False,
    world: WorldOpt = "lived-in",
    as_json: JsonOpt = False,
    spec=None,
    preset: PresetOpt = None,
    config: ConfigOpt = None,
    set_: SetOpt = None,
    cache: CacheOpt = None,
):
    """Every combination of settings × seeds, each run in its own folder: runs.csv, per-combination
    medians, plots, best.yaml (for --config).

    Runs in a local process pool, or on Ray with --ray. The map and its tables are built once and shared. Run the same command again to resume: finished runs are kept, failed ones run again."""
    from ..sweep.grid import parse_grid
    from ..sweep.sweep import Settings, run_sweep

    g = parse_grid(grid)
    settings = Settings(spec, config, tuple(set_ or ()), preset, world, cache)
    summary, tally = run_sweep(settings, g, runs, _workers(workers, ray), out, ray=ray, record=not no_record)
    if as_json:
        emit_json(summary)
    else:
        _print_summary(summary, list(g.axes), out)
    if tally.interrupted:
        err.print(f"interrupted: run the same command again to resume ({summary['done']} of {summary['runs']} done)")
        raise typer.Exit(130)


def _print_summary(summary: dict, keys: list[str], out: Path) -> None:
    for c in summary["combinations"]:
        setting = " ".join(f"{k}={c[k]}" for k in keys)
        rmse = c["rmse_after_localized_m_median"]
        success = "–" if c["success"] is None else f"{100 * c['success']:.0f}%"
        err.print(
            f"{setting}: success {success}, RMSE after {'–' if rmse is None else f'{rmse:.2f} m'}, "
            f"{c['done']}/{c['runs']} runs" + (f", {c['failed']} failed" if c["failed"] else ""),
            highlight=False,
            markup=False,
        )
    best = summary["best_settings"]
    err.print(
        f"best: {best} → {out / 'best.yaml'}" if best else "best: no combination succeeded in every run",
        highlight=False,
        markup=False,
    )
    err.print(f"runs.csv, combinations.csv, plots/ and each run's recording in {out}", highlight=False, markup=False)

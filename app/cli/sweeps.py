"""``lidarloc sweep`` and ``lidarloc tune``: many runs of one source, on this machine or on Ray."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from ..console import emit_json, err
from ..options import CacheOpt, JsonOpt, with_settings, with_source
from ..sweep.cluster import RAY_HELP
from .groups import app, bench_app

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


def workers_for(workers: int | None, ray: str | None) -> int:
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
@with_settings(world=True)
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
    as_json: JsonOpt = False,
    spec=None,
    settings=None,
    cache: CacheOpt = None,
):
    """Every combination of settings × seeds, each run in its own folder: runs.csv, per-combination
    medians, plots, best.yaml (for --config).

    Runs in a local process pool, or on Ray with --ray. The map and its tables are built once and shared. Run the same command again to resume: finished runs are kept, failed ones run again."""
    from ..sweep.grid import parse_grid
    from ..sweep.sweep import Settings, run_sweep

    g = parse_grid(grid)
    shared = Settings(spec, settings.config, settings.overrides, settings.preset, settings.world, cache)
    summary, tally = run_sweep(shared, g, runs, workers_for(workers, ray), out, ray=ray, record=not no_record)
    if as_json:
        emit_json(summary)
    else:
        _print_summary(summary, list(g.axes), out, recorded=not no_record)
    if tally.interrupted:
        err.print(f"interrupted: run the same command again to resume ({summary['done']} of {summary['runs']} done)")
        raise typer.Exit(130)


def _print_summary(summary: dict, keys: list[str], out: Path, recorded: bool) -> None:
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
    where = "runs.csv, combinations.csv, plots/" + (" and each run's recording" if recorded else "")
    err.print(f"{where} in {out}", highlight=False, markup=False)


@app.command("tune")
@with_source()
@with_settings(world=True)
def tune(
    param: Annotated[
        list[str] | None,
        typer.Option(
            "--param",
            metavar="KEY=LOW:HIGH",
            help=f"A searched entry and its range (repeatable; integer bounds search integers). {_KEYS}",
        ),
    ] = None,
    trials: Annotated[int, typer.Option("--trials", help="Settings tried (the starting settings are the first).")] = 60,
    runs: Annotated[int, typer.Option("--runs", help="Seeds per trial (0…N−1), the same for every trial.")] = 3,
    out: Annotated[Path, typer.Option("--out", help="Folder of the trials and the results.")] = Path("out/tune"),
    ray: RayOpt = None,
    workers: WorkersOpt = None,
    as_json: JsonOpt = False,
    spec=None,
    settings=None,
    cache: CacheOpt = None,
):
    """Search the settings that localize best: the lowest median RMSE after localization with every seed localized and no false fire.

    Optuna's TPE through Ray Tune (a local Ray instance unless --ray names a cluster); a trial whose seed fails, or whose RMSE is already worse than most, is stopped early. Writes trials.csv, best.yaml (for --config), importance.png and tune.json, and compares the best with the starting settings."""
    from ..sweep.sweep import Settings
    from ..sweep.tune import parse_params, run_tune

    params = parse_params(param)
    shared = Settings(spec, settings.config, settings.overrides, settings.preset, settings.world, cache)
    summary = run_tune(shared, params, trials, runs, workers_for(workers, ray), out, ray=ray)
    if as_json:
        emit_json(summary)
        return
    base, best = summary["defaults"]["trial"], summary["best"]
    err.print(
        f"{summary['trials']} trials, {summary['met']} met every seed, {summary['stopped_early']} stopped early",
        highlight=False,
    )
    if base is not None:
        rmse = base["rmse_median"]
        err.print(
            f"starting settings {summary['defaults']['settings']}: "
            + (f"RMSE after {rmse:.3f} m" if base["met"] else "did not meet every seed"),
            highlight=False,
            markup=False,
        )
    if best is None:
        err.print("best: no trial met every seed", highlight=False)
    else:
        gain = summary["improvement_m"]
        err.print(
            f"best {summary['best_settings']}: RMSE after {best['rmse_median']:.3f} m"
            + ("" if gain is None else f" ({gain:.3f} m lower than the starting settings')")
            + f" → {out / 'best.yaml'}",
            highlight=False,
            markup=False,
        )
    err.print(f"trials.csv, importance.png and tune.json in {out}", highlight=False, markup=False)


@bench_app.command("sweep")
def bench_sweep(
    runs: Annotated[int, typer.Option("--runs", min=1, help="Runs in the sweep.")] = 16,
    workers: Annotated[int, typer.Option("--workers", min=1, help="Runs at a time.")] = 2,
    run_s: Annotated[float, typer.Option("--run-s", min=0.1, help="CPU seconds of each run.")] = 20.0,
    as_json: JsonOpt = False,
):
    """A sweep's scheduling overhead on Ray beside the process pool: the same runs of fixed CPU work on both."""
    from ..sweep.overhead import measure

    result = measure(runs, workers, run_s)
    if as_json:
        emit_json(result)
        return
    err.print(
        f"{runs} runs of {run_s:g} s CPU on {workers} workers: process pool {result['pool_wall_s']:.1f} s, "
        f"Ray {result['ray_wall_s']:.1f} s ({result['ray_over_pool']:.3f}×; Ray's start {result['ray_start_s']:.1f} s "
        f"apart); overhead {result['overhead_per_run_s']:.2f} s per run = "
        f"{100 * result['overhead_share_of_run']:.1f} % of a run (load {result['load_1min']:.1f})",
        highlight=False,
    )

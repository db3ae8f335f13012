"""``lidarloc sweep``: every combination of the swept settings × seeds, each run in a folder of its own.

A run is ``lidarloc bench localize``'s seeded run (:func:`~lidarloc.app.bench.localize.run_one`:
replay clock, the odometry recorded once per world, its recording kept so ``lidarloc view --run``
opens it) with the combination's entries set over the sweep's configuration. The world is built
once: here, before the runs, for the base configuration, then by each combination's first run on
each machine (:mod:`.world`) — a combination that changes the map's or the odometry's settings
gets its own cache entries, one that does not only loads them.

Layout of ``--out``: ``runs/COMBINATION/seed_NNN/`` (summary.json, scans.csv, recording/),
``runs.csv`` / ``runs.json`` (one row per run), ``combinations.csv`` (one row per combination),
``plots/``, ``best.yaml``, ``sweep.json`` (what was swept, and the summary), ``ray/`` (Ray Tune's
trials, with ``--ray``).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from ...core.cache import default_cache_root
from ...core.config import Config, load_config
from ...core.errors import LidarlocError
from ...core.runs.results import make_out_dir
from ...core.sequences.factory import SourceSpec
from ..bench.localize import code_fingerprint, numba_threads_for, prepare_cache, run_one
from .bookkeeping import Run, Tally
from .executor import execute
from .grid import Grid, check_grid
from .results import write_results
from .world import ensure_world, mark_ready


@dataclass(frozen=True)
class Settings:
    """What every run of a sweep shares: source, configuration, where the world is cached."""

    spec: SourceSpec
    config: Path | None
    overrides: tuple[str, ...]
    preset: str | None
    world: str | None
    cache_root: Path | None

    def config_for(self, extra: list[str]) -> Config:
        """The configuration with ``extra`` entries set last (the odometry recorded once per world:
        the same numbers as computing it in every run, ~50 ms less per scan)."""
        return load_config(
            self.config,
            ["localize.recorded_odometry=true", *self.overrides, *extra],
            preset=self.preset,
            world=self.world,
        )

    @property
    def cache(self) -> str:
        return str(Path(self.cache_root or default_cache_root()).absolute())


def plan_runs(settings: Settings, grid: Grid, runs: int, out_dir: Path, workers: int, record: bool) -> list[Run]:
    """One Run per combination × seed (seeds 0…runs−1), in the grid's order."""
    spec_d = settings.spec.to_dict()
    threads = numba_threads_for(workers)
    plan = []
    for combo in grid.combinations():
        cfg_d = settings.config_for(grid.overrides(combo)).to_dict()
        cfg_d.pop("seed", None)
        for seed in range(runs):
            run_dir = str((out_dir / "runs" / grid.name(combo) / f"seed_{seed:03d}").absolute())
            plan.append(
                Run(
                    point=(*combo, seed),
                    label=f"{' '.join(grid.overrides(combo))} seed {seed}",
                    run_dir=run_dir,
                    args=(spec_d, cfg_d, seed, settings.cache, run_dir, threads, settings.preset, record),
                    before=(ensure_world, (spec_d, cfg_d, settings.cache, threads)),
                )
            )
    return plan


def check_identity(out_dir: Path, settings: Settings, runs_per: int) -> None:
    """A sweep's folder holds runs of one source, base configuration and code: a sweep with more
    values or seeds may add to it, anything else goes to another --out."""
    cfg = settings.config_for([]).to_dict()
    cfg.pop("seed", None)
    identity = json.dumps(
        {
            "source": settings.spec.to_dict(),
            "config": cfg,
            "preset": settings.preset,
            "code": code_fingerprint(),
        },
        sort_keys=True,
        default=str,
    )
    marker = out_dir / "sweep_identity.json"
    if marker.is_file() and marker.read_text() != identity:
        raise LidarlocError(
            f"{out_dir}: holds runs of another source, configuration or version of lidarloc's code; use another --out"
        )
    marker.write_text(identity)


def run_sweep(
    settings: Settings,
    grid: Grid,
    runs: int,
    workers: int,
    out_dir: Path,
    ray: str | None = None,
    record: bool = True,
    plots: bool = True,
) -> tuple[dict, Tally]:
    """Run the sweep (resuming what ``out_dir`` holds) and write its results; returns the
    summary (sweep.json) and the tally."""
    if runs < 1 or workers < 1:
        raise LidarlocError("--runs and --workers must be ≥ 1")
    check_grid(grid, settings.config_for)
    out_dir = Path(out_dir)
    make_out_dir(out_dir)
    check_identity(out_dir, settings, runs)
    planned = plan_runs(settings, grid, runs, out_dir, workers, record)
    if any(not Path(r.run_dir, "summary.json").is_file() for r in planned) and ray in (None, "local"):
        # the one long build (the map, ~2.5 min for the default town) here, behind a progress bar
        base = settings.config_for([])
        prepare_cache(settings.spec, base, Path(settings.cache))
        base_d = base.to_dict()
        base_d.pop("seed", None)
        mark_ready(settings.spec.to_dict(), base_d, settings.cache)
    axes = {**{k: list(v) for k, v in grid.axes.items()}, "seed": list(range(runs))}
    tally = execute(
        run_one,
        axes,
        planned,
        workers,
        on_done=lambda run, summary: None,
        label=f"sweep: {len(planned)} runs",
        ray=ray,
        ray_dir=out_dir / "ray",
    )
    summary = write_results(out_dir, grid, planned, settings, tally, plots=plots)
    return summary, tally

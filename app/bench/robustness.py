"""``lidarloc bench robustness``: how localization holds up when the world is not the map.

The matrix: the town changed since it was mapped (share of movable objects moved, removed or
added: 0, 0.3, 0.6) × traffic (off, on) × the sensor of the drive (HDL-64E, VLP-16, OS1-128) ×
motion skew (off, on) × configuration (``paper``: the paper's method, the ``paper`` preset;
``default``: the defaults; ``no-S2M``: the defaults without scan-to-map matching) — 108 cells,
each run R times with seeds 0…R−1 on the built-in town (optionally laid along a KITTI trajectory),
against the prior map of the town as mapped (``Sequence.map_source``). With the real KITTI drive
present, its figures for the same configurations come beside them (its world is what it is).
Options restrict any axis, so a slice runs alone.

Each cell is one ``lidarloc bench localize`` directory (``cells/NAME/``: runs, per-run CSV,
summary.json, report.md) run with the same machinery (:mod:`.localize`): replay clock, recorded
odometry, one pool of worker processes for every run of every cell, resume of finished runs.
The cache is filled before the runs: the map, lookup table and pyramid once in this process
(shared by every cell: the map is the mapping drive's, whatever the world), then each world's
scans and odometry in the workers (one task per world, shared by its configurations).

Figures per cell (:mod:`.robustness_report`): A–E (median and share of runs that met each),
success (localized and within 5 m of the truth from then to the end of the drive, share of
runs), the position RMSE from the rule's first firing on (median over runs), consistency_2sigma
(median over runs), the false-fire rate (share of runs) and the PF step's median latency.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from pathlib import Path

from rich.console import Console

from ...core.config import TOWN_SENSORS, Config, load_config
from ...core.errors import LidarlocError
from ...core.sequences.factory import SourceSpec
from ..console import progress_bar, stop_signals_like_ctrl_c
from ..sweep.bookkeeping import Run
from ..sweep.cluster import check_address
from ..sweep.executor import execute
from ..sweep.world import ensure_world, mark_ready
from .common import DATA_ENV, REAL_DRIVE, REAL_DRIVE_DATE, data_dir, real_drive, require_town
from .localize import (
    Plan,
    check_runs,
    code_fingerprint,
    numba_threads_for,
    prepare_cache,
    prepare_one,
    run_one,
    run_tasks,
)

# The full matrix (each axis restricted by its option).
CHANGES = (0.0, 0.3, 0.6)
TRAFFIC = (False, True)
SENSORS = ("hdl64e", "vlp16", "os1-128")
SKEW = (False, True)
# configuration name → (preset, overrides over it)
CONFIGS: dict[str, tuple[str, tuple[str, ...]]] = {
    "paper": ("paper", ()),
    "default": ("default", ()),
    "no-S2M": ("default", ("s2m.enabled=false",)),
}
# The entries the matrix sets: --set may not set them (the axis options restrict them instead).
MATRIX_KEYS = {
    "town.changes": "--changes",
    "town.traffic": "--traffic",
    "town.sensor": "--sensors",
    "town.skew": "--skew",
    "s2m.enabled": "--configs",
}
DEFAULT_SCANS = 300
# Wall seconds per scan of one worker, per configuration, for the estimate printed before the
# start (the progress bar's remaining time then follows the real pace): runs of the town's first
# 300 scans, two at a time, on the reference 2-core machine (the full matrix at 1 run per cell:
# default 44 s a run, S2M searching the whole mapping drive's map until localized; paper 67 s, its
# PF summing every point; no-S2M 4 s). A world's preparation (simulating its scans, KISS-ICP)
# took 33 s for 300 scans; the one-time map build (~2.5 min for the default town) is not counted.
RUN_S_PER_SCAN = {"paper": 0.22, "default": 0.15, "no-S2M": 0.014}
PREPARE_S_PER_SCAN = 0.11


# --------------------------------------------------------------------------------- the matrix
@dataclass(frozen=True)
class World:
    """What the localized town drive meets: changes since mapping, traffic, sensor, skew."""

    changes: float
    traffic: bool
    sensor: str
    skew: bool

    def overrides(self) -> list[str]:
        return [
            f"town.changes={self.changes:g}",
            f"town.traffic={str(self.traffic).lower()}",
            f"town.sensor={self.sensor}",
            f"town.skew={str(self.skew).lower()}",
        ]

    @property
    def name(self) -> str:
        return f"changes{self.changes:g}-traffic-{_onoff(self.traffic)}-{self.sensor}-skew-{_onoff(self.skew)}"

    @property
    def label(self) -> str:
        return f"changes {self.changes:g} · traffic {_onoff(self.traffic)} · {self.sensor} · skew {_onoff(self.skew)}"


@dataclass(frozen=True)
class Cell:
    """One configuration in one world (``world`` None: the real drive)."""

    world: World | None
    config: str

    @property
    def name(self) -> str:
        return f"{'real' if self.world is None else self.world.name}-{self.config}"

    @property
    def preset(self) -> str:
        return CONFIGS[self.config][0]

    def overrides(self) -> list[str]:
        return list(CONFIGS[self.config][1]) + ([] if self.world is None else self.world.overrides())


@dataclass(frozen=True)
class Matrix:
    """The axes of the matrix to run (each a subset of, or beyond, the full matrix's)."""

    changes: tuple[float, ...] = CHANGES
    traffic: tuple[bool, ...] = TRAFFIC
    sensors: tuple[str, ...] = SENSORS
    skew: tuple[bool, ...] = SKEW
    configs: tuple[str, ...] = tuple(CONFIGS)

    def worlds(self) -> list[World]:
        return [World(c, t, s, k) for c in self.changes for t in self.traffic for s in self.sensors for k in self.skew]

    def cells(self, real: bool) -> list[Cell]:
        cells = [Cell(w, c) for w in self.worlds() for c in self.configs]
        return cells + ([Cell(None, c) for c in self.configs] if real else [])

    def to_dict(self) -> dict:
        return {
            "changes": list(self.changes),
            "traffic": [_onoff(t) for t in self.traffic],
            "sensors": list(self.sensors),
            "skew": [_onoff(k) for k in self.skew],
            "configs": list(self.configs),
        }


def _onoff(flag: bool) -> str:
    return "on" if flag else "off"


def _items(text: str, option: str) -> list[str]:
    items = [t.strip() for t in str(text).split(",") if t.strip()]
    if not items:
        raise LidarlocError(f"{option}: give at least one value (comma-separated)")
    return list(dict.fromkeys(items))  # in the order given, each once


def _share(item: str) -> float:
    try:
        value = float(item)
    except ValueError:
        value = float("nan")
    if not 0.0 <= value <= 1.0:
        raise LidarlocError(f"--changes: '{item}' is not a share in [0, 1]")
    return value


def _flag(item: str, option: str) -> bool:
    if item.lower() not in ("on", "off"):
        raise LidarlocError(f"{option}: '{item}' is not on or off")
    return item.lower() == "on"


def _sensor(item: str) -> str:
    if item.lower() not in TOWN_SENSORS:
        raise LidarlocError(f"--sensors: unknown sensor '{item}' (choose from {','.join(TOWN_SENSORS)})")
    return item.lower()


def _config(item: str) -> str:
    names = {n.lower(): n for n in CONFIGS}
    if item.lower() not in names:
        raise LidarlocError(f"--configs: unknown configuration '{item}' (choose from {','.join(CONFIGS)})")
    return names[item.lower()]


def parse_matrix(changes: str, traffic: str, sensors: str, skew: str, configs: str) -> Matrix:
    """The matrix the axis options name (comma-separated values); a bad value is one line."""
    return Matrix(
        changes=tuple(dict.fromkeys(_share(i) for i in _items(changes, "--changes"))),
        traffic=tuple(dict.fromkeys(_flag(i, "--traffic") for i in _items(traffic, "--traffic"))),
        sensors=tuple(dict.fromkeys(_sensor(i) for i in _items(sensors, "--sensors"))),
        skew=tuple(dict.fromkeys(_flag(i, "--skew") for i in _items(skew, "--skew"))),
        configs=tuple(dict.fromkeys(_config(i) for i in _items(configs, "--configs"))),
    )


def check_overrides(overrides: list[str] | None) -> None:
    """``--set`` may not set what the matrix sets."""
    for item in overrides or []:
        key = item.split("=", 1)[0].strip()
        if key in MATRIX_KEYS:
            raise LidarlocError(f"--set {key}: the matrix sets it; restrict the matrix with {MATRIX_KEYS[key]}")


def cell_config(cell: Cell, config: Path | None, overrides: list[str] | None) -> Config:
    """A cell's configuration: its preset, the user's ``--config`` and ``--set``, then the cell's
    own entries (its world, S2M off for no-S2M); with the recorded odometry, as ``lidarloc bench
    localize`` runs (the same numbers, computed once per world)."""
    return load_config(
        config, ["localize.recorded_odometry=true", *(overrides or []), *cell.overrides()], preset=cell.preset
    )


# --------------------------------------------------------------------------------- running
def estimate_s(plans: dict, worlds_to_prepare: int, scans: int, workers: int) -> float:
    """Rough wall seconds of what is left (the module's constants; ``plans`` by cell name, which
    ends in the configuration's; the real drive's runs, which may be shorter, counted at ``scans``)."""
    run_s = sum(
        len(p.todo) * scans * RUN_S_PER_SCAN[next(c for c in CONFIGS if name.endswith("-" + c))]
        for name, p in plans.items()
    )
    return (run_s + worlds_to_prepare * scans * PREPARE_S_PER_SCAN) / workers


def _n(count: int, noun: str) -> str:
    return f"{count} {noun}{'' if count == 1 else 's'}"


def format_duration(seconds: float) -> str:
    minutes = int(round(seconds / 60.0))
    if minutes < 1:
        return "under a minute"
    hours, minutes = divmod(minutes, 60)
    return f"{hours} h {minutes:02d} min" if hours else f"{minutes} min"


def run_robustness(
    town: SourceSpec,
    config: Path | None,
    overrides: list[str] | None,
    matrix: Matrix,
    runs: int,
    workers: int,
    out_dir: Path,
    real: bool | None = None,
    cache_root: Path | None = None,
    console: Console | None = None,
    record: bool = False,
    ray: str | None = None,
) -> dict:
    """Run the ``matrix`` (``runs`` seeds per cell) on the town ``town`` and, with ``real`` (None:
    where its data is present), on the real drive; write the cells' directories and the report
    into ``out_dir``; returns the summary (summary.json). The runs go through the sweep's executor:
    a local process pool, or Ray Tune trials with ``ray`` (:mod:`lidarloc.app.sweep.cluster`)."""
    from .robustness_report import write_cell_table

    console = console or Console(stderr=True)
    stop_signals_like_ctrl_c()  # from the start: preparing the cache can take minutes
    check_runs(runs, workers)
    check_address(ray)
    require_town(town, "robustness", "the built-in town's drive in a changed world")
    check_overrides(overrides)
    if town.scans is None:
        town = replace(town, scans=DEFAULT_SCANS)
    real_spec = real_drive(town.scans) if real is not False else None
    if real and real_spec is None:
        raise LidarlocError(
            f"--real: KITTI raw {REAL_DRIVE_DATE} drive {REAL_DRIVE} not found under "
            f"{data_dir() / 'kitti_raw'} (set ${DATA_ENV}), or use --no-real"
        )
    cells = matrix.cells(real=real_spec is not None)
    configs = {c.name: cell_config(c, config, overrides) for c in cells}
    fingerprint = code_fingerprint()
    out_dir = Path(out_dir)
    plans = {
        c.name: Plan(
            out_dir / "cells" / c.name,
            town if c.world is not None else real_spec,
            configs[c.name],
            runs,
            c.preset,
            fingerprint,
            record=record,
        )
        for c in cells
    }
    todo_cells = [c for c in cells if plans[c.name].todo]
    worlds = list(dict.fromkeys(c.world for c in todo_cells if c.world is not None))
    total = sum(len(p.todo) for p in plans.values())
    console.print(
        f"robustness: {_n(len(cells), 'cell')} × {_n(runs, 'run')} of up to {town.scans} scans "
        f"({total} to do, {len(cells) * runs - total} resumed): estimated "
        f"{format_duration(estimate_s(plans, len(worlds), town.scans, workers))} on {_n(workers, 'worker')}",
        highlight=False,
        soft_wrap=True,
    )
    if real is None and real_spec is None:
        console.print("robustness: the real KITTI drive was not found: town only", highlight=False, soft_wrap=True)
    cache = str(cache_root) if cache_root else None
    threads = numba_threads_for(workers)
    t0 = time.perf_counter()
    _prepare(todo_cells, plans, worlds, cache_root, cache, workers, threads)
    runs_ = cell_runs(cells, plans, runs, cache, threads)

    def done(run, summary):
        name, seed = run.point
        plan = plans[name]
        plan.summaries[seed] = summary
        if len(plan.summaries) == plan.runs:
            plan.report(plots=False)  # a finished cell is readable while others run

    axes = {"cell": [c.name for c in cells], "seed": list(range(runs))}
    tally = execute(
        run_one,
        axes,
        runs_,
        workers,
        on_done=done,
        label=f"robustness: {len(cells)} cells",
        ray=ray,
        ray_dir=out_dir / "ray",
        console=console,
    )
    if tally.interrupted or tally.failed:
        raise LidarlocError(
            f"robustness: {len(tally.failed)} runs failed"
            + (
                f" (first: {next(iter(tally.failed.items()))[0]}: {next(iter(tally.failed.values()))})"
                if tally.failed
                else ""
            )
            + ("; interrupted" if tally.interrupted else "")
            + f"; run the same command again to resume ({tally.kept + tally.done} of {tally.total} done)"
        )
    aggs = {name: plan.report(plots=False) for name, plan in plans.items()}
    return write_cell_table(out_dir, cells, aggs, matrix, town, real_spec, runs, time.perf_counter() - t0)


def cell_runs(cells: list[Cell], plans: dict, runs: int, cache: str | None, threads: int) -> list[Run]:
    """One executor Run per cell × seed (the finished ones too: the executor keeps them), each
    with its world made sure of on the machine that runs it (a Ray cluster's node without the
    cache builds it there, once)."""
    out = []
    for cell in cells:
        plan = plans[cell.name]
        for seed in range(runs):
            run_dir = str(plan.out_dir / "runs" / f"seed_{seed:03d}")
            args = (plan.spec_d, plan.cfg_d, seed, cache, run_dir, threads, plan.preset, plan.record)
            out.append(
                Run(
                    point=(cell.name, seed),
                    label=f"{cell.name} seed {seed}",
                    run_dir=run_dir,
                    args=args,
                    before=(ensure_world, (plan.spec_d, plan.cfg_d, cache, threads)),
                )
            )
    return out


def _prepare(
    todo_cells: list[Cell],
    plans: dict,
    worlds: list[World],
    cache_root: Path | None,
    cache: str | None,
    workers: int,
    threads: int,
) -> None:
    """Fill the cache for the cells still to run. Here: the shared map, lookup table and pyramid
    (with the first world's scans and odometry) for each configuration, and the real drive's;
    then every other world's scans and odometry in the workers, one task per world."""
    first_world = worlds[0] if worlds else None
    for cell in todo_cells:
        if cell.world is None or cell.world == first_world:
            plan = plans[cell.name]
            prepare_cache(plan.spec, plan.cfg, cache_root, label=cell.name)
    rest = {w: next(c for c in todo_cells if c.world == w) for w in worlds[1:]}
    if rest:
        with progress_bar() as bar:
            task = bar.add_task("preparing the worlds' scans and odometry", total=len(rest))
            tasks = {w: (plans[c.name].spec_d, plans[c.name].cfg_d, cache, threads) for w, c in rest.items()}
            run_tasks(prepare_one, tasks, workers, lambda key, _: bar.advance(task))
    for cell in todo_cells:  # every cell's world is in this machine's cache now
        mark_ready(plans[cell.name].spec_d, plans[cell.name].cfg_d, cache)

"""The ``lidarloc`` command line (typer). Every command that takes a sequence accepts the same
source options; errors the user can fix print one line on stderr and exit with status 2."""

from __future__ import annotations

import json
import resource
import sys
import time
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from lidarloc.core.errors import LidarlocError

from .options import (CacheOpt, CalibOpt, ConfigOpt, DateOpt, DriveOpt, KittiOdometryOpt, KittiRawOpt, ScansOpt,
                      SequenceOpt, SetOpt, TownSeedOpt, TrajectoryOpt, config_from, source_spec)

app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False,
                  help="LiDAR-only localization in a prior 3D map: scan-matching particle filter with a live viewer.")
map_app = typer.Typer(no_args_is_help=True, help="Build and inspect prior maps.")
bench_app = typer.Typer(no_args_is_help=True, help="Benchmarks behind BENCHMARKS.md.")
app.add_typer(map_app, name="map")
app.add_typer(bench_app, name="bench")

err = Console(stderr=True)


def progress_bar(transient: bool = True) -> Progress:
    return Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                    TimeRemainingColumn(), console=err, transient=transient)


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # kB on Linux


def emit_json(data: dict) -> None:
    typer.echo(json.dumps(data, indent=2, default=float))


# ------------------------------------------------------------------------------------------ map
@map_app.command("build")
def map_build(
    out: Annotated[Optional[Path], typer.Option("--out", help="Cache directory to build into (default: the cache).")] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print a JSON summary on stdout.")] = False,
    kitti_odometry: KittiOdometryOpt = None, sequence: SequenceOpt = None, kitti_raw: KittiRawOpt = None,
    date: DateOpt = None, drive: DriveOpt = None, town_seed: TownSeedOpt = 0, trajectory: TrajectoryOpt = None,
    calib: CalibOpt = None, scans: ScansOpt = None, config: ConfigOpt = None, set_: SetOpt = None,
):
    """Build the prior map of a sequence from its scans and ground-truth poses (and cache it)."""
    from lidarloc.core.mapping import load_or_build_map
    from lidarloc.core.sequences.factory import open_sequence

    cfg = config_from(config, set_)
    seq = open_sequence(source_spec(kitti_odometry, sequence, kitti_raw, date, drive, town_seed, trajectory, calib, scans), cfg)
    t0 = time.perf_counter()
    with progress_bar() as bar:
        task = bar.add_task(f"map of {seq.name}", total=len(seq))
        prior, directory, cached = load_or_build_map(seq, cfg.map, out, progress=lambda i, n: bar.update(task, completed=i))
    summary = {"points": int(len(prior.points)), "points_road_removed": int(len(prior.points_bev)),
               "seconds": round(time.perf_counter() - t0, 3), "peak_rss_mb": round(peak_rss_mb(), 1),
               "cached": cached, "cache_dir": str(directory), "scans": len(seq)}
    if as_json:
        emit_json(summary)
    else:
        err.print(f"map: {summary['points']:,} points, {summary['points_road_removed']:,} after road removal, "
                  f"{summary['seconds']} s ({'from cache' if cached else 'built'}) → {directory}")


# ---------------------------------------------------------------------------------------- synth
@app.command()
def synth(
    out: Annotated[Path, typer.Option("--out", help="Directory to write the KITTI odometry layout into.")],
    sequence_id: Annotated[str, typer.Option("--sequence-id", help="Sequence id to write as.")] = "00",
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace an existing exported sequence.")] = False,
    town_seed: TownSeedOpt = 0, trajectory: TrajectoryOpt = None, calib: CalibOpt = None, scans: ScansOpt = None,
    config: ConfigOpt = None, set_: SetOpt = None,
):
    """Export the built-in town's drive in KITTI odometry layout (velodyne/*.bin, calib, times, poses)."""
    from lidarloc.core.sequences.export import export_kitti_odometry
    from lidarloc.core.sequences.factory import open_sequence

    cfg = config_from(config, set_)
    seq = open_sequence(source_spec(None, None, None, None, None, town_seed, trajectory, calib, scans), cfg)
    with progress_bar() as bar:
        task = bar.add_task(f"scans of {seq.name}", total=len(seq))
        export_kitti_odometry(seq, out, sequence=sequence_id, overwrite=overwrite,
                              progress=lambda i, n: bar.update(task, completed=i))
    err.print(f"wrote {len(seq)} scans to {out}/sequences/{sequence_id}")


# ------------------------------------------------------------------------------------ localize
@app.command()
def run(
    out: Annotated[Path, typer.Option("--out", help="Directory for trajectory, per-scan CSV, events and summary.")],
    seed: Annotated[Optional[int], typer.Option("--seed", min=0, help="Random seed (default: the config's).")] = None,
    clock: Annotated[Optional[str], typer.Option("--clock", help="replay (deterministic) or realtime (default: the config's).")] = None,
    no_s2m: Annotated[bool, typer.Option("--no-s2m", help="Disable scan-to-map matching (plain particle filter).")] = False,
    as_json: Annotated[bool, typer.Option("--json", help="Print the summary JSON on stdout.")] = False,
    kitti_odometry: KittiOdometryOpt = None, sequence: SequenceOpt = None, kitti_raw: KittiRawOpt = None,
    date: DateOpt = None, drive: DriveOpt = None, town_seed: TownSeedOpt = 0, trajectory: TrajectoryOpt = None,
    calib: CalibOpt = None, scans: ScansOpt = None, config: ConfigOpt = None, set_: SetOpt = None, cache: CacheOpt = None,
):
    """Localize headless over a sequence and write results to --out."""
    from .headless import run_headless

    overrides = list(set_ or []) + ([f"localize.clock={clock}"] if clock else []) + (["s2m.enabled=false"] if no_s2m else [])
    cfg = config_from(config, overrides, seed=seed)
    spec = source_spec(kitti_odometry, sequence, kitti_raw, date, drive, town_seed, trajectory, calib, scans)
    summary, interrupted = run_headless(spec, cfg, out, cache_root=cache, console=err)
    if as_json:
        emit_json(summary)
    if interrupted:
        raise typer.Exit(130)


# -------------------------------------------------------------------------------------- viewer
def _serve(spec, cfg, host, port, cache, open_browser):
    from .viewer_main import serve_until_interrupted

    serve_until_interrupted(spec, cfg, host=host, port=port, cache_root=cache, console=err, open_browser=open_browser)


HostOpt = Annotated[str, typer.Option("--host", help="Interface to bind (default loopback only).")]
PortOpt = Annotated[int, typer.Option("--port", help="Port for the viewer.")]


@app.command()
def demo(host: HostOpt = "127.0.0.1", port: PortOpt = 8080, seed: Annotated[Optional[int], typer.Option("--seed", min=0, help="Random seed (default: the config's).")] = None,
         scans: ScansOpt = None, config: ConfigOpt = None, set_: SetOpt = None, cache: CacheOpt = None,
         open_browser: Annotated[bool, typer.Option("--open/--no-open", help="Open a browser tab.")] = False):
    """The live demo on the built-in town: browse to the printed URL."""
    cfg = config_from(config, set_, seed=seed)
    _serve(source_spec(None, None, None, None, None, cfg.town.seed, None, None, scans), cfg, host, port, cache, open_browser)


@app.command()
def view(
    host: HostOpt = "127.0.0.1", port: PortOpt = 8080, seed: Annotated[Optional[int], typer.Option("--seed", min=0, help="Random seed (default: the config's).")] = None,
    kitti_odometry: KittiOdometryOpt = None, sequence: SequenceOpt = None, kitti_raw: KittiRawOpt = None,
    date: DateOpt = None, drive: DriveOpt = None, town_seed: TownSeedOpt = 0, trajectory: TrajectoryOpt = None,
    calib: CalibOpt = None, scans: ScansOpt = None, config: ConfigOpt = None, set_: SetOpt = None, cache: CacheOpt = None,
    open_browser: Annotated[bool, typer.Option("--open/--no-open", help="Open a browser tab.")] = False,
):
    """The live viewer on any sequence source."""
    cfg = config_from(config, set_, seed=seed)
    spec = source_spec(kitti_odometry, sequence, kitti_raw, date, drive, town_seed, trajectory, calib, scans)
    _serve(spec, cfg, host, port, cache, open_browser)


# -------------------------------------------------------------------------------------- benches
@bench_app.command("town")
def bench_town(seed: Annotated[Optional[int], typer.Option("--seed", min=0, help="Random seed (default: the config's).")] = None, as_json: Annotated[bool, typer.Option("--json")] = False):
    """Town generation time and simulated-scan time."""
    from .bench_town import run as run_bench

    emit_json(run_bench(seed=seed))


@bench_app.command("map")
def bench_map(
    data: Annotated[Path, typer.Option("--data", help="Shared data directory (real KITTI).")] = Path("../shared/data"),
    as_json: Annotated[bool, typer.Option("--json")] = False,
):
    """Prior-map build and cache-load times, default town and the real drive (fresh cache)."""
    from .bench_map import run as run_bench

    emit_json(run_bench(data_dir=data))


@bench_app.command("pf")
def bench_pf(
    particles: Annotated[int, typer.Option("--particles")] = 1000,
    data: Annotated[Path, typer.Option("--data", help="Shared data directory (real KITTI).")] = Path("../shared/data"),
    as_json: Annotated[bool, typer.Option("--json")] = False,
):
    """Particle-filter step time and lookup-table cost (issue targets)."""
    from .bench_pf import run as run_bench

    emit_json(run_bench(n_particles=particles, data_dir=data))


@bench_app.command("s2m")
def bench_s2m(
    source: Annotated[str, typer.Option("--source", help="town or kitti_raw")] = "town",
    scans: Annotated[int, typer.Option("--scans")] = 350,
    data: Annotated[Path, typer.Option("--data")] = Path("../shared/data"),
    out: Annotated[Optional[Path], typer.Option("--out", help="Write the RMSE histogram PNG here.")] = None,
    as_json: Annotated[bool, typer.Option("--json")] = False,
):
    """Global/local M3RSM matching: success rate, latency, RMSE (the paper's experiment)."""
    from .bench_s2m import run as run_bench

    emit_json(run_bench(source=source, scans=scans, data_dir=data, out_dir=out))


@bench_app.command("rpe")
def bench_rpe(
    source: Annotated[str, typer.Option("--source", help="town or kitti_raw")] = "town",
    scans: Annotated[int, typer.Option("--scans", min=11)] = 300,
    convergence: Annotated[Optional[list[float]], typer.Option("--convergence", help="KISS-ICP convergence criteria to compare (repeatable).")] = None,
    data: Annotated[Path, typer.Option("--data")] = Path("../shared/data"),
    as_json: Annotated[bool, typer.Option("--json")] = False,
):
    """KISS-ICP odometry: registration time and error against the truth per convergence setting."""
    from .bench_rpe import run as run_bench

    emit_json(run_bench(source=source, scans=scans, data_dir=data,
                        **({"convergences": tuple(convergence)} if convergence else {})))


@bench_app.command("viewer")
def bench_viewer(as_json: Annotated[bool, typer.Option("--json")] = False):
    """Server-side cost of one display update."""
    from .bench_viewer import run as run_bench

    emit_json(run_bench())


@bench_app.command("startup")
def bench_startup(repeats: Annotated[int, typer.Option("--repeats", min=1, help="Cached starts after the first.")] = 3,
                  as_json: Annotated[bool, typer.Option("--json")] = False):
    """Start-up time of `lidarloc demo`: first start (empty cache), then cached starts."""
    from .bench_startup import run as run_bench

    emit_json(run_bench(repeats=repeats))


@bench_app.command("stop")
def bench_stop(repeats: Annotated[int, typer.Option("--repeats", min=1, help="Stops per clock and delay.")] = 3,
               delay: Annotated[Optional[list[float]], typer.Option("--delay", min=0.0, help="Seconds after 'localizing' to press Ctrl-C (repeatable).")] = None,
               cache: CacheOpt = None, as_json: Annotated[bool, typer.Option("--json")] = False):
    """How fast Ctrl-C stops `lidarloc run` on the town, both clocks (target ≤ 2 s)."""
    from .bench_stop import run as run_bench

    emit_json(run_bench(repeats=repeats, cache=None if cache is None else str(cache),
                        **({"delays_s": tuple(delay)} if delay else {})))


@bench_app.command("localize")
def bench_localize(
    runs: Annotated[int, typer.Option("--runs")] = 20,
    workers: Annotated[int, typer.Option("--workers")] = 2,
    out: Annotated[Path, typer.Option("--out")] = Path("out/bench-localize"),
    no_s2m: Annotated[bool, typer.Option("--no-s2m")] = False,
    live_odometry: Annotated[bool, typer.Option(
        "--live-odometry", help="Run KISS-ICP in every run instead of replaying its poses, computed once "
                                "per sequence (the same numbers; only slower).")] = False,
    executor: Annotated[str, typer.Option("--executor", help="process or ray")] = "process",
    address: Annotated[Optional[str], typer.Option("--address", help="Ray cluster address.")] = None,
    as_json: Annotated[bool, typer.Option("--json")] = False,
    kitti_odometry: KittiOdometryOpt = None, sequence: SequenceOpt = None, kitti_raw: KittiRawOpt = None,
    date: DateOpt = None, drive: DriveOpt = None, town_seed: TownSeedOpt = 0, trajectory: TrajectoryOpt = None,
    calib: CalibOpt = None, scans: ScansOpt = None, config: ConfigOpt = None, set_: SetOpt = None, cache: CacheOpt = None,
):
    """Metrics A–E over many seeded runs in parallel workers (the paper's Simulation section)."""
    from .bench_localize import run_bench

    overrides = ([] if live_odometry else ["localize.recorded_odometry=true"]) + list(set_ or []) \
        + (["s2m.enabled=false"] if no_s2m else [])
    cfg = config_from(config, overrides)
    spec = source_spec(kitti_odometry, sequence, kitti_raw, date, drive, town_seed, trajectory, calib, scans)
    summary = run_bench(spec, cfg, runs=runs, workers=workers, out_dir=out, executor=executor, address=address,
                        cache_root=cache, console=err)
    if as_json:
        emit_json(summary)


def main() -> None:
    """Entry point: click's usage errors behave as usual; LidarlocError becomes one line + exit 2."""
    command = typer.main.get_command(app)
    try:
        command.main(prog_name="lidarloc", standalone_mode=True)
    except LidarlocError as exc:
        # plain write: one unwrapped line, no markup interpretation of paths with brackets
        sys.stderr.write(f"lidarloc: error: {exc}\n")
        sys.exit(2)
    except MemoryError:
        sys.stderr.write("lidarloc: error: out of memory\n")
        sys.exit(2)


if __name__ == "__main__":
    main()

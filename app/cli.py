"""The ``lidarloc`` command line (typer). Every command that takes a sequence accepts the same
source options; errors the user can fix print one line on stderr and exit with status 2."""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path
from typing import Annotated, Optional

import typer

from lidarloc.core.errors import LidarlocError

from .bench.common import DATA_ENV, DEFAULT_DATA, REAL_DRIVE, REAL_DRIVE_DATE
from .console import emit_json, err, fail, peak_rss_mb, progress_bar, show_result
from .options import (OWN_DATA, SOURCE_CHOICE, SOURCE_OPTIONS, CacheOpt, ConfigOpt, InitOpt, JsonOpt, WorldOpt,
                      PresetOpt, ScansOpt, SetOpt, config_from, given, open_source,
                      source_spec, with_source)

app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False,
                  help="LiDAR-only localization in a prior 3D map: scan-matching particle filter with a live viewer.")
map_app = typer.Typer(no_args_is_help=True, help="Build and inspect prior maps.")
bench_app = typer.Typer(no_args_is_help=True, help="Benchmarks behind BENCHMARKS.md.")
app.add_typer(map_app, name="map")
app.add_typer(bench_app, name="bench")


# ------------------------------------------------------------------------------------------ map
@map_app.command("build")
@with_source()
def map_build(
    out: Annotated[Optional[Path], typer.Option(
        "--out", help="A .pcd or .ply map file to write (the map, and its road-removed layer beside it as "
                      "NAME_road_removed.pcd/.ply), or a cache directory to build into (default: the cache).")] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print a JSON summary on stdout.")] = False,
    spec=None, preset: PresetOpt = None, config: ConfigOpt = None, set_: SetOpt = None, cache: CacheOpt = None,
):
    """Build the prior map of a sequence from its scans and ground-truth poses (and cache it).

    Any source with ground truth: a KITTI drive, the town, or a recording (--bag/--scans-dir) with --gt."""
    from lidarloc.core.mapfile import WRITE_SUFFIXES, write_map
    from lidarloc.core.mapping import load_or_build_map

    to_file = out is not None and out.suffix.lower() in WRITE_SUFFIXES
    if out is not None and not to_file and out.suffix:
        raise LidarlocError(f"{out}: cannot write a map of this type ({out.suffix}); supported: "
                            f"{', '.join(WRITE_SUFFIXES)} (or a cache directory)")
    cfg = config_from(config, set_, preset=preset)
    # the map of a source is its whole mapping drive (--scans N plays N scans inside it)
    seq = open_source(spec, cfg).map_source
    surveyed = getattr(seq, "delivers_map", False)      # a generated city's survey map
    if not surveyed and (not hasattr(seq, "poses") or not seq.has_poses):
        raise LidarlocError(f"{seq.name}: no ground-truth poses to fuse the scans with (give --gt)")
    t0 = time.perf_counter()
    with progress_bar() as bar:
        task = bar.add_task(f"map of {seq.name}", total=None if surveyed else len(seq))
        prior, directory, cached = load_or_build_map(seq, cfg.map, cache if to_file else out,
                                                     progress=lambda i, n: bar.update(task, completed=i, total=n))
    summary = {"points": int(len(prior.points)), "points_road_removed": int(len(prior.points_bev)),
               "seconds": round(time.perf_counter() - t0, 3), "peak_rss_mb": round(peak_rss_mb(), 1),
               "cached": cached, "cache_dir": str(directory), "scans": 0 if surveyed else len(seq)}
    if to_file:
        road_removed = road_removed_path(out)
        origin = prior.origin if prior.origin.any() else None
        write_map(out, prior.points, origin=origin)
        write_map(road_removed, prior.points_bev, origin=origin)
        summary.update(out=str(out), out_road_removed=str(road_removed))
    if as_json:
        emit_json(summary)
    else:
        where = f"{out} and {summary['out_road_removed']}" if to_file else str(directory)
        err.print(f"map: {summary['points']:,} points, {summary['points_road_removed']:,} after road removal, "
                  f"{summary['seconds']} s ({'from cache' if cached else 'built'}) → {where}",
                  markup=False, highlight=False, soft_wrap=True)


def road_removed_path(out: Path) -> Path:
    """Where ``map build --out FILE`` writes the road-removed layer: beside FILE, ``NAME_road_removed``."""
    return out.with_name(f"{out.stem}_road_removed{out.suffix}")


@map_app.command("info")
def map_info(
    file: Annotated[Path, typer.Argument(help="Map file: .pcd, .ply, .las, .laz, .npy or .npz.", show_default=False)],
    as_json: JsonOpt = False,
):
    """Points, extent and origin (in the file's frame) and density of a point-cloud map file."""
    from lidarloc.core.mapfile import describe_map, map_info_lines, read_map

    with progress_bar() as bar:
        task = bar.add_task(f"reading {file.name}", total=1)
        cloud = read_map(file, progress=lambda done, total: bar.update(task, completed=done, total=total))
    info = describe_map(cloud)
    if as_json:
        emit_json(info)
    else:
        err.print("\n".join(map_info_lines(info)), markup=False, highlight=False, soft_wrap=True)


@map_app.command("export")
@with_source()
def map_export(
    out: Annotated[Path, typer.Option("--out", help="Map file to write: .pcd or .ply (binary, x y z).", show_default=False)],
    as_json: Annotated[bool, typer.Option("--json", help="Print a JSON summary on stdout.")] = False,
    spec=None, preset: PresetOpt = None, config: ConfigOpt = None, set_: SetOpt = None,
    cache: CacheOpt = None,
):
    """Write a source's prior map (built or from the cache) as a .pcd or .ply file.

    The map is written in the source's frame: a map read from a georeferenced file goes back to its own coordinates, as float64."""
    from lidarloc.core.mapfile import WRITE_SUFFIXES, write_map
    from lidarloc.core.mapping import load_or_build_map

    if out.suffix.lower() not in WRITE_SUFFIXES:     # before building a map that cannot be written
        raise LidarlocError(f"{out}: cannot write a map of this type ({out.suffix or 'no extension'}); "
                            f"supported: {', '.join(WRITE_SUFFIXES)}")
    cfg = config_from(config, set_, preset=preset)
    seq = open_source(spec, cfg).map_source
    with progress_bar() as bar:
        task = bar.add_task(f"map of {seq.name}", total=None)
        prior = load_or_build_map(seq, cfg.map, cache, progress=lambda i, n: bar.update(task, completed=i, total=n),
                                  road_removal=False).value
    origin = prior.origin if prior.origin.any() else None
    write_map(out, prior.points, origin=origin)
    summary = {"points": int(len(prior.points)), "out": str(out), "origin_m": [float(v) for v in prior.origin]}
    if as_json:
        emit_json(summary)
    else:
        err.print(f"wrote {summary['points']:,} map points to {out}", markup=False, highlight=False)


# ---------------------------------------------------------------------------------------- synth
@app.command()
@with_source(exclude=("kitti_odometry", "sequence", "kitti_raw", "date", "drive") + OWN_DATA)
def synth(
    out: Annotated[Path, typer.Option("--out", help="Directory to write the KITTI odometry layout into.")],
    sequence_id: Annotated[str, typer.Option("--sequence-id", help="Sequence id to write as.")] = "00",
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace an existing exported sequence.")] = False,
    spec=None, preset: PresetOpt = None, config: ConfigOpt = None, set_: SetOpt = None,
):
    """Export the built-in town's drive in KITTI odometry layout (velodyne/*.bin, calib, times, poses)."""
    from lidarloc.core.sequences.export import export_kitti_odometry
    from lidarloc.core.sequences.factory import open_sequence

    cfg = config_from(config, set_, preset=preset)
    seq = open_sequence(spec, cfg)
    with progress_bar() as bar:
        task = bar.add_task(f"scans of {seq.name}", total=len(seq))
        export_kitti_odometry(seq, out, sequence=sequence_id, overwrite=overwrite,
                              progress=lambda i, n: bar.update(task, completed=i))
    err.print(f"wrote {len(seq)} scans to {out}/sequences/{sequence_id}")


# ------------------------------------------------------------------------------------ localize
@app.command()
@with_source()
def run(
    ctx: typer.Context,
    out: Annotated[Path, typer.Option("--out", help="Directory for trajectory, per-scan CSV, events, summary and the recording.")],
    seed: Annotated[Optional[int], typer.Option("--seed", min=0, help="Random seed (default: the config's).")] = None,
    clock: Annotated[Optional[str], typer.Option("--clock", help="replay (deterministic) or realtime (default: the config's).")] = None,
    no_s2m: Annotated[bool, typer.Option("--no-s2m", help="Disable scan-to-map matching (plain particle filter).")] = False,
    no_record: Annotated[bool, typer.Option("--no-record", help="Do not record the run's steps into OUT/recording/ (view --run, --branch, compare and export read it).")] = False,
    branch: Annotated[Optional[str], typer.Option("--branch", metavar="RUN_DIR:STEP", help="Continue the recorded run in RUN_DIR from the filter's exact state after its step STEP (0-based), with --set changes, into --out; source and configuration come from the recording.")] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print the summary JSON on stdout.")] = False,
    init: InitOpt = None, spec=None, preset: PresetOpt = None, config: ConfigOpt = None, set_: SetOpt = None, cache: CacheOpt = None,
):
    """Localize headless over a sequence and write results to --out (recorded: scrub it with view --run)."""
    overrides = list(set_ or []) + ([f"localize.clock={clock}"] if clock else []) + (["s2m.enabled=false"] if no_s2m else [])
    if branch is not None:
        if given(ctx, SOURCE_OPTIONS) or config or preset or init:
            raise LidarlocError("--branch takes its source and configuration from the recording; give changes with --set")
        from .branch import parse_branch, run_branch

        run_dir, step = parse_branch(branch)
        overrides += [f"seed={seed}"] if seed is not None else []
        summary, interrupted = run_branch(run_dir, step, overrides, out, cache_root=cache, console=err,
                                          record=not no_record)
    else:
        from .headless import run_headless

        cfg = config_from(config, overrides, seed=seed, preset=preset)
        summary, interrupted = run_headless(replace(spec, init=init), cfg, out, cache_root=cache, console=err,
                                            preset=preset, record=not no_record)
    if as_json:
        emit_json(summary)
    if interrupted:
        raise typer.Exit(130)


@app.command()
@with_source()
def inspect(
    scan: Annotated[int, typer.Option("--scan", min=0, help="The scan to inspect (0-based); the run replays up to it.")],
    out: Annotated[Path, typer.Option("--out", help="Directory for the likelihood surfaces (PNG + .npy), residuals.png and inspect.json.")],
    seed: Annotated[Optional[int], typer.Option("--seed", min=0, help="Random seed (default: the config's).")] = None,
    best_over_yaw: Annotated[bool, typer.Option("--best-over-yaw", help="Each surface cell: the best of the yaws within ±10° in 2° steps, not the pose's yaw alone.")] = False,
    as_json: Annotated[bool, typer.Option("--json", help="Print inspect.json on stdout too.")] = False,
    init: InitOpt = None, spec=None, preset: PresetOpt = None, config: ConfigOpt = None, set_: SetOpt = None, cache: CacheOpt = None,
):
    """Replay a run to one scan and write why the filter is where it is: the likelihood surface
    around the estimate and around the truth, the scan's residuals to the map, and a JSON summary."""
    from .inspect import run_inspect

    cfg = config_from(config, set_, seed=seed, preset=preset)
    result = run_inspect(replace(spec, init=init), cfg, scan, out, cache_root=cache, console=err, best_over_yaw=best_over_yaw)
    if as_json:
        emit_json(result)


# ------------------------------------------------------------------------------ runs: compare, share
@app.command("compare")
def compare(
    runs: Annotated[list[Path], typer.Argument(help="Two or more run folders (lidarloc run, the viewer, a branch, a benchmark run).")],
    out: Annotated[Optional[Path], typer.Option("--out", help="Write the overlay plot (trajectories; error, std and N_eff against the step) to this PNG.")] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print the figures as JSON on stdout instead of the table.")] = False,
):
    """The summary figures of two or more runs side by side (A–E, success, RMSE, consistency, false fires, PF latency, scans) and an overlay plot for papers."""
    from .compare import compare_runs

    compare_runs(runs, out, as_json=as_json, console=err)


@app.command("export")
def export(
    run: Annotated[Path, typer.Argument(help="A recorded run folder (with recording/).")],
    out: Annotated[Path, typer.Option("--out", help="NAME: writes NAME.viser and the folder NAME/ (open NAME/index.html in a browser; no server needed).")],
    no_scans: Annotated[bool, typer.Option("--no-scans", help="Leave each step's scan out (a smaller file).")] = False,
    as_json: JsonOpt = False,
    cache: CacheOpt = None,
):
    """Share a recorded run: a .viser recording of its scene and a static web folder that plays it in any browser from disk (no Python, no server)."""
    from .export import export_run

    result = export_run(run, out, console=err, cache_root=cache, scans=not no_scans)
    if as_json:
        emit_json(result)


# -------------------------------------------------------------------------------------- viewer
def _serve(spec, cfg, host, port, cache, open_browser, autoplay=False, record_dir=None, preset=None, record=True):
    from .viewer.serve import serve_until_interrupted

    serve_until_interrupted(spec, cfg, host=host, port=port, cache_root=cache, console=err, open_browser=open_browser,
                            autoplay=autoplay, record_dir=record_dir, preset=preset, record=record)


HostOpt = Annotated[str, typer.Option("--host", help="Interface to bind (default loopback only).")]
PortOpt = Annotated[int, typer.Option("--port", help="Port for the viewer.")]
AutoplayOpt = Annotated[bool, typer.Option(
    "--autoplay", help="Start playing as soon as the localizer is ready (default: when the first browser tab opens).")]
RecordDirOpt = Annotated[Optional[Path], typer.Option(
    "--record-dir", help="Folder for the runs the viewer plays, each start, restart and branch in a folder of its own "
                         "(default: a new runs/<date-time> folder under the cache directory).")]
NoRecordViewOpt = Annotated[bool, typer.Option(
    "--no-record", help="Do not record what the viewer plays (no disk use; the timeline and Branch from here are then off).")]
RunOpt = Annotated[Optional[list[Path]], typer.Option(
    "--run", help="Open a recorded run folder instead of localizing (repeat once to compare two runs of the same "
                  "source side by side); the map and scans come from the source the run names.")]


@app.command()
def demo(host: HostOpt = "127.0.0.1", port: PortOpt = 8080, seed: Annotated[Optional[int], typer.Option("--seed", min=0, help="Random seed (default: the config's).")] = None,
         scans: ScansOpt = None, preset: PresetOpt = None, config: ConfigOpt = None, set_: SetOpt = None, cache: CacheOpt = None,
         open_browser: Annotated[bool, typer.Option("--open/--no-open", help="Open a browser tab.")] = False,
         autoplay: AutoplayOpt = False, record_dir: RecordDirOpt = None, no_record: NoRecordViewOpt = False):
    """The live demo on the built-in town: browse to the printed URL."""
    cfg = config_from(config, set_, seed=seed, preset=preset)
    _serve(source_spec(town_seed=cfg.town.seed, scans=scans), cfg, host, port, cache, open_browser, autoplay,
           record_dir=record_dir, preset=preset, record=not no_record)


@app.command()
@with_source()
def view(
    host: HostOpt = "127.0.0.1", port: PortOpt = 8080, seed: Annotated[Optional[int], typer.Option("--seed", min=0, help="Random seed (default: the config's).")] = None,
    init: InitOpt = None, spec=None, preset: PresetOpt = None, config: ConfigOpt = None, set_: SetOpt = None, cache: CacheOpt = None,
    open_browser: Annotated[bool, typer.Option("--open/--no-open", help="Open a browser tab.")] = False,
    autoplay: AutoplayOpt = False, record_dir: RecordDirOpt = None, no_record: NoRecordViewOpt = False,
    run: RunOpt = None,
):
    """The live viewer on any sequence source, or on recorded runs (--run DIR, twice to compare)."""
    if run:
        from .viewer.runs import serve_runs

        serve_runs(run, host=host, port=port, cache_root=cache, open_browser=open_browser, console=err)
        return
    cfg = config_from(config, set_, seed=seed, preset=preset)
    _serve(replace(spec, init=init), cfg, host, port, cache, open_browser, autoplay, record_dir=record_dir,
           preset=preset, record=not no_record)


# -------------------------------------------------------------------------------------- benches
# Every benchmark takes the source options and --config/--set; --json prints its result as JSON
# on stdout, else the result is listed on stderr.
def _result(name: str, result: dict, as_json: bool) -> None:
    if as_json:
        emit_json(result)
    else:
        show_result(f"lidarloc bench {name}", result)


def _real_drive_unless_given(ctx: typer.Context, spec, bench: str):
    """``spec`` when a source was chosen, else the real KITTI drive (with ``spec``'s --scans and --map)."""
    from .bench.common import require_real_drive

    if given(ctx, SOURCE_CHOICE):
        return spec
    return replace(require_real_drive(bench, spec.scans), map=spec.map)


SeedOpt = Annotated[Optional[int], typer.Option("--seed", min=0, help="Random seed (default: the config's).")]
_MAP_PANEL = "Source (default: the built-in town and the real KITTI drive)"
_PF_PANEL = f"Source (default: KITTI raw {REAL_DRIVE_DATE} drive {REAL_DRIVE} in ${DATA_ENV} or {DEFAULT_DATA})"
_VIEWER_PANEL = "Source (none: the inputs are synthetic)"


@bench_app.command("town")
@with_source(exclude=OWN_DATA)
def bench_town(
    as_json: JsonOpt = False,
    spec=None, preset: PresetOpt = None, config: ConfigOpt = None, set_: SetOpt = None,
):
    """Town generation time and simulated-scan time.

    The built-in town only: --kitti-odometry and --kitti-raw do not apply."""
    from .bench.town import run as run_bench

    cfg = config_from(config, set_, preset=preset)
    _result("town", run_bench(spec, cfg), as_json)


@bench_app.command("map")
@with_source(_MAP_PANEL)
def bench_map(
    ctx: typer.Context, as_json: JsonOpt = False,
    spec=None, preset: PresetOpt = None, config: ConfigOpt = None, set_: SetOpt = None,
):
    """Prior-map build and cache-load times, default town and the real drive (fresh cache).

    With a source option, that source's map only."""
    from .bench.common import config_args
    from .bench.map import default_sources, run as run_bench, source_name

    config_from(config, set_, preset=preset)      # a bad config fails here, not in the first child process
    sources = {source_name(spec): spec} if given(ctx, SOURCE_CHOICE + ("map",)) else default_sources(spec)
    _result("map", run_bench(sources, config_args(config, set_, preset)), as_json)


@bench_app.command("mapfile")
def bench_mapfile(
    points: Annotated[int, typer.Option("--points", min=1000, help="Points of the generated map file.")] = 50_000_000,
    as_json: JsonOpt = False,
):
    """Loading a large .pcd map and building its lookup table (target ≤ 2 min, ≤ 6 GB at 50 M points).

    The map is generated in a temporary directory; reading, voxelizing and the lookup table are timed in a fresh process, then road removal apart."""
    from .bench.mapfile import run as run_bench

    _result("mapfile", run_bench(points), as_json)


@bench_app.command("bag")
@with_source(_PF_PANEL)
def bench_bag(
    ctx: typer.Context,
    total: Annotated[int, typer.Option("--total", min=1, help="Scans in the bag (the source's scans, repeated).")] = 300,
    storage: Annotated[str, typer.Option("--storage", help="Bag kind: mcap, sqlite3 (ROS 2) or ros1.")] = "mcap",
    repeats: Annotated[int, typer.Option("--repeats", min=1, help="Times the whole bag is read (median).")] = 3,
    as_json: JsonOpt = False,
    spec=None, preset: PresetOpt = None, config: ConfigOpt = None, set_: SetOpt = None,
):
    """Reading scans from a bag: a PointCloud2 bag of the source's scans, written in a temporary
    directory, opened (index) and read scan by scan (decode); target ≥ 200 scans/s.

    Default source: the real KITTI raw drive (64-beam scans); --town-seed N for the town."""
    from .bench.bag import run as run_bench

    cfg = config_from(config, set_, preset=preset)
    spec = _real_drive_unless_given(ctx, spec, "bag")
    _result("bag", run_bench(spec, cfg, total=total, storage=storage, repeats=repeats), as_json)


@bench_app.command("pf")
@with_source(_PF_PANEL)
def bench_pf(
    ctx: typer.Context,
    particles: Annotated[Optional[int], typer.Option("--particles", min=1, help="Particles (default: the config's).")] = None,
    seed: SeedOpt = None,
    big_map: Annotated[bool, typer.Option("--big-map/--no-big-map", help="Time the lookup table of a KITTI-05-sized synthetic map.")] = True,
    town_lookup: Annotated[bool, typer.Option("--town/--no-town", help="Time the lookup table of the default town's map.")] = True,
    as_json: JsonOpt = False,
    spec=None, preset: PresetOpt = None, config: ConfigOpt = None, set_: SetOpt = None,
):
    """Particle-filter step time and lookup-table cost, against their targets.

    Default source: the real KITTI raw drive; --town-seed N for the town."""
    from .bench.pf import run as run_bench

    cfg = config_from(config, set_, seed=seed, preset=preset)
    if particles is not None:
        cfg.pf.n_particles = particles
    spec = _real_drive_unless_given(ctx, spec, "pf")
    _result("pf", run_bench(spec, cfg, big_map=big_map, town=town_lookup), as_json)


@bench_app.command("surface")
@with_source(_PF_PANEL)
def bench_surface(
    ctx: typer.Context,
    samples: Annotated[int, typer.Option("--samples", min=1, help="Scans to time, spread over the sequence.")] = 10,
    repeats: Annotated[int, typer.Option("--repeats", min=1, help="Surfaces per scan, each around another offset of the truth.")] = 3,
    seed: SeedOpt = None,
    as_json: JsonOpt = False,
    spec=None, preset: PresetOpt = None, config: ConfigOpt = None, set_: SetOpt = None,
):
    """The viewer's likelihood surface: time of an 81 × 81 grid (target ≤ 150 ms) and its maximum's error.

    Default source: the real KITTI raw drive; --town-seed N for the town."""
    from .bench.surface import run as run_bench

    cfg = config_from(config, set_, seed=seed, preset=preset)
    spec = _real_drive_unless_given(ctx, spec, "surface")
    _result("surface", run_bench(spec, cfg, scans=samples, repeats=repeats), as_json)


def _recorded_unless(run_dir: Path | None, spec, cfg):
    """(spec, the sequence to record first): none with --run, else the source's first 1000 scans
    unless --scans says otherwise."""
    if run_dir is not None:
        return spec, None
    spec = replace(spec, scans=1000 if spec.scans is None else spec.scans)
    return spec, open_source(spec, cfg, err)


@bench_app.command("record")
@with_source()
def bench_record(
    particles: Annotated[Optional[int], typer.Option("--particles", min=1, help="Particles (default: the config's).")] = None,
    seed: SeedOpt = None,
    as_json: JsonOpt = False,
    spec=None, preset: PresetOpt = None, config: ConfigOpt = None, set_: SetOpt = None, cache: CacheOpt = None,
):
    """What recording a run costs (≤ 5 % of the PF step, ≤ 60 MB per 1000 scans at 1000
    particles) and how fast it opens again (≤ 3 s for 1000 scans).

    Records the town's first 1000 scans unless the source options say otherwise."""
    from .bench.record import run as run_bench

    cfg = config_from(config, set_, seed=seed, preset=preset)
    if particles is not None:
        cfg.pf.n_particles = particles
    spec, seq = _recorded_unless(None, spec, cfg)
    with progress_bar() as bar:
        task = bar.add_task("recording", total=len(seq))
        result = run_bench(spec, seq, cfg, cache_root=cache, progress=lambda i, n: bar.update(task, completed=i))
    _result("record", result, as_json)


@bench_app.command("scrub")
@with_source()
def bench_scrub(
    run_dir: Annotated[Optional[Path], typer.Option("--run", help="A recorded run folder to scrub (default: record the source's scans first).")] = None,
    moves: Annotated[int, typer.Option("--moves", min=1, help="Slider moves timed.")] = 200,
    out: Annotated[Optional[Path], typer.Option("--out", help="Keep the run recorded first here (default: a temporary folder).")] = None,
    seed: SeedOpt = None,
    as_json: JsonOpt = False,
    spec=None, preset: PresetOpt = None, config: ConfigOpt = None, set_: SetOpt = None, cache: CacheOpt = None,
):
    """The viewer's timeline: the server-side redraw per slider move on a recorded run (target
    ≤ 50 ms median), and until the step's scan is drawn too.

    Without --run, records the town's first 1000 scans first (unless the source options say otherwise)."""
    from .bench.scrub import scrub

    cfg = config_from(config, set_, seed=seed, preset=preset)
    spec, seq = _recorded_unless(run_dir, spec, cfg)
    with progress_bar() as bar:
        task = bar.add_task("recording", total=None if seq is None else len(seq))
        result = scrub(run_dir, spec=spec, seq=seq, cfg=cfg, cache_root=cache, moves=moves, out=out,
                       progress=lambda i, n: bar.update(task, completed=i))
    _result("scrub", result, as_json)


@bench_app.command("branch")
@with_source()
def bench_branch(
    run_dir: Annotated[Optional[Path], typer.Option("--run", help="A recorded run to branch (default: record the source's scans first).")] = None,
    repeats: Annotated[int, typer.Option("--repeats", min=1, help="Times each of the last 10 steps is branched.")] = 3,
    as_json: JsonOpt = False,
    spec=None, preset: PresetOpt = None, config: ConfigOpt = None, set_: SetOpt = None, cache: CacheOpt = None,
):
    """How fast a branch of a recorded run starts (target ≤ 1 s, the sequence open) and what the
    resume data costs per 1000 steps (checkpoints and per-step fields ≤ 10 MB at the run's own
    particle counts; scaled to 1000 particles beside it).

    Records the town's first 1000 scans unless --run or the source options say otherwise."""
    from .bench.branch import run as run_bench

    cfg = config_from(config, set_, preset=preset)
    spec, seq = _recorded_unless(run_dir, spec, cfg)
    with progress_bar() as bar:
        task = bar.add_task("recording", total=None if seq is None else len(seq))
        result = run_bench(spec, seq, cfg, cache_root=cache, run_dir=run_dir, repeats=repeats,
                           progress=lambda i, n: bar.update(task, completed=i))
    _result("branch", result, as_json)


@bench_app.command("filter")
@with_source(_PF_PANEL)
def bench_filter(
    ctx: typer.Context,
    seeds: Annotated[int, typer.Option("--seeds", min=1, help="Runs per likelihood option (seeds 0…N−1).")] = 3,
    option: Annotated[Optional[list[str]], typer.Option("--option", help="A likelihood option to study (repeatable), each over the paper's likelihood: paper, default, T=<number>, per-point mean, unexplained 0.1 (default: paper, default, T=10, T=100, per-point mean, unexplained 0.1).")] = None,
    as_json: JsonOpt = False,
    spec=None, preset: PresetOpt = None, config: ConfigOpt = None, set_: SetOpt = None, cache: CacheOpt = None,
):
    """Does the filter's uncertainty mean something while it tracks? Each likelihood option started
    around the truth, no S2M: N_eff share, error and 2σ consistency (target ≥ 85 %).

    Default source: the real KITTI raw drive; --town-seed N for the town."""
    from .bench.filter import run as run_bench

    cfg = config_from(config, set_, preset=preset)
    spec = _real_drive_unless_given(ctx, spec, "filter")
    with progress_bar() as bar:
        task = bar.add_task("filter study", total=None)
        result = run_bench(spec, lambda s: open_source(s, cfg, err), cfg, seeds=seeds, options=option,
                           cache_root=cache, progress=lambda i, n: bar.update(task, completed=i, total=n))
    _result("filter", result, as_json)


@bench_app.command("s2m")
@with_source()
def bench_s2m(
    matches: Annotated[int, typer.Option("--matches", min=1, help="Random scans to match (at most all of the source's).")] = 350,
    seed: SeedOpt = None,
    out: Annotated[Optional[Path], typer.Option("--out", help="Write the result, per-scan rows and RMSE histogram PNG here.")] = None,
    gicp_comparison: Annotated[bool, typer.Option("--gicp-comparison/--no-gicp-comparison", help="Compare small_gicp with open3d GICP.")] = True,
    cell_study: Annotated[bool, typer.Option("--cell-study", help="Also match with every BEV cell value.")] = False,
    world: WorldOpt = "lived-in",
    as_json: JsonOpt = False,
    spec=None, preset: PresetOpt = None, config: ConfigOpt = None, set_: SetOpt = None,
):
    """Global/local M3RSM matching: success rate, latency, RMSE (the paper's experiment).

    On the built-in town the scans come from a lived-in drive unless --world kind says otherwise."""
    from .bench.s2m import run as run_bench

    cfg = config_from(config, set_, seed=seed, preset=preset, world=world)
    _result("s2m", run_bench(spec, cfg, matches=matches, out_dir=out, compare_gicp=gicp_comparison,
                             cell_study=cell_study), as_json)


@bench_app.command("rpe")
@with_source()
def bench_rpe(
    convergence: Annotated[Optional[list[float]], typer.Option("--convergence", help="KISS-ICP convergence criteria to compare (repeatable).")] = None,
    as_json: JsonOpt = False,
    spec=None, preset: PresetOpt = None, config: ConfigOpt = None, set_: SetOpt = None,
):
    """KISS-ICP odometry: registration time and error against the truth per convergence setting.

    Registers the first 300 scans unless --scans says otherwise (at least 11)."""
    from .bench.rpe import run as run_bench

    cfg = config_from(config, set_, preset=preset)
    _result("rpe", run_bench(spec, cfg, **({"convergences": tuple(convergence)} if convergence else {})), as_json)


@bench_app.command("viewer")
@with_source(_VIEWER_PANEL)
def bench_viewer(
    ctx: typer.Context, as_json: JsonOpt = False,
    spec=None, preset: PresetOpt = None, config: ConfigOpt = None, set_: SetOpt = None,
):
    """Server-side cost of one display update.

    The inputs are synthetic, sized like a real drive: the source options do not apply."""
    from .bench.viewer import run as run_bench

    cfg = config_from(config, set_, preset=preset)
    chosen = given(ctx, SOURCE_OPTIONS)
    if chosen:
        raise LidarlocError(f"bench viewer times synthetic display updates and reads no sequence; "
                            f"--{chosen[0].replace('_', '-')} does not apply")
    _result("viewer", run_bench(n_particles=cfg.pf.n_particles), as_json)


@bench_app.command("startup")
@with_source()
def bench_startup(
    ctx: typer.Context,
    repeats: Annotated[int, typer.Option("--repeats", min=1, help="Cached starts after the first.")] = 3,
    as_json: JsonOpt = False,
    spec=None, preset: PresetOpt = None, config: ConfigOpt = None, set_: SetOpt = None,
):
    """Start-up time of `lidarloc demo`: first start (empty cache), then cached starts.

    With a source option, the start-up time of `lidarloc view` on that source."""
    from .bench.common import config_args, source_args
    from .bench.startup import run as run_bench

    config_from(config, set_, preset=preset)
    if given(ctx, SOURCE_CHOICE + ("map",)):
        command = ["view", *source_args(spec)]
    else:
        command = ["demo"] + (["--scans", str(spec.scans)] if spec.scans is not None else [])
    _result("startup", run_bench(command + config_args(config, set_, preset), repeats=repeats), as_json)


@bench_app.command("stop")
@with_source()
def bench_stop(
    repeats: Annotated[int, typer.Option("--repeats", min=1, help="Stops per clock and delay.")] = 3,
    delay: Annotated[Optional[list[float]], typer.Option("--delay", min=0.0, help="Seconds after 'localizing' to press Ctrl-C (repeatable).")] = None,
    as_json: JsonOpt = False,
    spec=None, preset: PresetOpt = None, config: ConfigOpt = None, set_: SetOpt = None, cache: CacheOpt = None,
):
    """How fast Ctrl-C stops `lidarloc run` on the town, both clocks (target ≤ 2 s).

    Runs the town's first 300 scans unless the source options say otherwise."""
    from .bench.common import config_args, source_args
    from .bench.stop import run as run_bench

    config_from(config, set_, preset=preset)
    spec = replace(spec, scans=300 if spec.scans is None else spec.scans)
    _result("stop", run_bench(source_args(spec) + config_args(config, set_, preset), repeats=repeats,
                              cache=None if cache is None else str(cache), **({"delays_s": tuple(delay)} if delay else {})),
            as_json)


RecordBenchOpt = Annotated[bool, typer.Option("--record", help="Record every run into its folder (runs/seed_NNN/recording: scrub, branch and compare them later).")]


@bench_app.command("localize")
@with_source()
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
    record: RecordBenchOpt = False,
    world: WorldOpt = "lived-in",
    as_json: JsonOpt = False,
    spec=None, preset: PresetOpt = None, config: ConfigOpt = None, set_: SetOpt = None, cache: CacheOpt = None,
):
    """Metrics A–E over many seeded runs in parallel workers (the paper's Simulation section).

    On the built-in town the drive is lived-in unless --world kind says otherwise."""
    from .bench.localize import run_bench

    overrides = ([] if live_odometry else ["localize.recorded_odometry=true"]) + list(set_ or []) \
        + (["s2m.enabled=false"] if no_s2m else [])
    cfg = config_from(config, overrides, preset=preset, world=world)
    summary = run_bench(spec, cfg, runs=runs, workers=workers, out_dir=out, executor=executor, address=address,
                        cache_root=cache, console=err, preset=preset, record=record)
    _result("localize", summary, as_json)


_AXES = "Matrix (comma-separated values; each axis restricts the matrix)"


@bench_app.command("robustness")
@with_source(exclude=OWN_DATA)
def bench_robustness(
    runs: Annotated[int, typer.Option("--runs", help="Seeded runs per cell (seeds 0…N−1).")] = 5,
    workers: Annotated[int, typer.Option("--workers", help="Worker processes.")] = 2,
    out: Annotated[Path, typer.Option("--out", help="Directory for the cells' runs, report.md, cells.csv, summary.json and heatmap.png.")] = Path("out/bench-robustness"),
    changes: Annotated[str, typer.Option("--changes", help="Shares of the town's movable objects changed since mapping, in [0, 1].", rich_help_panel=_AXES)] = "0,0.3,0.6",
    traffic: Annotated[str, typer.Option("--traffic", help="Traffic: off, on.", rich_help_panel=_AXES)] = "off,on",
    sensors: Annotated[str, typer.Option("--sensors", help="Sensors of the localized drive: hdl64e, vlp16, vlp32c, os1-128.", rich_help_panel=_AXES)] = "hdl64e,vlp16,os1-128",
    skew: Annotated[str, typer.Option("--skew", help="Motion skew: off, on.", rich_help_panel=_AXES)] = "off,on",
    configs: Annotated[str, typer.Option("--configs", help="Configurations: paper (the paper preset), default, no-S2M (default without S2M).", rich_help_panel=_AXES)] = "paper,default,no-S2M",
    real: Annotated[Optional[bool], typer.Option("--real/--no-real", help="Also the real KITTI drive, same configurations (default: where its data is present).", rich_help_panel=_AXES)] = None,
    record: RecordBenchOpt = False,
    as_json: JsonOpt = False,
    spec=None, config: ConfigOpt = None, set_: SetOpt = None, cache: CacheOpt = None,
):
    """Localization when the world is not the map: changes × traffic × sensor × skew × configuration.

    Each cell: --runs seeded runs of the town's first 300 scans (unless --scans says otherwise) against the map of the town as mapped, plus the real KITTI drive's cells. The configurations are presets (so no --preset); --config and --set apply to every cell, e.g. --set town.route=2, but may not set what the matrix sets."""
    from .bench.robustness import parse_matrix, run_robustness

    matrix = parse_matrix(changes, traffic, sensors, skew, configs)
    summary = run_robustness(spec, config, set_, matrix, runs=runs, workers=workers, out_dir=out,
                             real=real, cache_root=cache, console=err, record=record)
    if as_json:
        emit_json(summary)
    else:
        err.print((out / "report.md").read_text(), markup=False, highlight=False, soft_wrap=True)
        err.print(f"report, cells.csv, summary.json and heatmap.png in {out}", highlight=False)


@bench_app.command("integrity")
@with_source()
def bench_integrity(
    runs: Annotated[int, typer.Option("--runs", help="Seeded runs per case and world (seeds 0…N−1).")] = 1,
    workers: Annotated[int, typer.Option("--workers", help="Worker processes.")] = 2,
    out: Annotated[Path, typer.Option("--out", help="Directory for the runs, report.md and summary.json.")] = Path("out/bench-integrity"),
    cases: Annotated[str, typer.Option("--cases", help="Cases: s2m-at-0, s2m-at-20, s2m-at-50, s2m-at-100 (S2M held back until that scan), wrong-place (a start around a look-alike street), kidnap, moved (the particles moved 60 m unannounced).")] = "s2m-at-0,s2m-at-20,s2m-at-50,s2m-at-100,wrong-place,kidnap,moved",
    sensors: Annotated[str, typer.Option("--sensors", help="Sensors of the town's drive: hdl64e, vlp16, vlp32c, os1-128.")] = "hdl64e,vlp16,os1-128",
    real: Annotated[Optional[bool], typer.Option("--real/--no-real", help="Also the real KITTI drive (default: where its data is present).")] = None,
    world: WorldOpt = "lived-in",
    as_json: JsonOpt = False,
    spec=None, config: ConfigOpt = None, set_: SetOpt = None, cache: CacheOpt = None,
):
    """Never green while wrong: S2M late, a wrong-place start, a kidnap, an estimate moved unannounced.

    Per case: false fires, scans called localized while more than 5 m off, scans to recover (or to say lost), spurious relocalizations. The town's first 300 scans unless --scans says otherwise."""
    from .bench.integrity import run_integrity

    summary = run_integrity(spec, config, set_, [c.strip() for c in cases.split(",") if c.strip()],
                            [s.strip() for s in sensors.split(",") if s.strip()], world, runs=runs, workers=workers,
                            out_dir=out, real=real, cache_root=cache, console=err)
    if as_json:
        emit_json(summary)
    else:
        err.print((out / "report.md").read_text(), markup=False, highlight=False, soft_wrap=True)
        err.print(f"report and summary.json in {out}", highlight=False)


def main() -> None:
    """Entry point: click's usage errors behave as usual; LidarlocError becomes one line + exit 2."""
    command = typer.main.get_command(app)
    try:
        command.main(prog_name="lidarloc", standalone_mode=True)
    except LidarlocError as exc:
        fail(str(exc))
    except MemoryError:
        fail("out of memory")


if __name__ == "__main__":
    main()

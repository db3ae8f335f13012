"""``lidarloc run``, ``inspect``, ``compare`` and ``export``: a run, its why, its results (the viewer's commands are in
:mod:`.viewing`)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Annotated

import typer

from ...core.errors import LidarlocError
from ..console import emit_json, err
from ..options import SOURCE_OPTIONS, CacheOpt, InitOpt, JsonOpt, given, with_settings, with_source
from .groups import app


@app.command()
@with_source()
@with_settings()
def run(
    ctx: typer.Context,
    out: Annotated[
        Path, typer.Option("--out", help="Directory for trajectory, per-scan CSV, events, summary and the recording.")
    ],
    seed: Annotated[int | None, typer.Option("--seed", min=0, help="Random seed (default: the config's).")] = None,
    clock: Annotated[
        str | None, typer.Option("--clock", help="replay (deterministic) or realtime (default: the config's).")
    ] = None,
    no_s2m: Annotated[
        bool, typer.Option("--no-s2m", help="Disable scan-to-map matching (plain particle filter).")
    ] = False,
    no_record: Annotated[
        bool,
        typer.Option(
            "--no-record",
            help="Do not record the run's steps into OUT/recording/ (view --run, --branch, compare and export read it).",
        ),
    ] = False,
    branch: Annotated[
        str | None,
        typer.Option(
            "--branch",
            metavar="RUN_DIR:STEP",
            help="Continue the recorded run in RUN_DIR from the filter's exact state after its step STEP (0-based), with --set changes, into --out; source and configuration come from the recording.",
        ),
    ] = None,
    write_bag: Annotated[
        Path | None,
        typer.Option(
            "--write-bag",
            metavar="OUT.mcap",
            help="Also write the run as a ROS 2 bag (MCAP; a name without .mcap: a bag folder) for RViz2 and Foxglove: estimate, /tf, particles, truth, scan, map, events.",
        ),
    ] = None,
    with_input: Annotated[
        bool,
        typer.Option(
            "--with-input", help="With --write-bag on a --bag source: copy the input bag's topics into it too."
        ),
    ] = False,
    as_json: Annotated[bool, typer.Option("--json", help="Print the summary JSON on stdout.")] = False,
    init: InitOpt = None,
    spec=None,
    settings=None,
    cache: CacheOpt = None,
):
    """Localize headless over a sequence and write results to --out (recorded: scrub it with view --run)."""
    if write_bag is not None or with_input:
        from ..export_bag import bag_target

        if write_bag is None:
            raise LidarlocError("--with-input copies the input bag into the bag --write-bag writes; give --write-bag")
        if no_record:
            raise LidarlocError("--write-bag writes the run's recording as a bag; drop --no-record")
        bag_target(write_bag)  # a bad name fails now, not after the run
        if with_input and branch is None:
            from ..export_bag import check_input

            check_input(spec.bag)
    flags = ([f"localize.clock={clock}"] if clock else []) + (["s2m.enabled=false"] if no_s2m else [])
    if branch is not None:
        if given(ctx, SOURCE_OPTIONS) or settings.config or settings.preset or init:
            raise LidarlocError(
                "--branch takes its source and configuration from the recording; give changes with --set"
            )
        from ..branch import parse_branch, run_branch

        run_dir, step = parse_branch(branch)
        overrides = [*settings.overrides, *flags] + ([f"seed={seed}"] if seed is not None else [])
        summary, interrupted = run_branch(
            run_dir, step, overrides, out, cache_root=cache, console=err, record=not no_record
        )
    else:
        from ..headless import run_headless

        cfg = settings.load(seed=seed, last=flags)
        summary, interrupted = run_headless(
            replace(spec, init=init),
            cfg,
            out,
            cache_root=cache,
            console=err,
            preset=settings.preset,
            record=not no_record,
        )
    if write_bag is not None:
        from ..export_bag import export_bag

        export_bag(out, write_bag, console=err, cache_root=cache, with_input=with_input)
    if as_json:
        emit_json(summary)
    if interrupted:
        raise typer.Exit(130)


@app.command()
@with_source()
@with_settings()
def inspect(
    scan: Annotated[
        int, typer.Option("--scan", min=0, help="The scan to inspect (0-based); the run replays up to it.")
    ],
    out: Annotated[
        Path,
        typer.Option(
            "--out", help="Directory for the likelihood surfaces (PNG + .npy), residuals.png and inspect.json."
        ),
    ],
    seed: Annotated[int | None, typer.Option("--seed", min=0, help="Random seed (default: the config's).")] = None,
    best_over_yaw: Annotated[
        bool,
        typer.Option(
            "--best-over-yaw",
            help="Each surface cell: the best of the yaws within ±10° in 2° steps, not the pose's yaw alone.",
        ),
    ] = False,
    as_json: Annotated[bool, typer.Option("--json", help="Print inspect.json on stdout too.")] = False,
    init: InitOpt = None,
    spec=None,
    settings=None,
    cache: CacheOpt = None,
):
    """Replay a run to one scan and write why the filter is where it is: the likelihood surface
    around the estimate and around the truth, the scan's residuals to the map, and a JSON summary."""
    from ..inspect import run_inspect

    cfg = settings.load(seed=seed)
    result = run_inspect(
        replace(spec, init=init), cfg, scan, out, cache_root=cache, console=err, best_over_yaw=best_over_yaw
    )
    if as_json:
        emit_json(result)


# ------------------------------------------------------------------------------ runs: compare, share
@app.command("compare")
def compare(
    runs: Annotated[
        list[Path],
        typer.Argument(help="Two or more run folders (lidarloc run, the viewer, a branch, a benchmark run)."),
    ],
    out: Annotated[
        Path | None,
        typer.Option(
            "--out", help="Write the overlay plot (trajectories; error, std and N_eff against the step) to this PNG."
        ),
    ] = None,
    as_json: Annotated[
        bool, typer.Option("--json", help="Print the figures as JSON on stdout instead of the table.")
    ] = False,
):
    """The summary figures of two or more runs side by side (A–E, success, RMSE, consistency, false fires, PF latency, scans) and an overlay plot for papers."""
    from ..compare import compare_runs

    compare_runs(runs, out, as_json=as_json, console=err)


@app.command("export")
def export(
    run: Annotated[Path, typer.Argument(help="A recorded run folder (with recording/).")],
    out: Annotated[
        Path | None,
        typer.Option(
            "--out",
            help="NAME: writes NAME.viser and the folder NAME/ (open NAME/index.html in a browser; no server needed).",
        ),
    ] = None,
    bag: Annotated[
        Path | None,
        typer.Option(
            "--bag",
            metavar="OUT.mcap",
            help="Write the run as a ROS 2 bag (MCAP; a name without .mcap: a bag folder) of standard messages, for RViz2 (ros2 bag play) and Foxglove.",
        ),
    ] = None,
    foxglove: Annotated[
        Path | None,
        typer.Option(
            "--foxglove",
            metavar="OUT.mcap",
            help="Write the run in Foxglove's own schemas, and OUT.layout.json beside it (Foxglove: Layouts → Import from file).",
        ),
    ] = None,
    with_input: Annotated[
        bool,
        typer.Option("--with-input", help="With --bag, for a run on a bag: copy the input bag's topics into it too."),
    ] = False,
    no_scans: Annotated[bool, typer.Option("--no-scans", help="Leave each step's scan out (a smaller file).")] = False,
    as_json: JsonOpt = False,
    cache: CacheOpt = None,
):
    """Share a recorded run: a .viser recording of its scene and a static web folder that plays it in any browser from disk (no Python, no server); a ROS 2 bag (--bag); a Foxglove file and layout (--foxglove)."""
    if out is None and bag is None and foxglove is None:
        raise LidarlocError(
            "export: say what to write: --out NAME (viewer files), --bag OUT.mcap or --foxglove OUT.mcap"
        )
    if with_input and bag is None:
        raise LidarlocError("--with-input copies the input bag into the bag --bag writes; give --bag")
    result = {}
    if bag is not None:
        from ..export_bag import export_bag

        result["bag"] = export_bag(run, bag, console=err, cache_root=cache, with_input=with_input, scans=not no_scans)
    if foxglove is not None:
        from ..export_foxglove import export_foxglove

        result["foxglove"] = export_foxglove(run, foxglove, console=err, cache_root=cache, scans=not no_scans)
    if out is not None:
        from ..export import export_run

        result.update(export_run(run, out, console=err, cache_root=cache, scans=not no_scans))
    if as_json:
        emit_json(result)

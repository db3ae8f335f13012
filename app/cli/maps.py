"""``lidarloc map build|info|export`` and ``lidarloc synth``: prior maps and the town's drive as files."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Annotated

import typer

from ...core.errors import LidarlocError
from ..console import emit_json, err, peak_rss_mb, progress_bar
from ..options import NOT_TOWN, OWN_DATA, CacheOpt, JsonOpt, open_source, with_settings, with_source
from .groups import app, map_app


@map_app.command("build")
@with_source()
@with_settings()
def map_build(
    out: Annotated[
        Path | None,
        typer.Option(
            "--out",
            help="A .pcd or .ply map file to write (the map, and its road-removed layer beside it as "
            "NAME_road_removed.pcd/.ply), or a cache directory to build into (default: the cache).",
        ),
    ] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print a JSON summary on stdout.")] = False,
    spec=None,
    settings=None,
    cache: CacheOpt = None,
):
    """Build the prior map of a sequence from its scans and ground-truth poses (and cache it).

    Any source with ground truth: a KITTI drive, the town, or a recording (--bag/--scans-dir) with --gt."""
    from ...core.maps.mapfile import WRITE_SUFFIXES
    from ...core.maps.mapfile_write import write_map
    from ...core.maps.mapping import load_or_build_map

    to_file = out is not None and out.suffix.lower() in WRITE_SUFFIXES
    if out is not None and not to_file and out.suffix:
        raise LidarlocError(
            f"{out}: cannot write a map of this type ({out.suffix}); supported: "
            f"{', '.join(WRITE_SUFFIXES)} (or a cache directory)"
        )
    cfg = settings.load()
    # the map of a source is its whole mapping drive (--scans N plays N scans inside it)
    seq = open_source(spec, cfg).map_source
    surveyed = getattr(seq, "delivers_map", False)  # a generated city's survey map
    if not surveyed and (not hasattr(seq, "poses") or not seq.has_poses):
        raise LidarlocError(f"{seq.name}: no ground-truth poses to fuse the scans with (give --gt)")
    t0 = time.perf_counter()
    with progress_bar() as bar:
        task = bar.add_task(f"map of {seq.name}", total=None if surveyed else len(seq))
        prior, directory, cached = load_or_build_map(
            seq, cfg.map, cache if to_file else out, progress=lambda i, n: bar.update(task, completed=i, total=n)
        )
    summary = {
        "points": int(len(prior.points)),
        "points_road_removed": int(len(prior.points_bev)),
        "seconds": round(time.perf_counter() - t0, 3),
        "peak_rss_mb": round(peak_rss_mb(), 1),
        "cached": cached,
        "cache_dir": str(directory),
        "scans": 0 if surveyed else len(seq),
    }
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
        err.print(
            f"map: {summary['points']:,} points, {summary['points_road_removed']:,} after road removal, "
            f"{summary['seconds']} s ({'from cache' if cached else 'built'}) → {where}",
            markup=False,
            highlight=False,
            soft_wrap=True,
        )


def road_removed_path(out: Path) -> Path:
    """Where ``map build --out FILE`` writes the road-removed layer: beside FILE, ``NAME_road_removed``."""
    return out.with_name(f"{out.stem}_road_removed{out.suffix}")


@map_app.command("info")
def map_info(
    file: Annotated[Path, typer.Argument(help="Map file: .pcd, .ply, .las, .laz, .npy or .npz.", show_default=False)],
    as_json: JsonOpt = False,
):
    """Points, extent and origin (in the file's frame) and density of a point-cloud map file."""
    from ...core.maps.map_info import describe_map, map_info_lines
    from ...core.maps.mapfile import read_map

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
@with_settings()
def map_export(
    out: Annotated[
        Path, typer.Option("--out", help="Map file to write: .pcd or .ply (binary, x y z).", show_default=False)
    ],
    as_json: Annotated[bool, typer.Option("--json", help="Print a JSON summary on stdout.")] = False,
    spec=None,
    settings=None,
    cache: CacheOpt = None,
):
    """Write a source's prior map (built or from the cache) as a .pcd or .ply file.

    The map is written in the source's frame: a map read from a georeferenced file goes back to its own coordinates, as float64."""
    from ...core.maps.mapfile import WRITE_SUFFIXES
    from ...core.maps.mapfile_write import write_map
    from ...core.maps.mapping import load_or_build_map

    if out.suffix.lower() not in WRITE_SUFFIXES:  # before building a map that cannot be written
        raise LidarlocError(
            f"{out}: cannot write a map of this type ({out.suffix or 'no extension'}); "
            f"supported: {', '.join(WRITE_SUFFIXES)}"
        )
    cfg = settings.load()
    seq = open_source(spec, cfg).map_source
    with progress_bar() as bar:
        task = bar.add_task(f"map of {seq.name}", total=None)
        prior = load_or_build_map(
            seq, cfg.map, cache, progress=lambda i, n: bar.update(task, completed=i, total=n), road_removal=False
        ).value
    origin = prior.origin if prior.origin.any() else None
    write_map(out, prior.points, origin=origin)
    summary = {"points": int(len(prior.points)), "out": str(out), "origin_m": [float(v) for v in prior.origin]}
    if as_json:
        emit_json(summary)
    else:
        err.print(f"wrote {summary['points']:,} map points to {out}", markup=False, highlight=False)


# ---------------------------------------------------------------------------------------- synth
@app.command()
@with_source(exclude=NOT_TOWN + OWN_DATA)
@with_settings()
def synth(
    out: Annotated[Path, typer.Option("--out", help="Directory to write the KITTI odometry layout into.")],
    sequence_id: Annotated[str, typer.Option("--sequence-id", help="Sequence id to write as.")] = "00",
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace an existing exported sequence.")] = False,
    spec=None,
    cfg=None,
):
    """Export the built-in town's drive in KITTI odometry layout (velodyne/*.bin, calib, times, poses)."""
    from ...core.sequences.export import export_kitti_odometry
    from ...core.sequences.factory import open_sequence

    seq = open_sequence(spec, cfg)
    with progress_bar() as bar:
        task = bar.add_task(f"scans of {seq.name}", total=len(seq))
        export_kitti_odometry(
            seq, out, sequence=sequence_id, overwrite=overwrite, progress=lambda i, n: bar.update(task, completed=i)
        )
    err.print(f"wrote {len(seq)} scans to {out}/sequences/{sequence_id}")


# ------------------------------------------------------------------------------------ localize

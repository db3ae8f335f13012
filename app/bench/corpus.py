"""``lidarloc bench corpus``: does ``corpus compare`` find a planted regression, and only that?

One corpus (the built-in town's drives: town seeds × its sensors, lived-in, each under
``seeds`` seeds; plus the real drive where its data is) is run five ways into one folder:

- ``base-1w``: with one worker, only for its wall time;
- ``base``: with ``workers`` workers (the baseline; its wall time against ``base-1w``'s);
- ``reseeded``: the same drives under other seeds: the same code, so every regression
  ``corpus compare`` reports against ``base`` is a false alarm;
- ``sigma``: every drive with ``pf.sigma`` × 5: a regression everywhere;
- ``removed``: one drive's map has a building removed (every point inside its footprint), the
  other drives kept from ``base``: the drive must be ranked first.

Each of the last three is compared with ``base`` by :func:`~lidarloc.app.corpus.compare.compare_outputs`,
as ``lidarloc corpus compare`` does.
"""

from __future__ import annotations

import shutil
import time
from pathlib import Path

import numpy as np
from rich.console import Console

from ...core.config import Config, load_config
from ...core.errors import LidarlocError
from ...core.sequences.factory import SourceSpec, open_sequence
from ..corpus.compare import compare_outputs
from ..corpus.example import WORLD, example_drives
from ..corpus.figures import read_output
from ..corpus.run import run_corpus
from ..corpus.spec import parse_corpus
from .common import real_drive

#: the planted change of the whole corpus: the likelihood's σ five times the default
SIGMA_FACTOR = 5.0
#: the drive whose map loses a building (the first town drive, HDL-64E)
PLANTED_DRIVE = 0
#: the removed building stands within this distance of the drive's middle scan (metres)
NEAR_M = 30.0


def bench_drives(drives: int, scans: int, seeds: int, first_seed: int, real: bool) -> list[dict]:
    """The corpus's drives: ``drives`` of the town (with the real drive, if asked and present,
    as one of them), each under seeds ``first_seed`` … ``first_seed + seeds − 1`` named
    ``NAME-r0`` … (the same names under other seeds: compared drive by drive)."""
    spec = real_drive(scans) if real else None
    town = example_drives(drives - (spec is not None))
    rows = [{k: v for k, v in d.items() if k != "seed"} for d in town]
    if spec is not None:
        rows.append({"name": "kitti-0013", "world": None, **spec.to_dict(absolute=True)})
    out = []
    for row in rows:
        for k in range(seeds):
            out.append(
                {
                    **{k2: v for k2, v in row.items() if v is not None},
                    "name": f"{row['name']}-r{k}",
                    "seed": first_seed + k,
                }
            )
    return out


def corpus_of(drive_rows: list[dict], scans: int, where: Path, overrides=()):
    data = {"defaults": {"world": WORLD, "scans": scans}, "drives": drive_rows}
    return parse_corpus(data, where / "corpus.yaml", overrides)


def building_removed_map(row: dict, scans: int, cache_root: Path | None, out: Path) -> dict:
    """Write the map of the drive ``row`` with the largest building near its middle scan removed
    (every map point inside the building's footprint, 0.5 m wider), as ``out`` (.ply); returns
    what was removed."""
    from ...core.maps.mapfile_write import write_map
    from ...core.maps.mapping import load_or_build_map

    spec = SourceSpec(town_seed=row["town_seed"], scans=scans)
    cfg = load_config(None, list(row.get("set", [])), world=WORLD)
    seq = open_sequence(spec, cfg)
    prior = load_or_build_map(seq.map_source, cfg.map, cache_root, road_removal=False).value
    boxes = seq.town.solids.boxes.get("building", [])
    if not boxes:
        raise LidarlocError("bench corpus: the town has no building to remove")
    middle = seq.poses[min(len(seq), scans) // 2][:2, 3]
    rows = np.asarray([b[:5] for b in boxes], dtype=float)  # cx, cy, yaw, length, width
    # the largest within NEAR_M of the middle scan (the nearest building where none is): a
    # building the drive sees for many scans, not a shed
    distance = np.hypot(rows[:, 0] - middle[0], rows[:, 1] - middle[1])
    near = np.flatnonzero(distance <= NEAR_M)
    chosen = int(near[np.argmax(rows[near, 3] * rows[near, 4])]) if near.size else int(np.argmin(distance))
    cx, cy, yaw, length, width = rows[chosen]
    pts = prior.points
    dx, dy = pts[:, 0] - cx, pts[:, 1] - cy
    along = np.abs(np.cos(yaw) * dx + np.sin(yaw) * dy)
    across = np.abs(-np.sin(yaw) * dx + np.cos(yaw) * dy)
    inside = (along <= length / 2 + 0.5) & (across <= width / 2 + 0.5)
    write_map(out, pts[~inside], origin=prior.origin if prior.origin.any() else None)
    return {
        "building_xy_m": [round(float(cx), 1), round(float(cy), 1)],
        "size_m": [round(float(length), 1), round(float(width), 1)],
        "yaw_deg": round(float(np.degrees(yaw)), 2),
        "from_middle_scan_m": round(float(np.hypot(cx - middle[0], cy - middle[1])), 1),
        "points_removed": int(inside.sum()),
    }


def _timed_run(corpus, out: Path, workers: int, overrides, ray, cache_root, console) -> float:
    t0 = time.perf_counter()
    report, tally = run_corpus(
        corpus, out, workers, overrides=overrides, ray=ray, cache_root=cache_root, console=console
    )
    if tally.interrupted:
        raise KeyboardInterrupt
    if report["drives_failed"]:
        name, why = next(iter(report["drives_failed"].items()))
        raise LidarlocError(f"bench corpus: drive {name} failed in {out.name}: {why}")
    return time.perf_counter() - t0


def _ranked(result: dict) -> list[str]:
    """The drives of the regressions, worst first, each once."""
    seen: list[str] = []
    for e in result["regressions"]:
        if e["drive"] not in seen:
            seen.append(e["drive"])
    return seen


def corpus_bench(
    out: Path,
    drives: int,
    scans: int,
    seeds: int,
    workers: int,
    *,
    ray: str | None = None,
    real: bool = True,
    cache_root: Path | None = None,
    console: Console | None = None,
) -> dict:
    """Run the five corpora into ``out`` and return the figures (see the module's docstring)."""
    if drives < 2 or seeds < 2:
        raise LidarlocError("bench corpus needs --drives ≥ 2 and --seeds ≥ 2 (the noise is measured from seeds)")
    out = Path(out)
    if out.exists() and any(out.iterdir()):
        raise LidarlocError(f"{out}: exists and is not empty (bench corpus times fresh runs: give a new --out)")
    base_rows = bench_drives(drives, scans, seeds, 0, real)
    base = corpus_of(base_rows, scans, out)
    wall_1 = _timed_run(base, out / "base-1w", 1, (), ray, cache_root, console)
    wall_n = _timed_run(base, out / "base", workers, (), ray, cache_root, console)

    reseeded = corpus_of(bench_drives(drives, scans, seeds, seeds, real), scans, out)
    _timed_run(reseeded, out / "reseeded", workers, (), ray, cache_root, console)
    sigma = SIGMA_FACTOR * Config().pf.sigma
    _timed_run(base, out / "sigma", workers, [f"pf.sigma={sigma:g}"], ray, cache_root, console)

    planted = base_rows[PLANTED_DRIVE * seeds]["name"].rsplit("-r", 1)[0]
    map_file = out / f"{planted}-building-removed.ply"
    removed_info = building_removed_map(base_rows[PLANTED_DRIVE * seeds], scans, cache_root, map_file)
    shutil.copytree(out / "base", out / "removed", ignore=shutil.ignore_patterns("ray"))
    removed_rows = []
    for row in base_rows:
        if row["name"].rsplit("-r", 1)[0] == planted:
            shutil.rmtree(out / "removed" / "drives" / row["name"])
            row = {**row, "map": str(map_file.absolute())}
        removed_rows.append(row)
    _timed_run(corpus_of(removed_rows, scans, out), out / "removed", workers, (), ray, cache_root, console)

    base_out = read_output(out / "base", "BASE")
    results = {
        name: compare_outputs(base_out, read_output(out / name, "NEW")) for name in ("reseeded", "sigma", "removed")
    }
    ranked = {name: _ranked(r) for name, r in results.items()}
    n_drives = len(base_rows)
    return {
        "drives": n_drives,
        "logs": n_drives // seeds,
        "seeds": seeds,
        "scans": scans,
        "workers": workers,
        "ray": ray,
        "wall_s_1_worker": round(wall_1, 1),
        f"wall_s_{workers}_workers": round(wall_n, 1),
        "wall_ratio": round(wall_n / wall_1, 3),
        "false_alarms": len(results["reseeded"]["regressions"]),
        "false_alarm_drives": ranked["reseeded"],
        "sigma_regressed_drives": len(ranked["sigma"]),
        "sigma_first": ranked["sigma"][0] if ranked["sigma"] else None,
        "removed_drive": planted,
        "removed_building": removed_info,
        "removed_ranked": ranked["removed"],
        "removed_first": bool(ranked["removed"]) and ranked["removed"][0].rsplit("-r", 1)[0] == planted,
        "out": str(out),
    }

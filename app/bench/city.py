"""``lidarloc bench city``: lidarloc holding a city — the tiled tables' build, a later start, the
memory a drive keeps resident, and the exact global search over the whole city beside the
whole-map search and open3d's FPFH + RANSAC on the same scans and map.

Global matches are M3RSM's 2D optimum (no GICP), judged against the truth: within 2 m and 5°.
The whole-map search runs where its pyramid fits in memory (always, up to a 6 km city at 1 m
cells: 144 MB of L0); FPFH + RANSAC runs on ``peer_scans`` of the same scans, in a process of
its own stopped at a time and memory budget (on the town seconds a scan; on a 16 km² city its
feature map alone takes most of an hour and 12 GB on 2 cores).
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from ...core.config import Config
from ...core.maps.bev import load_or_build_pyramid
from ...core.maps.mapping import MAP_FILE, load_or_build_map, range_filter
from ...core.maps.places import PlaceSettings, index_of_tiles, load_or_build_place_index, place_index_name
from ...core.maps.point_tiles import PointTiles
from ...core.maps.tiled_bev import TiledBEV
from ...core.maps.tiled_lookup import TiledLookup
from ...core.matching.s2m import ScanToMapMatcher
from ...core.sequences.factory import SourceSpec
from ...core.worker_process import exit_words
from ..console import SIGNAL_POLL_S
from .city_figures import global_figures
from .city_rows import (
    ROW_CODE,
    ROW_CODE_EXCLUDED,
    GlobalRows,
    candidate_row,
    match_row,
    prepare,
    scan_order,
    warm_up,
)
from .common import load_avg, machine, median, open_source, rss_mb
from .localize import code_fingerprint

PEER_SAMPLE_S = 0.5  # how often FPFH + RANSAC's memory is read against its budget
# What FPFH + RANSAC's registrations depend on beyond the global matches' code (ROW_CODE).
PEER_CODE = ("app/bench/city_peer.py", "app/bench/peers_global.py", "core/o3d.py")


def stoppable(fn, *args):
    """``fn(*args)`` on a thread of its own, this thread waiting on it in short joins. A global
    search over a city runs for a minute or more inside numba, where Python runs no signal handler:
    called on the main thread, a Ctrl-C or SIGTERM would wait for it to end. Here the stop's
    KeyboardInterrupt is raised at once, and the search, on a daemon thread, is left to the
    process's exit (the rows done so far are on disk already)."""
    done: dict = {}

    def call() -> None:
        try:
            done["value"] = fn(*args)
        except BaseException as exc:  # handed to the waiting thread, raised there
            done["error"] = exc

    worker = threading.Thread(target=call, name="lidarloc-global-match", daemon=True)
    worker.start()
    while worker.is_alive():
        worker.join(SIGNAL_POLL_S)
    if "error" in done:
        raise done["error"]
    return done["value"]


def peer_identity(seq, cfg: Config) -> dict:
    """What FPFH + RANSAC's kept registrations depend on: the source, the configuration (the map's
    and the seed), open3d and the code that maps, prepares, registers and judges them."""
    from ...core.o3d import open3d

    return {
        "method": "FPFH + RANSAC",
        "source": seq.name,
        "scans": len(seq),
        "config": cfg.to_dict(),
        "open3d": open3d().__version__,
        "code": code_fingerprint(ROW_CODE + PEER_CODE, exclude=ROW_CODE_EXCLUDED),
    }


def _kept(path: Path) -> int:
    try:
        return len(json.loads(path.read_text())["rows"]) if path.is_file() else 0
    except (OSError, ValueError, KeyError, TypeError):  # not a rows file: the run refuses it
        return 0


def stopped_line(rows_dir: Path, peer_rows_dir: Path | None = None) -> str:
    """What a stopped ``bench city`` says: how many global matches (and FPFH + RANSAC
    registrations, where it keeps some) it keeps, where, and how to go on."""
    path = Path(rows_dir) / "rows.json"
    kept = f"{_kept(path)} global matches kept in {path}"
    peer_path = None if peer_rows_dir is None else Path(peer_rows_dir) / "rows.json"
    if peer_path is not None and peer_path.is_file():
        kept += f" and {_kept(peer_path)} FPFH + RANSAC registrations in {peer_path}"
    return f"stopped: {kept}; the same command resumes at the next scan"


def _tables(prior, map_dir: Path, cfg: Config, tile_m: float, bev_tile_m: float, progress):
    key = map_dir.name
    lookup = TiledLookup.load_or_build(
        prior.points, map_dir / "tiles-lookup", key, cfg.pf.lookup_resolution, cfg.pf.d_max, tile_m,
        progress=lambda f: progress("lookup tiles", f),
    )  # fmt: skip
    bev = TiledBEV.load_or_build(
        prior.points_bev, map_dir / "tiles-bev", key, cfg.s2m.match_resolution, bev_tile_m,
        "binary" if cfg.s2m.binary_cells else None, progress=lambda f: progress("pyramid tiles", f),
    )  # fmt: skip
    return lookup, bev


def run(
    spec: SourceSpec,
    cfg: Config,
    cache_root: Path | None = None,
    global_scans: int = 200,
    peer_scans: int = 10,
    tile_m: float = 400.0,
    bev_tile_m: float = 256.0,
    whole_map: bool = True,
    exact_scans: int | None = None,
    progress=None,
    rows_dir: Path | None = None,
    peer_budget_s: float = 3600.0,
    peer_budget_mb: float | None = None,
    peer_rows_dir: Path | None = None,
    ray: str | None = None,
    ray_workers: int = 2,
) -> dict:
    """The figures above. Every scan is localized as lidarloc does it (the place index's
    candidates verified by M3RSM and GICP; the whole-map second opinion beside it); the exact tiled
    search over the whole city, the reference, runs on the first ``exact_scans`` of them (None:
    all), the whole-map search beside it where ``whole_map``. ``rows_dir``: keep the global matches there and resume those an earlier
    run of the same source, configuration and code left (:class:`GlobalRows`); ``peer_rows_dir``:
    the same for FPFH + RANSAC's registrations. FPFH + RANSAC is stopped at ``peer_budget_s`` of
    wall time or ``peer_budget_mb`` of resident memory (default: three quarters of the machine's)
    and says so (:func:`peers`). ``ray``: the exact tiled search runs on Ray (local, auto or an
    address) over ``ray_workers`` shards (:mod:`.shards`), with the same answers."""
    report = progress or (lambda what, f: None)
    seq = open_source(spec, cfg, "city", need_poses=True)
    t0 = time.perf_counter()
    # a large map stays on disk, mapped (as in a run on tiles), not read into memory whole: the
    # system pages in what the tables, the whole-map pyramid and FPFH's down-sampling read
    prior, map_dir, _ = load_or_build_map(seq.map_source, cfg.map, cache_root, memory_map=True)
    map_meta = json.loads((map_dir / "meta.json").read_text()) if (map_dir / "meta.json").is_file() else {}
    map_load_s = time.perf_counter() - t0
    lookup, bev = _tables(prior, map_dir, cfg, tile_m, bev_tile_m, report)
    places, places_path = _places(prior, bev, map_dir, report)
    build = {
        "map": map_meta.get("build_seconds"),
        "lookup": lookup.index.get("build_seconds"),
        "pyramid": bev.index.get("build_seconds"),
    }
    # GICP reads the map near each match from its point tiles, as a run on the city does
    prior.use_tiles(PointTiles.load_or_build(prior.points, map_dir / "tiles-points", map_dir.name))
    matcher = ScanToMapMatcher(prior, bev, cfg.s2m, cfg.map, places=places)
    x0, y0, x1, y1 = bev.extent
    whole_cfg = replace(cfg.s2m, region_x=2.0 * (x1 - x0), region_y=2.0 * (y1 - y0))
    out: dict = {
        "source": seq.name,
        "machine": machine(),
        "load_avg_start": load_avg(),
        "map_points": int(len(prior.points)),
        "map_points_road_removed": int(len(prior.points_bev)) if prior.points_bev is not None else 0,
        "tile_m": lookup.tile_m,
        "bev_tile_m": bev.tile_cells * bev.resolution,
        "build_parts_s": build,
        "build_s": sum(v for v in build.values() if v is not None),
        "map_load_s": map_load_s,
        "cache_mb": (_dir_bytes(map_dir)) / 1e6,
        "tiles_mb": (lookup.cache_bytes + bev.cache_bytes) / 1e6,
        "places": len(places),
        "places_build_s": places.meta.get("build_seconds"),
        "places_mb": places_path.stat().st_size / 1e6,
    }
    # what the place index adds to the tables' build and to the cache
    out["places_build_share"] = (out["places_build_s"] or 0.0) / out["build_s"] if out["build_s"] else None
    out["places_cache_share"] = out["places_mb"] / max(out["cache_mb"] - out["places_mb"], 1e-9)
    idx = scan_order(len(seq), global_scans, cfg.seed)
    exact_on = f"ray:{ray_workers}" if ray else "threads"  # the same answers, other times
    kept = kept_peer = None
    if rows_dir is not None:
        identity = {
            "source": seq.name,
            "scans": len(seq),
            "config": cfg.to_dict(),
            "bev_tile_m": bev_tile_m,
            "whole_map": whole_map,
            "exact_scans": exact_scans,
            "exact_on": exact_on,
            "code": code_fingerprint(ROW_CODE, exclude=ROW_CODE_EXCLUDED),
        }
        kept = GlobalRows(rows_dir, identity)
    if peer_rows_dir is not None and peer_scans > 0:
        kept_peer = GlobalRows(peer_rows_dir, peer_identity(seq, cfg))
    out["global_scans_resumed"] = sum(k in kept.rows for k in idx) if kept is not None else 0
    n_exact = len(idx) if exact_scans is None else min(int(exact_scans), len(idx))
    # exact searches still to run: none where every one was kept by an earlier run
    exact_to_run = n_exact > 0 and (kept is None or any(k not in kept.rows for k in idx[:n_exact]))
    pyramid = None
    if whole_map and exact_to_run:
        pyramid = load_or_build_pyramid(prior, map_dir, cfg.s2m).value
    rows, warm, shards = [], False, None
    tiles = None  # the exact search's shards, where it runs on Ray
    if ray is not None and exact_to_run:
        from .shards import RayShards

        shards = RayShards(bev, ray_workers, ray)
        tiles = shards.tiles
    try:
        for j, k in enumerate(idx):
            if kept is not None and k in kept.rows:
                rows.append(kept.rows[k])
                report("global matches", (j + 1) / len(idx))
                continue
            truth, prep = seq.pose(k), matcher.prepare(seq.scan(k))
            scan = prep.road_removed
            if not warm:  # numba's kernels compiled, the tiles' first pages read, off the clock
                stoppable(warm_up, bev, pyramid if n_exact else None, scan, cfg.s2m.angle_step, n_exact > 0, tiles)
                stoppable(candidate_row, k, prep, truth, matcher, whole_cfg)
                warm = True
            row = stoppable(candidate_row, k, prep, truth, matcher, whole_cfg)
            if j < n_exact:
                row.update(stoppable(match_row, k, scan, truth, bev, pyramid, cfg.s2m.angle_step, tiles))
            rows.append(row)
            if kept is not None:
                kept.add(row)
            report("global matches", (j + 1) / len(idx))
    finally:
        if shards is not None:
            shards.close()
    out["exact_on"] = exact_on
    out.update(global_figures(rows, seq, whole_map))
    if peer_scans > 0:
        budget_mb = default_peer_budget_mb() if peer_budget_mb is None else peer_budget_mb
        # in the seeded order, not the drive's: the registrations a stopped run kept are a fair
        # sample of the scans, as the global matches' are
        chosen = idx[:peer_scans]
        out.update(peers(seq, map_dir / MAP_FILE, cfg, chosen, report, peer_budget_s, budget_mb, kept_peer))
    out.update(_probe(seq, lookup, bev, cfg, idx))
    out["localize_success"] = None  # filled by localize_figures (``--localize-runs``)
    out["load_avg_end"] = load_avg()
    out["rss_bench_mb"] = rss_mb()
    out["rows"] = rows
    return out


def _places(prior, bev: TiledBEV, map_dir: Path, report):
    """The city's place index, built from its pyramid tiles and the map, cached beside them."""
    settings = PlaceSettings()
    path = map_dir / place_index_name(f"tiles-bev-{bev.index['key'].split('|bev|')[1].replace('|', '-')}", settings)
    index, _ = load_or_build_place_index(
        lambda: index_of_tiles(bev, prior.points, settings, progress=lambda f: report("place index", f)), path
    )
    return index, path


def localize_figures(spec: SourceSpec, cfg: Config, runs: int, workers: int, out_dir: Path, cache_root=None) -> dict:
    """Full localization from a start spread over the whole city: ``runs`` seeded runs of
    ``bench localize`` on the city's drive (into ``out_dir``, resumable as its own). A run
    succeeds if it localized and was within 5 m of the truth to the end of the drive; the
    targets also ask for D max ≤ 40 and no false fire."""
    from .localize import run_bench as localize_runs

    agg = localize_runs(spec, cfg, runs=runs, workers=workers, out_dir=out_dir, cache_root=cache_root)
    return {
        "localize_runs": runs,
        "localize_success": agg.get("within_5m_to_end_ratio"),
        "localize_D_max": (agg.get("D") or {}).get("max"),
        "localize_false_fire_rate": agg.get("false_fire_rate"),
        # the drive's seconds from its first scan to the first fix, the median run: what a user
        # waits on the real-time clock (--set localize.clock=realtime)
        "first_fix_s_median": agg.get("localized_at_s_median"),
        "localize_clock": cfg.localize.clock,
        "localize_rmse_after_localized_m_median": agg.get("rmse_after_localized_m_median"),
        "localize_out": str(out_dir),
    }


def _dir_bytes(directory: Path) -> int:
    return sum(p.stat().st_size for p in Path(directory).rglob("*") if p.is_file())


def peers(
    seq, map_file: Path, cfg: Config, idx: list[int], report, budget_s: float, budget_mb: float, kept=None
) -> dict:
    """FPFH + RANSAC on the scans ``idx`` against the whole map, in a process of its own
    (:mod:`.city_peer`), stopped once it has run ``budget_s``, its own memory passes ``budget_mb``
    or the machine's available memory falls to :func:`memory_reserve`: on a 16 km² city the
    feature map alone takes ~40 min and 12 GB on 2 cores (it is kept beside the map, so only the
    first run pays for it). Its own memory is its anonymous resident memory: the pages of the
    memory-mapped map it has read count in its RSS too, but the system takes them back when it
    needs them. What it finished before a stop is reported, with how and where it stopped
    (``fpfh_ransac_status``) and its peak memory; a stop is a figure, not a failure of the bench.
    ``kept`` (a :class:`GlobalRows`): the registrations are kept there as they are done and those
    it holds are not run again."""
    resumed = {k: kept.rows[k] for k in idx if kept is not None and k in kept.rows}
    todo = [k for k in idx if k not in resumed]

    def keep(line: dict) -> None:  # on the child's reader thread, as each registration ends
        if kept is not None and "scan" in line:
            kept.add(line)

    child = None
    if todo:
        with tempfile.TemporaryDirectory() as tmp:
            scans = [np.asarray(range_filter(seq.scan(k), cfg.map)[:, :3], dtype=np.float64) for k in todo]
            np.savez(
                Path(tmp) / "scans.npz",
                points=np.concatenate(scans),
                ends=np.cumsum([len(s) for s in scans], dtype=np.int64),
                truth=np.stack([seq.pose(k) for k in todo]),
                scan=np.asarray(todo, dtype=np.int64),
            )
            args = {
                "map": str(map_file),
                "features_dir": str(Path(map_file).parent),
                "scans": str(Path(tmp) / "scans.npz"),
                "seed": cfg.seed,
            }
            with open(Path(tmp) / "stderr.txt", "w+") as err:
                child = _PeerChild([sys.executable, "-m", f"{__package__}.city_peer", json.dumps(args)], err, keep)
                stop = child.watch(
                    budget_s, budget_mb, lambda n: report("FPFH + RANSAC", (len(resumed) + n) / max(len(idx), 1))
                )
                err.seek(0)
                last_error = ([ln.strip() for ln in err if ln.strip()] or [""])[-1]
    lines = child.lines if child else []
    features = next((ln for ln in lines if "features_s" in ln), None)
    if features is None:  # nothing run, or stopped before: what the kept feature map's record says
        features = _cached_features(Path(map_file).parent)
    registered = {**resumed, **{ln["scan"]: ln for ln in lines if "scan" in ln}}
    done = [registered[k] for k in idx if k in registered]
    if child is None:
        status = "done"
    elif stop is not None:
        where = "while building the map's features" if features is None else f"after {len(done)} of {len(idx)} scans"
        status = f"stopped at {stop} {where}"
    elif child.returncode != 0 or len(done) < len(idx):
        status = f"failed ({exit_words(child.returncode)}): {last_error}"
    else:
        status = "done"
    peak_rss = max([child.peak_rss_mb if child else 0.0] + [ln["rss_peak_mb"] for ln in done])
    return {
        "fpfh_ransac_scans": len(idx),
        "fpfh_ransac_scans_done": len(done),
        "fpfh_ransac_scans_resumed": len(resumed),
        "fpfh_ransac_ms_median": median(ln["ms"] for ln in done),
        "fpfh_ransac_success": float(np.mean([ln["ok"] for ln in done])) if done else None,
        "fpfh_ransac_status": status,
        "fpfh_map_build_s": features["features_s"] if features else None,
        "fpfh_features_cached": features["features_cached"] if features else None,
        "fpfh_index_s": features.get("index_s") if features else None,
        "fpfh_feature_points": features["feature_points"] if features else None,
        "fpfh_peak_rss_mb": round(peak_rss, 1),
        "fpfh_peak_own_mb": round(child.peak_own_mb, 1) if child else None,
        "fpfh_wall_s": round(child.wall_s, 1) if child else 0.0,
        "fpfh_ransac_rows": done,
    }


def _cached_features(map_dir: Path) -> dict | None:
    """The record of the FPFH feature map kept in ``map_dir``, as the child reports it, or None."""
    from .peers_global import FEATURES_RECORD, features_dir

    try:
        record = json.loads((features_dir(map_dir) / FEATURES_RECORD).read_text())
        return {"features_s": record["build_s"], "features_cached": True, "feature_points": record["feature_points"]}
    except (OSError, ValueError, KeyError, TypeError):
        return None


class _PeerChild:
    """The FPFH + RANSAC process, its JSON lines read on a thread as they come."""

    def __init__(self, cmd: list[str], stderr, on_line=None):
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=stderr, text=True)
        self.lines: list[dict] = []
        self._on_line = on_line or (lambda line: None)
        self.peak_rss_mb = 0.0
        self.peak_own_mb = 0.0  # anonymous: the RSS without the mapped map's pages
        self.wall_s = 0.0
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            if line.startswith("{"):  # open3d may print its own lines on stdout
                try:
                    parsed = json.loads(line)
                except ValueError:
                    continue
                self.lines.append(parsed)
                self._on_line(parsed)

    @property
    def returncode(self) -> int | None:
        return self.proc.returncode

    def watch(self, budget_s: float, budget_mb: float, progress) -> str | None:
        """Wait for the child's end, sampling its memory; kill it at a budget and name that
        budget (None: it ended by itself). The child never outlives this call."""
        import psutil

        t0 = time.perf_counter()
        stop = None
        try:
            while True:
                try:
                    self.proc.wait(timeout=PEER_SAMPLE_S)  # ends at once with the child
                    break
                except subprocess.TimeoutExpired:
                    pass
                try:
                    mem = psutil.Process(self.proc.pid).memory_info()
                except psutil.Error:  # ended meanwhile: the next wait returns
                    continue
                self.peak_rss_mb = max(self.peak_rss_mb, mem.rss / 2**20)
                self.peak_own_mb = max(self.peak_own_mb, (mem.rss - mem.shared) / 2**20)
                progress(sum("scan" in ln for ln in self.lines))
                if time.perf_counter() - t0 > budget_s:
                    stop = f"the time budget ({budget_s / 60:g} min)"
                    break
                if self.peak_own_mb > budget_mb:
                    stop = f"the memory budget ({budget_mb / 1024:g} GB)"
                    break
                left = psutil.virtual_memory().available
                if left < memory_reserve():  # whatever else runs, never run the machine out of memory
                    stop = f"the machine's memory ({left / 2**30:.1f} GB left, at {self.peak_own_mb / 1024:.1f} GB of its own)"
                    break
        finally:
            if self.proc.poll() is None:
                self.proc.kill()
            self.proc.wait()
            self._reader.join()  # the pipe closes with the child: every line it wrote is read
            self.wall_s = time.perf_counter() - t0
        return stop


def memory_reserve() -> int:
    """Bytes FPFH + RANSAC always leaves the machine: 5 % of its memory, at least 1 GB."""
    import psutil

    return max(2**30, int(0.05 * psutil.virtual_memory().total))


def default_peer_budget_mb() -> float:
    """What the machine has available now, less the reserve, and at most three quarters of its
    memory: the bench itself holds the city (4.4 GB for the 16 km² one) beside it."""
    import psutil

    vm = psutil.virtual_memory()
    return max(0.0, min(0.75 * vm.total, vm.available - memory_reserve())) / 2**20


def _probe(seq, lookup: TiledLookup, bev: TiledBEV, cfg: Config, idx: list[int]) -> dict:
    """Start and resident memory in a fresh process (see :mod:`.city_probe`)."""
    with tempfile.TemporaryDirectory() as tmp:
        poses = np.array([seq.pose(k)[:3, 3] for k in range(0, len(seq), 5)])
        np.save(Path(tmp) / "poses.npy", poses)
        np.save(Path(tmp) / "scan.npy", prepare(seq.scan(idx[0]), cfg)[:, :2])
        args = {
            "poses": str(Path(tmp) / "poses.npy"),
            "scan": str(Path(tmp) / "scan.npy"),
            "lookup_dir": str(lookup.directory),
            "lookup_key": lookup.index["key"],
            "bev_dir": str(bev.directory),
            "bev_key": bev.index["key"].split("|bev|")[0],
            "bev_res": bev.resolution,
            "bev_tile_m": bev.tile_cells * bev.resolution,
            "angle_step": cfg.s2m.angle_step,
        }
        done = subprocess.run(
            [sys.executable, "-m", "lidarloc.app.bench.city_probe", json.dumps(args)], capture_output=True, text=True
        )
    if done.returncode != 0:
        return {"start_s": None, "rss_tracking_mb": None, "probe_error": done.stderr.strip().splitlines()[-1:]}
    got = json.loads(done.stdout.strip().splitlines()[-1])
    return {
        "start_s": got["start_s"],
        "rss_tracking_mb": got["rss_peak_mb"],
        "tracking_windows": got["windows"],
        "window_mb": got["window_mb"],
    }

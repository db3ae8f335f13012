"""The paper's own figures beside lidarloc's, for ``lidarloc bench peers``: the paper measured on
KITTI odometry sequence 05 (2750 real scans, 250 runs, an 8-core Intel i9); lidarloc runs on the
built-in town laid along sequence 05's true trajectory (the same drive through a simulated
street; the KITTI 05 scans are not here), one seeded run of its first scans, and its S2M matches
scans against the whole map.

Where each figure is in the paper (``../shared/paper/scan-matching-particle-filter.tex``,
section "Simulation" unless said):

- metrics A–E as 75th percentile / worst run, in scans (the box plot, Figure "Localization
  performance", read out in the text): A 17 / 28 (line 309), B 14 / 24 (line 307), C 16 / 78
  (line 311), D – / 90 and E – / – (line 313; E is said to look like D);
- 0.4 s per scan on average, wall clock, the S2M block included, Intel i9 with 8 cores (line 323);
- 1.6 minutes (96 s) average wall clock of one scan matched against the whole map, with > 87 %
  of the scans matched within the 1 m resolution (section "Scan-to-map matching", line 212).
"""

from __future__ import annotations

import os
import time
from pathlib import Path

from ...core.config import Config
from ...core.sequences.factory import SourceSpec, open_sequence
from .common import data_dir
from .localize_report import PAPER

#: the figures quoted above (see the module docstring for where)
PAPER_FIGURES = {
    "metrics": {k: dict(v) for k, v in PAPER.items() if k in ("A", "B", "C", "D", "E")},
    "s_per_scan": 0.4,
    "cores": 8,
    "global_match_s": 96.0,
    "global_match_success": 0.87,
    "source": "KITTI odometry 05, 2750 scans, 250 runs",
}


def kitti05_spec(scans: int) -> SourceSpec | None:
    """The town laid along KITTI 05 (its poses and calibration in the data directory), or None."""
    root = data_dir() / "kitti_odometry_poses"
    poses, calib = root / "poses" / "05.txt", root / "calib" / "05.txt"
    if not (poses.is_file() and calib.is_file()):
        return None
    return SourceSpec(trajectory=poses, calib=calib, scans=scans)


def run(
    cfg: Config,
    scans: int,
    cache_root: Path | None = None,
    progress=None,
    required: bool = False,
    global_scans: int = 5,
) -> dict | None:
    """lidarloc's A–E, wall time per scan and PF latency over one run of the KITTI 05 town's first
    ``scans`` scans, and its whole-map S2M time on ``global_scans`` of them; None where the KITTI
    05 poses are absent (a one-line error if ``required``)."""
    from ...core.errors import LidarlocError
    from ...core.localizer import Localizer
    from ...core.runs.results import summarize_run
    from .peers_global import global_localization

    spec = kitti05_spec(scans)
    if spec is None:
        if required:
            raise LidarlocError(
                f"bench peers --paper: KITTI 05's poses not found under {data_dir() / 'kitti_odometry_poses'}"
            )
        return None
    matched = global_localization(spec, cfg, global_scans, cache_root, peers=False)
    seq = open_sequence(spec, cfg)
    with Localizer(seq, cfg, cache_root) as loc:
        loc.wait_ready()
        t0 = time.perf_counter()
        while not loc.done:
            loc.step()
            if progress is not None:
                progress(len(loc.records), len(seq))
        wall = time.perf_counter() - t0
        summary = summarize_run(loc, wall)
    return {
        "paper": PAPER_FIGURES,
        "lidarloc": {
            "source": seq.name,
            "scans": summary["scans"],
            "seed": cfg.seed,
            "metrics": summary["metrics"],
            "localized_at_scan": summary["localized_at_scan"],
            "rmse_after_localized_m": summary["rmse_after_localized_m"],
            "s_per_scan": wall / max(summary["scans"], 1),
            "pf_ms_median": summary["pf_ms_median"],
            "cores": os.cpu_count(),
            "global_match_s": None if matched["m3rsm_ms_median"] is None else matched["m3rsm_ms_median"] / 1e3,
            "global_match_success": matched["m3rsm_success"],
            "global_match_scans": matched["scans"],
            "global_match_err_m_median": matched["m3rsm_err_m_median"],
        },
        "speedup_per_scan": PAPER_FIGURES["s_per_scan"] / max(wall / max(summary["scans"], 1), 1e-9),
        "speedup_global_match": (
            PAPER_FIGURES["global_match_s"] * 1e3 / matched["m3rsm_ms_median"] if matched["m3rsm_ms_median"] else None
        ),
    }

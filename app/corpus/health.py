"""A drive's health from what its run wrote: the per-scan table (scans.csv) and the events
(events.json) of :mod:`lidarloc.core.runs.results`.

Whole-drive figures say whether a drive got worse; the stretches say where: each is
``{first_scan, last_scan, kind, figure, text}``, e.g. "scans 120–131: poor fit, inlier share
0.55". The kinds:

- ``poor_fit``: at least :data:`POOR_FIT_MIN_SCANS` localized scans in a row whose inlier share
  (scan points within d_max of the map at the estimate) is below ``localize.min_inlier_share``;
  the figure is the stretch's median share. Only localized scans count: before the first fix the
  estimate is a guess, and its poor fit says nothing about the map or the method. Shorter dips
  are left out: a crossing or a passing lorry hides the map for a scan or two on every drive.
- ``wrong``: scans the rule called localized while the truth was farther than the rule's
  tolerance (:data:`~lidarloc.core.rules.truth.FALSE_FIRE_M`); the figure is the median error (m).
  Needs truth.
- ``unlocalized``: scans not localized after the first fix (a withdrawal, a loss); the figure is
  the stretch's length in scans.
- ``late``: scans whose particle-filter step took longer than one LiDAR period
  (:data:`~lidarloc.core.runs.results.LATE_MS`); the figure is the median step (ms). A corpus runs
  on the replay clock, which waits for every scan: these are the scans that real time would have
  made late (wall-clock figures, so they vary from run to run, unlike the others). The drive's
  first scan is left out: its step compiles the filter's kernels.
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np

from ...core.rules.truth import FALSE_FIRE_M
from ...core.runs.results import LATE_MS

#: localized scans in a row below the inlier share before a poor fit is reported
POOR_FIT_MIN_SCANS = 10


def read_run(folder: Path) -> tuple[dict[str, np.ndarray], list[dict]]:
    """A run's scans.csv as columns (floats, NaN where empty) and its events.json."""
    folder = Path(folder)
    with open(folder / "scans.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    names = list(rows[0]) if rows else ["scan"]
    table = {n: np.array([float(r[n]) if r[n] != "" else np.nan for r in rows], dtype=float) for n in names}
    events_path = folder / "events.json"
    events = json.loads(events_path.read_text()) if events_path.is_file() else []
    return table, events


def runs_of(mask: np.ndarray, min_length: int = 1) -> list[tuple[int, int]]:
    """The (first, last) indices of each run of True in ``mask`` at least ``min_length`` long."""
    mask = np.asarray(mask, dtype=bool)
    edges = np.diff(np.r_[0, mask.astype(np.int8), 0])
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1) - 1
    return [(int(a), int(b)) for a, b in zip(starts, ends) if b - a + 1 >= min_length]


def _stretch(scans: np.ndarray, a: int, b: int, kind: str, figure: float, text: str) -> dict:
    first, last = int(scans[a]), int(scans[b])
    where = f"scan {first}" if first == last else f"scans {first}–{last}"
    return {"first_scan": first, "last_scan": last, "kind": kind, "figure": figure, "text": f"{where}: {text}"}


def stretches(table: dict[str, np.ndarray], min_inlier_share: float) -> list[dict]:
    """Every stretch of the drive (see the module docstring), in scan order."""
    n = len(table.get("scan", ()))
    if n == 0:
        return []
    scans = table["scan"]
    localized = table["localized"] == 1
    found = []
    share = table.get("inlier_share", np.full(n, np.nan))
    poor = localized & np.isfinite(share) & (share < min_inlier_share)
    for a, b in runs_of(poor, POOR_FIT_MIN_SCANS):
        median = float(np.median(share[a : b + 1]))
        found.append(_stretch(scans, a, b, "poor_fit", median, f"poor fit, inlier share {median:.2f}"))
    error = table.get("error_m", np.full(n, np.nan))
    for a, b in runs_of(localized & np.isfinite(error) & (error > FALSE_FIRE_M)):
        median = float(np.median(error[a : b + 1]))
        found.append(_stretch(scans, a, b, "wrong", median, f"localized but wrong, {median:.1f} m from the truth"))
    if localized.any():
        after = np.arange(n) > np.argmax(localized)
        for a, b in runs_of(after & ~localized):
            length = b - a + 1
            found.append(_stretch(scans, a, b, "unlocalized", float(length), f"not localized ({length} scans)"))
    pf_ms = table.get("pf_ms", np.full(n, np.nan))
    # not the first scan: its step compiles the filter's kernels in a fresh process (seconds)
    for a, b in runs_of(np.isfinite(pf_ms) & (pf_ms > LATE_MS) & (np.arange(n) > 0)):
        median = float(np.median(pf_ms[a : b + 1]))
        found.append(_stretch(scans, a, b, "late", median, f"late, filter step {median:.0f} ms"))
    return sorted(found, key=lambda s: (s["first_scan"], s["kind"]))


def drive_health(table: dict[str, np.ndarray], events: list[dict], min_inlier_share: float) -> dict:
    """The drive's health: its first fix (scan, and seconds after the first scan), when
    "localized" was withdrawn, false fires and RMSE while localized (None without truth), the
    counts of poor-fit and late scans, and its stretches."""
    n = len(table.get("scan", ()))
    localized = table["localized"] == 1 if n else np.zeros(0, dtype=bool)
    scans = table.get("scan", np.zeros(0))
    first_fix = None
    if localized.any():
        k = int(np.argmax(localized))
        first_fix = {"scan": int(scans[k]), "seconds": float(table["time"][k] - table["time"][0])}
    dropped = localized[:-1] & ~localized[1:] if n else np.zeros(0, dtype=bool)
    error = table.get("error_m", np.full(n, np.nan))
    truth = bool(np.isfinite(error).any())
    onsets = localized & ~np.r_[False, localized[:-1]] if n else localized
    right = error[localized & np.isfinite(error)]
    found = stretches(table, min_inlier_share)
    return {
        "first_fix": first_fix,
        "withdrawals": [int(k) for k in scans[1:][dropped]],
        "false_fires": int(np.sum(onsets & np.isfinite(error) & (error > FALSE_FIRE_M))) if truth else None,
        "wrong_scans": int(np.sum(localized & np.isfinite(error) & (error > FALSE_FIRE_M))) if truth else None,
        "rmse_localized_m": float(math.sqrt(np.mean(right**2))) if truth and right.size else None,
        "poor_fit_scans": sum(s["last_scan"] - s["first_scan"] + 1 for s in found if s["kind"] == "poor_fit"),
        "late_scans": sum(s["last_scan"] - s["first_scan"] + 1 for s in found if s["kind"] == "late"),
        "losses": sum(1 for e in events if e.get("kind") == "loss"),
        "stretches": found,
    }


def run_health(folder: Path, min_inlier_share: float) -> dict:
    """:func:`drive_health` of the run in ``folder``."""
    table, events = read_run(folder)
    return drive_health(table, events, min_inlier_share)

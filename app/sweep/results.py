"""A sweep's (or a tuning's) results: one row per run, one per combination, plots, the best settings.

``runs.csv`` / ``runs.json``: the swept entries (named by their keys, e.g. ``pf.sigma``), ``seed``,
then the run summary's own fields: A–E, ``success`` (localized and within 5 m of the truth from
then to the end of the drive), ``rmse_after_localized_m``, ``consistency_2sigma``, ``false_fire``,
``pf_ms_median``, ``s2m_ms_median``, …, and ``status`` / ``error`` (a failed run's one line).
``combinations.csv``: per combination the share of runs that succeeded and that fired falsely, and
the medians over its runs. ``best.yaml``: the combination whose runs all succeeded without a false
fire with the lowest median RMSE after localization, as a configuration file for ``--config``.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import yaml

from ...core.runs.metrics import METRIC_KEYS
from ..bench.localize_report import _within_5m_to_end
from .bookkeeping import DONE_FILE, Run, Tally, read_error
from .grid import Grid, typed
from .plots import median_or_none, write_plots

RUN_FIELDS = (
    *METRIC_KEYS,
    "success",
    "rmse_after_localized_m",
    "consistency_2sigma",
    "false_fire",
    "pf_ms_median",
    "s2m_ms_median",
    "localized_at_scan",
    "final_error_m",
    "ape_rmse_m",
    "n_particles_median",
    "scans",
)
MEDIANS = ("rmse_after_localized_m", "consistency_2sigma", *METRIC_KEYS, "pf_ms_median", "s2m_ms_median")


def run_row(keys: list[str], point: tuple, run_dir: str) -> dict:
    """One run's row: its grid point, then its summary's fields (or its error)."""
    row = {k: typed(v) if isinstance(v, str) else v for k, v in zip(keys, point)}
    row["seed"] = point[-1]
    folder = Path(run_dir)
    done = folder / DONE_FILE
    if not done.is_file():
        row.update({f: None for f in RUN_FIELDS}, status="failed" if read_error(folder) else "not run")
        row["error"] = read_error(folder)
        return row
    s = json.loads(done.read_text())
    metrics = s.get("metrics") or {}
    row.update({k: metrics.get(k) for k in METRIC_KEYS})
    row["success"] = _within_5m_to_end(folder) if (folder / "scans.csv").is_file() else None
    row.update({f: s.get(f) for f in RUN_FIELDS if f not in row})
    row.update(status="done", error=None, run=str(folder))
    return row


def _share(values) -> float | None:
    vals = [bool(v) for v in values if v is not None]
    return sum(vals) / len(vals) if vals else None


def combination_rows(keys: list[str], rows: list[dict]) -> list[dict]:
    """Per combination: runs, failed, success and false-fire shares, medians over its runs;
    ``met``: every seed ran, succeeded and fired no false alarm."""
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault(tuple(r[k] for k in keys), []).append(r)
    out = []
    for combo, rs in groups.items():
        done = [r for r in rs if r["status"] == "done"]
        row = dict(zip(keys, combo))
        row.update(runs=len(rs), done=len(done), failed=sum(r["status"] == "failed" for r in rs))
        row["success"] = _share(r["success"] for r in done)
        row["false_fire"] = _share(r["false_fire"] for r in done)
        row.update({f"{m}_median": median_or_none(r[m] for r in done) for m in MEDIANS})
        row["met"] = bool(done) and len(done) == len(rs) and all(r["success"] and not r["false_fire"] for r in done)
        out.append(row)
    return out


def best_combination(combos: list[dict]) -> dict | None:
    """The combination that met every seed with the lowest median RMSE (None: none met them all)."""
    met = [c for c in combos if c["met"] and c["rmse_after_localized_m_median"] is not None]
    return min(met, key=lambda c: c["rmse_after_localized_m_median"]) if met else None


def settings_yaml(entries: dict, header: str) -> str:
    """Dotted entries (``pf.sigma: 1``) as a nested configuration file for ``--config``."""
    nested: dict = {}
    for key, value in entries.items():
        section, _, name = key.partition(".")
        nested.setdefault(section, {})[name] = value
    return header + yaml.safe_dump(nested, sort_keys=False)


def overrides_dict(overrides) -> dict:
    """``--set`` entries as ``{key: typed value}``."""
    out = {}
    for item in overrides or ():
        key, _, value = item.partition("=")
        out[key.strip()] = typed(value.strip())
    return out


def write_table(path: Path, rows: list[dict]) -> None:
    fields = list(dict.fromkeys(k for r in rows for k in r))
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=fields)
        w.writeheader()
        w.writerows(rows)


def write_results(out_dir: Path, grid: Grid, planned: list[Run], settings, tally: Tally, plots: bool = True) -> dict:
    """Every results file of a sweep; returns its summary (also sweep.json)."""
    keys = list(grid.axes)
    rows = [run_row(keys, r.point, r.run_dir) for r in planned]
    combos = combination_rows(keys, rows)
    write_table(out_dir / "runs.csv", rows)
    (out_dir / "runs.json").write_text(json.dumps(rows, indent=1, default=str))
    write_table(out_dir / "combinations.csv", combos)
    best = best_combination(combos)
    base = overrides_dict(settings.overrides)
    best_entries = None
    if best is not None:
        best_entries = {**base, **{k: best[k] for k in keys}}
        preset = f" --preset {settings.preset}" if settings.preset else ""
        header = (
            f"# Best of the sweep in {out_dir}: every seed localized, no false fire, median RMSE after "
            f"localization {best['rmse_after_localized_m_median']:.3f} m.\n# Use it with: lidarloc run{preset} "
            "--config best.yaml\n"
        )
        (out_dir / "best.yaml").write_text(settings_yaml(best_entries, header))
    else:
        (out_dir / "best.yaml").unlink(missing_ok=True)
    if plots:
        write_plots(out_dir / "plots", keys, rows, combos)
    summary = {
        "grid": grid.to_dict(),
        "runs_per_combination": len(planned) // max(1, len(combos)),
        "runs": tally.total,
        "done": sum(r["status"] == "done" for r in rows),
        "done_now": tally.done,
        "failed": dict(tally.failed),
        "interrupted": tally.interrupted,
        "best": best,
        "best_settings": best_entries,
        "combinations": combos,
        "out": str(out_dir),
    }
    (out_dir / "sweep.json").write_text(json.dumps(summary, indent=1, default=str))
    return summary

"""The robustness matrix's outputs: one row per cell in ``cells.csv``, ``summary.json`` and
``report.md`` (a markdown table), and ``heatmap.png`` (success and RMSE per world and
configuration). The cells' own directories hold their runs and per-cell reports."""

from __future__ import annotations

import csv
import math
from pathlib import Path

from ...core.runs.metrics import METRIC_KEYS
from ...core.runs.results import write_json
from ...core.sequences.factory import SourceSpec

# One row per cell. The world columns are empty for the real drive (its world is what it is).
COLUMNS = (
    "cell",
    "source",
    "changes",
    "traffic",
    "sensor",
    "skew",
    "config",
    "runs",
    "scans",
    *[f"{k}_{s}" for k in METRIC_KEYS for s in ("median", "success")],
    "success",
    "rmse_after_localized_m",
    "consistency_2sigma",
    "false_fire_rate",
    "pf_ms_median",
    "localized_wrong_scans",
    "relocalizations",
    "spurious_relocalizations",
)
REAL_LABEL = "real KITTI drive"


def cell_row(cell, agg: dict) -> dict:
    """The figures of one cell (``agg``: its bench-localize summary)."""
    w = cell.world
    row = {
        "cell": cell.name,
        "source": "real" if w is None else "town",
        "changes": None if w is None else w.changes,
        "traffic": None if w is None else ("on" if w.traffic else "off"),
        "sensor": None if w is None else w.sensor,
        "skew": None if w is None else ("on" if w.skew else "off"),
        "config": cell.config,
        "runs": agg["runs"],
        "scans": agg["scans_per_run"],
    }
    for k in METRIC_KEYS:
        row[f"{k}_median"] = agg[k]["median"]
        row[f"{k}_success"] = agg[k]["success"]
    row.update(
        success=agg["within_5m_to_end_ratio"],
        rmse_after_localized_m=agg["rmse_after_localized_m_median"],
        consistency_2sigma=agg["consistency_2sigma"],
        false_fire_rate=agg["false_fire_rate"],
        pf_ms_median=agg["pf_ms_median"],
        localized_wrong_scans=agg.get("localized_wrong_scans"),
        relocalizations=agg.get("relocalizations"),
        spurious_relocalizations=agg.get("spurious_relocalizations"),
    )
    return row


def write_cell_table(
    out_dir: Path,
    cells: list,
    aggs: dict,
    matrix,
    town: SourceSpec,
    real: SourceSpec | None,
    runs: int,
    elapsed_s: float,
) -> dict:
    """Write cells.csv, summary.json, report.md and heatmap.png; returns the summary."""
    rows = [cell_row(c, aggs[c.name]) for c in cells]
    summary = {
        "source": town.describe(),
        "real_source": None if real is None else real.describe(),
        "matrix": matrix.to_dict(),
        "real": real is not None,
        "runs": runs,
        "scans": town.scans,
        "elapsed_s": round(elapsed_s, 1),
        "columns": list(COLUMNS),
        "cells": rows,
    }
    out_dir = Path(out_dir)
    with open(out_dir / "cells.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=COLUMNS)
        w.writeheader()
        for row in rows:
            w.writerow({k: "" if row[k] is None else row[k] for k in COLUMNS})
    write_json(out_dir / "summary.json", summary)
    _heatmap(out_dir / "heatmap.png", rows, list(matrix.configs))
    (out_dir / "report.md").write_text(_markdown(summary, rows))
    return summary


def row_label(row: dict) -> str:
    if row["source"] == "real":
        return REAL_LABEL
    return f"changes {row['changes']:g} · traffic {row['traffic']} · {row['sensor']} · skew {row['skew']}"


# ---------------------------------------------------------------------------------- markdown
def _pct(v) -> str:
    return "–" if v is None else f"{100 * v:.0f}%"


def _num(v, digits: int = 2) -> str:
    if v is None or not math.isfinite(v):
        return "–"
    return f"{v:.0f}" if float(v).is_integer() else f"{v:.{digits}f}"


def _metric(row: dict, k: str) -> str:
    median = row[f"{k}_median"]
    return f"{'fail' if median is None else _num(median)} ({_pct(row[f'{k}_success'])})"


def _n(count: int, noun: str) -> str:
    return f"{count} {noun}{'' if count == 1 else 's'}"


def _seeds(runs: int) -> str:
    return "0" if runs == 1 else f"0–{runs - 1}"


def _opt(value) -> str:
    return "–" if value is None else str(value)


def _markdown(summary: dict, rows: list[dict]) -> str:
    real = f" and {summary['real_source']}" if summary["real"] else ""
    lines = [
        f"# Robustness: {summary['source']}{real}",
        "",
        f"{_n(len(rows), 'cell')} × {_n(summary['runs'], 'run')} (seeds {_seeds(summary['runs'])}) of up to "
        f"{summary['scans']} scans, replay clock, against the prior map of the town as mapped"
        + (" (the real drive: the map of its own scans)." if summary["real"] else "."),
        "",
        "| changes | traffic | sensor | skew | config | success | RMSE after | A | B | C | D | E "
        "| 2σ consistency | false fires | wrong & localized | relocalized (spurious) | PF ms |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        world = (
            ("real drive", "–", "–", "–")
            if r["source"] == "real"
            else (f"{r['changes']:g}", r["traffic"], r["sensor"], r["skew"])
        )
        rmse = "–" if r["rmse_after_localized_m"] is None else f"{r['rmse_after_localized_m']:.2f} m"
        lines.append(
            f"| {' | '.join(world)} | {r['config']} | {_pct(r['success'])} | {rmse} | "
            + " | ".join(_metric(r, k) for k in METRIC_KEYS)
            + f" | {_pct(r['consistency_2sigma'])} | {_pct(r['false_fire_rate'])} | "
            f"{_opt(r['localized_wrong_scans'])} | {_opt(r['relocalizations'])} "
            f"({_opt(r['spurious_relocalizations'])}) | {_num(r['pf_ms_median'], 1)} |"
        )
    lines += [
        "",
        "- success: share of runs localized and within 5 m of the truth from then to the end of the drive.",
        "- RMSE after: position RMSE from the rule's first firing on, median over runs.",
        "- A–E: the paper's metrics in scans, median over runs (share of runs that met it); "
        "a median of 'fail': most runs never met it.",
        "- 2σ consistency: share of localized scans with the truth inside the filter's 2σ ellipse, "
        "median over runs (an honest covariance: ~86%).",
        "- false fires: share of runs whose localization rule fired more than 5 m from the truth.",
        "- wrong & localized: scans, over all runs, that the rule called localized more than 5 m from the truth.",
        "- relocalized (spurious): times, over all runs, the whole-map check moved the filter (of those, "
        "from an estimate within 5 m of the truth).",
        "- PF ms: the particle filter's step, median over every scan of every run.",
        "- Each cell's runs and report: cells/NAME/.",
        "",
        "![success and RMSE per cell](heatmap.png)",
        "",
    ]
    return "\n".join(lines)


# ---------------------------------------------------------------------------------- heat map
def _heatmap(path: Path, rows: list[dict], configs: list[str]) -> None:
    """Two panels, one row per world (the real drive last) and one column per configuration:
    success (share of runs) and the RMSE after localization (m, median over runs)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    labels = list(dict.fromkeys(row_label(r) for r in rows))
    success = np.full((len(labels), len(configs)), np.nan)
    rmse = np.full_like(success, np.nan)
    for r in rows:
        i, j = labels.index(row_label(r)), configs.index(r["config"])
        success[i, j] = np.nan if r["success"] is None else r["success"]
        rmse[i, j] = np.nan if r["rmse_after_localized_m"] is None else r["rmse_after_localized_m"]
    height = max(2.5, 0.32 * len(labels) + 1.6)
    fig, axes = plt.subplots(1, 2, figsize=(11, height), sharey=True)
    # the RMSE's colours stop at 5 m, the success bound: beyond it a run has failed anyway
    rmse_top = float(np.clip(np.nanmax(rmse), 0.5, 5.0)) if np.isfinite(rmse).any() else 1.0
    panels = (
        (axes[0], success, "success (share of runs)", "RdYlGn", (0.0, 1.0), lambda v: f"{100 * v:.0f}%"),
        (axes[1], rmse, "RMSE after localization (m)", "viridis_r", (0.0, rmse_top), lambda v: f"{v:.2f}"),
    )
    for ax, data, title, cmap, (vmin, vmax), fmt in panels:
        colours = plt.get_cmap(cmap).copy()
        colours.set_bad("#d0d0d0")  # grey: no value (never localized, or no truth)
        image = ax.imshow(np.ma.masked_invalid(data), cmap=colours, vmin=vmin, vmax=vmax, aspect="auto")
        for (i, j), v in np.ndenumerate(data):
            r, g, b, _ = image.cmap(image.norm(v)) if np.isfinite(v) else (1, 1, 1, 1)
            dark = 0.299 * r + 0.587 * g + 0.114 * b < 0.5
            ax.text(
                j,
                i,
                "–" if not np.isfinite(v) else fmt(v),
                ha="center",
                va="center",
                fontsize=7,
                color="white" if dark else "black",
            )
        ax.set_xticks(range(len(configs)), configs)
        ax.set_title(title, fontsize=10)
        fig.colorbar(image, ax=ax, fraction=0.05, pad=0.02)
    axes[0].set_yticks(range(len(labels)), labels, fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)

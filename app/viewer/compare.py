"""The Compare folder's table: two runs' summary figures side by side — the paper's metrics A–E,
the position RMSE after localization, the PF latency — from each run's ``summary.json`` where it
has one, else computed from its recorded steps (a viewer run, or a process that was killed)."""

from __future__ import annotations

import numpy as np

from ...core.runs.metrics import METRIC_KEYS, ScanLog, compute_metrics

from .style import css

ROWS = (("A", "A: scans until localized (sum)"), ("B", "B: scans until the rule"),
        ("C", "C: … within 5 m for 10"), ("D", "D: … within 5 m for 50"), ("E", "E: … within 2.5 m for 50"),
        ("rmse_after_localized_m", "RMSE after localized (m)"), ("pf_ms_median", "PF latency, median (ms)"),
        ("s2m_ms_median", "S2M latency, median (ms)"), ("scans", "scans"))


def figures_of(summary: dict | None, series: dict | None = None) -> dict:
    """The table's figures of one run: its summary, else computed from its recorded ``series``
    (:meth:`RecordedRun.series`, with ``localized``)."""
    if summary:
        out = {k: summary.get(k) for k, _ in ROWS}
        out.update({k: (summary.get("metrics") or {}).get(k) for k in METRIC_KEYS})
        return out
    if series is None or not len(series.get("scan", ())):
        return {}
    err = np.asarray(series["error"], float)
    loc = np.asarray(series.get("localized", np.zeros(len(err), bool)), bool)
    metrics = compute_metrics(ScanLog(loc, err))
    after = err[loc & np.isfinite(err)]
    pf = np.asarray(series["pf_ms"], float)
    return {**{k: metrics.get(k) for k in METRIC_KEYS},
            "rmse_after_localized_m": float(np.sqrt(np.mean(after ** 2))) if after.size else None,
            "pf_ms_median": float(np.median(pf)) if pf.size else None, "s2m_ms_median": None,
            "scans": int(len(err))}


def _cell(v) -> str:
    if v is None:
        return "–"
    if isinstance(v, float):
        return f"{v:.2f}" if abs(v) < 100 else f"{v:.0f}"
    return str(v)


def summary_table(runs: list[tuple[str, dict]], colours=()) -> str:
    """Markdown: one column per (label, figures of :func:`figures_of`)."""
    head = []
    for i, (label, _) in enumerate(runs):
        c = colours[i] if i < len(colours) else None
        head.append(f"<span style='color:{css(c)}'>{label}</span>" if c is not None else label)
    lines = ["| | " + " | ".join(head) + " |", "|---" * (len(runs) + 1) + "|"]
    for key, label in ROWS:
        lines.append(f"| {label} | " + " | ".join(_cell((fig or {}).get(key)) for _, fig in runs) + " |")
    return "\n".join(lines)

"""The Compare folder's table: two runs' figures side by side, over the same steps, following the
runs as they grow.

A branch and its original share every step before the branch point: figures over whole runs
mix those in and differ only by what came after. So the table compares the steps from the
branch point (step 0 for two separate runs) to each run's newest step: the position
RMSE while localized, the share of those steps localized, the largest error while localized,
the false fires (onsets of localization more than 5 m from the truth: the summaries'
``false_fire`` test) and the PF latency. The paper's metrics A–E count scans from a run's start,
so they are computed from step 0 to the same end. Everything is read from the recorded steps
(a few per-step fields of each recording), so the table follows a branch while it plays."""

from __future__ import annotations

import numpy as np

from ...core.rules.truth import FALSE_FIRE_M
from ...core.runs.metrics import METRIC_KEYS, ScanLog, compute_metrics
from .style import css

ROWS = (
    ("A", "A: scans spent not localized (every try)"),
    ("B", "B: scans until first localized"),
    ("C", "C: scans until within 5 m for 10 scans"),
    ("D", "D: … within 5 m for 50 scans"),
    ("E", "E: … within 2.5 m for 50 scans"),
    ("rmse_after_localized_m", "RMSE while localized (m)"),
    ("localized_share", "steps localized"),
    ("max_error_localized_m", "max error while localized (m)"),
    ("false_fires", "false fires (> 5 m)"),
    ("pf_ms_median", "PF latency, median (ms)"),
    ("scans", "steps compared"),
)


def window_figures(cols: dict, start: int) -> dict:
    """The table's figures of one run from its per-step ``cols`` (``error``, ``localized``,
    ``pf_ms`` of steps ``first`` … end − 1, :meth:`RecordedRun.columns`): A–E over all of them
    (none where a rolling window dropped the first steps: they count from step 0), the rest over
    the steps from ``start`` on."""
    first = int(cols.get("first", 0))
    err = np.asarray(cols["error"], float)
    loc = np.asarray(cols["localized"], bool)
    if not len(err):
        return {}
    metrics = compute_metrics(ScanLog(loc, err)) if first == 0 else {}
    start = max(start - first, 0)
    e, lo = err[start:], loc[start:]
    known = lo & np.isfinite(e)
    onset = lo & ~np.r_[loc[start - 1] if start > 0 else False, lo[:-1]]
    pf = np.asarray(cols["pf_ms"], float)[start:]
    pf = pf[np.isfinite(pf)]
    has_truth = bool(np.isfinite(e).any())
    return {
        **{k: metrics.get(k) for k in METRIC_KEYS},
        "rmse_after_localized_m": float(np.sqrt(np.mean(e[known] ** 2))) if known.any() else None,
        "localized_share": f"{100 * lo.mean():.0f}%" if len(lo) else None,
        "max_error_localized_m": float(e[known].max()) if known.any() else None,
        "false_fires": int(np.sum(onset & np.isfinite(e) & (e > FALSE_FIRE_M))) if has_truth else None,
        "pf_ms_median": float(np.median(pf)) if pf.size else None,
        "scans": int(len(e)),
    }


def _cell(v) -> str:
    if v is None:
        return "–"
    if isinstance(v, float):
        return f"{v:.2f}" if abs(v) < 100 else f"{v:.0f}"
    return str(v)


def summary_table(runs: list[tuple[str, dict]], colours=(), caption: str = "") -> str:
    """Markdown: one column per (label, figures of :func:`window_figures`), ``caption`` above."""
    head = []
    for i, (label, _) in enumerate(runs):
        c = colours[i] if i < len(colours) else None
        head.append(f"<span style='color:{css(c)}'>{label}</span>" if c is not None else label)
    lines = [caption, ""] if caption else []
    lines += ["| | " + " | ".join(head) + " |", "|---" * (len(runs) + 1) + "|"]
    for key, label in ROWS:
        lines.append(f"| {label} | " + " | ".join(_cell((fig or {}).get(key)) for _, fig in runs) + " |")
    return "\n".join(lines)


def compare_markdown(primary, reference, labels: tuple[str, str], colours=(None, None)) -> str:
    """The Compare folder's content for two :class:`~lidarloc.app.viewer.recorded.RecordedRun`:
    each run's steps from where ``primary`` branched (0 for two separate runs) to its newest."""
    start = int(primary.start) if primary.parent is not None else 0
    a, b = primary.columns(), reference.columns()
    ends = [c["first"] + len(c["error"]) for c in (a, b)]
    spans = ", ".join(
        f"{label} {max(start, c['first'])}…{n - 1}" if n > max(start, c["first"]) else f"{label} none yet"
        for label, c, n in ((labels[0], a, ends[0]), (labels[1], b, ends[1]))
    )
    where = f"after the branch point, steps from {start}" if start else "steps from 0"
    window = (
        "; a rolling window dropped the first steps of a run (the recording budget): A–E need them"
        if a["first"] or b["first"]
        else ""
    )
    caption = f"<small>{where} ({spans}); A–E count from step 0{window}</small>"
    return summary_table(
        [
            (labels[0], window_figures(a, min(start, ends[0]))),
            (labels[1], window_figures(b, min(start, ends[1]))),
        ],
        colours=colours,
        caption=caption,
    )

"""``lidarloc compare A B …``: the summary figures of two or more runs side by side, and an overlay
plot of their per-scan curves for papers.

A run is any results folder: a recorded run (with ``recording/``, from ``lidarloc run``, the viewer
or a branch) or a plain one (``summary.json`` + ``scans.csv``). The figures are the run's own
``summary.json`` where it has one; a recording without one (a viewer run, a process that was
killed) gets the same figures computed from its recorded steps.

Figures (one row each): the paper's metrics A–E, success (the rule met, and every estimate from
then to the end within 5 m of the truth: the benchmarks' "within 5 m to the end"), the position
RMSE over the localized scans, evo's APE and RPE RMSE over every scan (the summary's),
consistency_2sigma, false_fire, the PF step's median latency and the number of scans.

The plot (PNG): the trajectories in the map's frame (x–y; the truth dashed), the error, the
position std and N_eff as a share of the particles against the scan (a branch's curves start at its scan),
one colour per run (faint before the rule first fired); the scans where the rule fired are
marked (★) on every panel. The curves' axes are logarithmic; the std is floored at 1 mm.
"""

from __future__ import annotations

import csv
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.table import Table

from ..core.errors import LidarlocError
from ..core.runs.metrics import METRIC_KEYS, ScanLog, compute_metrics, confidence_metrics
from .console import emit_json

#: a run has succeeded when every estimate from the rule's first firing to the end is this close (m)
SUCCESS_M = 5.0
#: the std curve's floor on its log axis (m): a cloud collapsed onto one particle has a std of ~0
STD_FLOOR_M = 1e-3

#: (key, row label, format) of the table's rows, in order
ROWS = (
    *((k, f"{k} (scans)", "int") for k in METRIC_KEYS),
    ("success", "success (≤ 5 m to the end)", "bool"),
    ("rmse_after_localized_m", "RMSE after localized (m)", "m"),
    ("ape_rmse_m", "APE RMSE, evo, every scan (m)", "m"),
    ("rpe_rmse_m", "RPE RMSE, evo, 1 scan (m)", "m"),
    ("consistency_2sigma", "consistency 2σ", "share"),
    ("false_fire", "false fire", "bool"),
    ("pf_ms_median", "PF latency median (ms)", "ms"),
    ("scans", "scans", "int"),
)


@dataclass
class RunCurves:
    """One run's per-step series (index = step), NaN where unknown."""

    scan: np.ndarray
    x: np.ndarray
    y: np.ndarray
    gt_x: np.ndarray
    gt_y: np.ndarray
    error_m: np.ndarray
    std_m: np.ndarray  # max of the x and y std
    n_eff_share: np.ndarray
    localized: np.ndarray  # bool
    pf_ms: np.ndarray
    inside_2sigma: list  # bool | None per step


@dataclass
class RunFigures:
    path: Path
    label: str
    recorded: bool
    figures: dict
    curves: RunCurves = field(repr=False)
    origin: np.ndarray = field(default_factory=lambda: np.zeros(3), repr=False)


# ------------------------------------------------------------------------------------ reading
def _float(v: str) -> float:
    return float(v) if v not in ("", None) else math.nan


def _bool_or_none(v: str):
    return None if v in ("", None) else v in ("1", "True", "true")


def _curves_from_csv(path: Path) -> RunCurves:
    try:
        with open(path, newline="") as f:
            rows = list(csv.DictReader(f))
    except OSError as exc:
        raise LidarlocError(f"{path}: cannot read ({exc.strerror})") from None
    try:
        col = lambda name: np.array([_float(r[name]) for r in rows], float)  # noqa: E731
        return RunCurves(
            scan=np.array([int(r["scan"]) for r in rows], np.int64),
            x=col("x"),
            y=col("y"),
            gt_x=col("gt_x"),
            gt_y=col("gt_y"),
            error_m=col("error_m"),
            std_m=np.fmax(col("std_x"), col("std_y")),
            n_eff_share=col("n_eff_share"),
            localized=np.array([r["localized"] in ("1", "True", "true") for r in rows], bool),
            pf_ms=col("pf_ms"),
            inside_2sigma=[_bool_or_none(r.get("inside_2sigma", "")) for r in rows],
        )
    except (KeyError, ValueError) as exc:
        raise LidarlocError(f"{path}: not a lidarloc per-scan log ({exc})") from None


def _curves_from_recording(rec) -> RunCurves:
    pose = rec.mean_pose
    gt = rec.gt_pose
    std = rec.std_xyz
    n = np.maximum(rec.n_particles.astype(float), 1.0)
    inside = rec.inside_2sigma
    return RunCurves(
        scan=rec.scan_index.astype(np.int64),
        x=pose[:, 0, 3].copy(),
        y=pose[:, 1, 3].copy(),
        gt_x=gt[:, 0, 3].copy(),
        gt_y=gt[:, 1, 3].copy(),
        error_m=rec.error_m.astype(float),
        std_m=np.fmax(std[:, 0], std[:, 1]),
        n_eff_share=rec.n_eff / n,
        localized=rec.localized.astype(bool),
        pf_ms=rec.pf_ms.astype(float),
        inside_2sigma=[None if v < 0 else bool(v) for v in inside],
    )


def success(curves: RunCurves) -> bool | None:
    """The rule fired and every estimate from then to the end is within 5 m of the truth; None
    without ground truth."""
    err = curves.error_m
    if not len(err) or not np.isfinite(err).any():
        return None
    first = np.flatnonzero(curves.localized)
    if not first.size:
        return False
    tail = err[first[0] :]
    return bool(np.all(np.isfinite(tail) & (tail <= SUCCESS_M)))


def figures_from_curves(c: RunCurves) -> dict:
    """The summary figures of a run that has no summary.json (the same rules as summarize_run)."""
    metrics = compute_metrics(ScanLog(c.localized, c.error_m))
    after = c.error_m[c.localized]
    after = after[np.isfinite(after)]
    pf = c.pf_ms[np.isfinite(c.pf_ms)]
    return {
        "metrics": metrics,
        "scans": int(len(c.scan)),
        "rmse_after_localized_m": float(np.sqrt(np.mean(after**2))) if after.size else None,
        "pf_ms_median": float(np.median(pf)) if pf.size else None,
        **confidence_metrics(c.localized, c.error_m, c.inside_2sigma),
    }


def _figures(summary: dict, curves: RunCurves) -> dict:
    metrics = summary.get("metrics") or {}
    out = {k: metrics.get(k) for k in METRIC_KEYS}
    out["success"] = success(curves)
    for key in (
        "rmse_after_localized_m",
        "ape_rmse_m",
        "rpe_rmse_m",
        "consistency_2sigma",
        "false_fire",
        "pf_ms_median",
        "scans",
    ):
        out[key] = summary.get(key)
    return out


def load_run(path) -> RunFigures:
    """A results folder's figures and curves (one-line LidarlocError for anything else)."""
    from ..core.runs import recording

    path = Path(path).expanduser()
    if not path.is_dir():
        raise LidarlocError(f"{path}: no such run folder")
    if path.name == recording.FOLDER and (path / recording.INDEX).is_file():
        path = path.parent
    summary = None
    if (path / recording.FOLDER).is_dir():
        rec = recording.open(path)
        curves = _curves_from_recording(rec)
        summary = rec.summary
        recorded = True
    elif (path / "scans.csv").is_file():
        curves = _curves_from_csv(path / "scans.csv")
        recorded = False
    else:
        raise LidarlocError(f"{path}: not a lidarloc run folder (no recording/ and no scans.csv)")
    if summary is None and (path / "summary.json").is_file():
        try:
            summary = json.loads((path / "summary.json").read_text())
        except (OSError, ValueError) as exc:
            raise LidarlocError(f"{path / 'summary.json'}: unreadable ({exc})") from None
    if summary is not None and not isinstance(summary, dict):
        raise LidarlocError(f"{path / 'summary.json'}: not a run summary")
    if summary is None:
        summary = figures_from_curves(curves)
    origin = np.asarray(summary.get("map_origin_m") or [0.0, 0.0, 0.0], float)
    return RunFigures(
        path=path, label=path.name, recorded=recorded, figures=_figures(summary, curves), curves=curves, origin=origin
    )


def distinct_labels(paths: list[Path]) -> list[str]:
    """Each path's label: its folder's name, or, where names repeat (the viewer names every first
    run ``run``), the shortest ending of its path that no other path shares (``a/run``,
    ``b/run``); the same folder given twice is numbered."""
    parts = [Path(p).resolve().parts for p in paths]
    labels = []
    for i, mine in enumerate(parts):
        others = [p for j, p in enumerate(parts) if j != i and p != mine]
        k = 1
        while k < len(mine) and any(p[-k:] == mine[-k:] for p in others):
            k += 1
        labels.append("/".join(mine[-k:]) if k < len(mine) else str(Path(*mine)))
    return [
        f"{label} #{labels[:i].count(label) + 1}" if labels.count(label) > 1 else label
        for i, label in enumerate(labels)
    ]


def _labels(runs: list[RunFigures]) -> None:
    for r, label in zip(runs, distinct_labels([r.path for r in runs])):
        r.label = label


# ------------------------------------------------------------------------------------ output
def _fmt(value, kind: str) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "—"
    if kind == "int":
        return str(int(value))
    if kind == "bool":
        return "yes" if value else "no"
    if kind == "m":
        return f"{value:.2f}"
    if kind == "share":
        return f"{100 * value:.0f} %"
    return f"{value:.1f}"


def table(runs: list[RunFigures]) -> Table:
    t = Table(title="runs compared", show_lines=False)
    t.add_column("figure")
    for r in runs:
        t.add_column(r.label, justify="right")
    for key, label, kind in ROWS:
        t.add_row(label, *(_fmt(r.figures.get(key), kind) for r in runs))
    return t


def _marks(c: RunCurves) -> np.ndarray:
    """Steps at which the rule fired (an onset of "localized"). A run localized at its first step
    is a branch that inherited it: the rule fired in its original, not there."""
    loc = c.localized
    return np.flatnonzero(loc & ~np.r_[True, loc[:-1]])


def plot(runs: list[RunFigures], out_png: Path) -> None:
    """The overlay plot: trajectories (truth dashed) and error, std, N_eff share against the step."""
    import matplotlib

    matplotlib.use("Agg")  # files only, no display
    import matplotlib.pyplot as plt

    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    fig = plt.figure(figsize=(12, 8), dpi=120)
    gs = fig.add_gridspec(3, 2, width_ratios=(1.1, 1.0))
    ax_xy = fig.add_subplot(gs[:, 0])
    axes = [fig.add_subplot(gs[i, 1]) for i in range(3)]
    for i in (1, 2):
        axes[i].sharex(axes[0])
    truth_drawn = False
    for j, r in enumerate(runs):
        c, col = r.curves, colors[j % len(colors)]
        ox, oy = r.origin[0], r.origin[1]
        # against the source's scan: a branch's curves start where it left its original
        step = np.asarray(c.scan, dtype=np.float64)
        marks = _marks(c)
        if np.isfinite(c.gt_x).any():
            ax_xy.plot(
                c.gt_x + ox,
                c.gt_y + oy,
                "--",
                color=col,
                lw=1.0,
                alpha=0.8,
                label=None if truth_drawn else "truth (dashed)",
            )
            truth_drawn = True
        # before the rule first fires the estimate jumps between hypotheses: drawn faint
        k0 = int(marks[0]) if marks.size else len(c.x)
        ax_xy.plot(c.x[: k0 + 1] + ox, c.y[: k0 + 1] + oy, "-", color=col, lw=0.8, alpha=0.35)
        ax_xy.plot(c.x[k0:] + ox, c.y[k0:] + oy, "-", color=col, lw=1.4, label=r.label)
        ax_xy.plot(c.x[marks] + ox, c.y[marks] + oy, "*", color=col, ms=11, mec="black", mew=0.6)
        # a collapsed cloud has a std of ~0: floored so that a log axis can show it
        std = np.maximum(c.std_m, STD_FLOOR_M)
        for ax, series in zip(axes, (c.error_m, std, 100 * c.n_eff_share)):
            ax.plot(step, series, "-", color=col, lw=1.2)
            for m in marks:
                ax.axvline(step[m], color=col, lw=0.8, ls=":")
            if marks.size:
                ax.plot(step[marks], series[marks], "*", color=col, ms=9, mec="black", mew=0.5)
    ax_xy.set_xlabel("x (m, map frame)")
    ax_xy.set_ylabel("y (m, map frame)")
    ax_xy.set_aspect("equal", adjustable="datalim")
    ax_xy.set_title("trajectories (★ localized)", fontsize=10)
    ax_xy.legend(fontsize=8, loc="best")
    for ax, label in zip(
        axes, ("error (m)", f"position std (m, ≥ {STD_FLOOR_M * 1000:.0f} mm)", "N_eff (% of particles)")
    ):
        ax.set_ylabel(label)
        ax.grid(alpha=0.3, which="both")
        ax.set_yscale("log")
    # fixed decades: a flat curve (one particle holding the weight) must not zoom into noise
    axes[1].set_ylim(bottom=STD_FLOOR_M * 0.7)
    shares = [100 * np.nanmin(r.curves.n_eff_share) for r in runs if np.isfinite(r.curves.n_eff_share).any()]
    axes[2].set_ylim(min([0.1] + [v / 2 for v in shares if v > 0]), 150)
    axes[-1].set_xlabel("scan")
    fig.tight_layout()
    try:
        fig.savefig(out_png)
    except OSError as exc:
        raise LidarlocError(f"{out_png}: cannot write the plot ({exc.strerror})") from None
    finally:
        plt.close(fig)


def as_dict(runs: list[RunFigures], out_png: Path | None) -> dict:
    from ..core.runs.results import json_safe

    return json_safe(
        {
            "runs": [{"run": str(r.path), "label": r.label, "recorded": r.recorded, **r.figures} for r in runs],
            "plot": None if out_png is None else str(out_png),
        }
    )


def compare_runs(run_dirs, out_png: Path | None = None, as_json: bool = False, console: Console | None = None) -> dict:
    """Compare runs: a table on ``console`` (or, ``as_json``, the same as JSON on stdout) and, with
    ``out_png``, the overlay plot. Returns the JSON's content."""
    if len(run_dirs) < 2:
        raise LidarlocError("compare needs at least two run folders")
    runs = [load_run(p) for p in run_dirs]
    _labels(runs)
    if out_png is not None:
        out_png = Path(out_png)
        if out_png.suffix.lower() != ".png":
            raise LidarlocError(f"{out_png}: the plot is written as PNG (name it .png)")
        out_png.parent.mkdir(parents=True, exist_ok=True)
        plot(runs, out_png)
    data = as_dict(runs, out_png)
    if as_json:
        emit_json(data)
    else:
        console = console or Console()
        console.print(table(runs))
        if out_png is not None:
            console.print(f"plot: {out_png}")
    return data

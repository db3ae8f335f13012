"""``lidarloc bench localize``'s report: summary.json, runs.csv and report.md of a benchmark
directory's runs, with the metrics' box plot and the latency histogram."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np

from ...core.config import Config
from ...core.runs.metrics import METRIC_KEYS, aggregate, aggregate_confidence
from ...core.runs.results import write_json
from ...core.sequences.factory import SourceSpec
from .common import median

# The paper's figures for KITTI 05, 250 runs (Simulation section), for the report table.
PAPER = {
    "B": {"p75": 14, "max": 24},
    "A": {"p75": 17, "max": 28},
    "C": {"p75": 16, "max": 78},
    "D": {"p75": None, "max": 90},
    "E": {"p75": None, "max": None},
    "latency_s": 0.4,
}


def _within_5m_to_end(run_dir: Path) -> bool | None:
    """The rule was met, and from that scan to the end of the drive every
    estimate is within 5 m of the truth (None without ground truth)."""
    with open(run_dir / "scans.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    if not rows or rows[0]["error_m"] == "":
        return None
    first = next((i for i, r in enumerate(rows) if r["localized"] in ("1", "True", "true")), None)
    return first is not None and all(r["error_m"] != "" and float(r["error_m"]) <= 5.0 for r in rows[first:])


def write_report(
    out_dir: Path, summaries: list[dict], cfg: Config, spec: SourceSpec, preset: str | None = None, plots: bool = True
) -> dict:
    """summary.json, runs.csv and report.md of the runs' ``summaries`` in ``out_dir`` (and with
    ``plots`` the metrics' box plot and the latency histogram); returns the summary."""
    per_run = [dict(s["metrics"], seed=s["seed"]) for s in summaries]
    agg = aggregate(per_run)
    # whether the filter's own uncertainty can be trusted (lidarloc.core.runs.metrics): the median run's
    # share of localized scans inside the 2σ ellipse, and the share of runs that fired > 5 m off
    agg.update(aggregate_confidence(summaries))
    within = [_within_5m_to_end(out_dir / "runs" / f"seed_{s['seed']:03d}") for s in summaries]
    known = [w for w in within if w is not None]
    agg["within_5m_to_end_ratio"] = sum(known) / len(known) if known else None
    # a run that never localizes has no "after": it counts as a failure in the ratio above
    agg["rmse_after_localized_m_median"] = median(s["rmse_after_localized_m"] for s in summaries)
    # evo's figures of each run's written trajectory (every scan, no alignment)
    agg["ape_rmse_m_median"] = median(s.get("ape_rmse_m") for s in summaries)
    agg["rpe_rmse_m_median"] = median(s.get("rpe_rmse_m") for s in summaries)
    # never green while wrong (lidarloc.core.rules.integrity): sums over runs; None where a run had no truth
    for key in ("relocalizations", "spurious_relocalizations", "localized_wrong_scans"):
        values = [s.get(key) for s in summaries]
        agg[key] = None if not values or any(v is None for v in values) else int(sum(values))
    agg["localized_at_scan_median"] = median(s["localized_at_scan"] for s in summaries)
    # a run that never localized waits for ever: it counts, as the longest wait (None when it is the median)
    waits = [
        math.inf if s["localized_at_s"] is None else s["localized_at_s"] for s in summaries if "localized_at_s" in s
    ]
    mid = float(np.median(waits)) if waits else math.inf
    agg["localized_at_s_median"] = mid if math.isfinite(mid) else None
    pf_ms = np.concatenate([np.load(out_dir / "runs" / f"seed_{s['seed']:03d}" / "pf_ms.npy") for s in summaries])
    s2m_parts = [np.load(out_dir / "runs" / f"seed_{s['seed']:03d}" / "s2m_ms.npy") for s in summaries]
    s2m_ms = np.concatenate(s2m_parts) if s2m_parts else np.array([])
    agg["pf_ms_median"] = float(np.median(pf_ms)) if pf_ms.size else None
    agg["s2m_ms_median"] = float(np.median(s2m_ms)) if s2m_ms.size else None
    agg["source"] = spec.describe()
    agg["world"] = summaries[0].get("world") if summaries else None  # the town's drive (None: other sources)
    agg["preset"] = preset
    agg["s2m"] = cfg.s2m.enabled
    agg["particles"] = cfg.pf.n_particles
    agg["scans_per_run"] = summaries[0]["scans"] if summaries else 0
    with open(out_dir / "runs.csv", "w", newline="") as f:
        w = csv.writer(f)
        metric_cols = [*METRIC_KEYS, "rmse_pos_after_D_m", "rmse_yaw_after_D_deg"]
        w.writerow(
            [
                "seed",
                *metric_cols,
                "pf_ms_median",
                "false_positives",
                "losses",
                "localized_at_scan",
                "rmse_after_localized_m",
                "within_5m_to_end",
                "consistency_2sigma",
                "false_fire",
                "relocalizations",
                "spurious_relocalizations",
                "localized_wrong_scans",
            ]
        )
        for s, ok in zip(summaries, within):
            m = s["metrics"]
            w.writerow(
                [
                    s["seed"],
                    *["" if m.get(k) is None else m[k] for k in metric_cols],
                    f"{s['pf_ms_median']:.2f}",
                    s["false_positives"],
                    s["losses"],
                    "" if s["localized_at_scan"] is None else s["localized_at_scan"],
                    "" if s["rmse_after_localized_m"] is None else f"{s['rmse_after_localized_m']:.3f}",
                    "" if ok is None else int(ok),
                    "" if s.get("consistency_2sigma") is None else f"{s['consistency_2sigma']:.3f}",
                    "" if s.get("false_fire") is None else int(s["false_fire"]),
                    *[
                        "" if s.get(k) is None else s[k]
                        for k in ("relocalizations", "spurious_relocalizations", "localized_wrong_scans")
                    ],
                ]
            )
    write_json(out_dir / "summary.json", agg)
    if plots:
        _plots(out_dir, per_run, pf_ms, s2m_ms, agg)
    _report(out_dir, agg, plots)
    return agg


def _plots(out_dir: Path, per_run: list[dict], pf_ms: np.ndarray, s2m_ms: np.ndarray, agg: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    data = [[r[k] for r in per_run if r.get(k) is not None] for k in METRIC_KEYS]
    labels = [f"{k}\n{100 * agg[k]['success']:.0f}% met" for k in METRIC_KEYS]
    ax.boxplot([d if d else [np.nan] for d in data], tick_labels=labels, whis=(0, 100))
    ax.set_ylabel("scans")
    ax.set_title(
        f"Localization metrics over {len(per_run)} runs ({'S2M' if agg['s2m'] else 'no S2M'}); "
        "whiskers = min/max of runs that met the metric"
    )
    fig.tight_layout()
    fig.savefig(out_dir / "metrics_boxplot.png", dpi=120)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(7, 4))
    ax.hist(pf_ms, bins=50, alpha=0.8, label=f"PF step (median {np.median(pf_ms):.1f} ms)")
    if s2m_ms.size:
        ax.hist(s2m_ms, bins=50, alpha=0.6, label=f"S2M match (median {np.median(s2m_ms):.1f} ms)")
    ax.set_xlabel("latency per scan [ms]")
    ax.set_ylabel("scans")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out_dir / "latency_hist.png", dpi=120)
    plt.close(fig)


def _world_text(world: dict) -> str:
    return ", ".join(f"{k} {v}" for k, v in world.items())


def _metres(value) -> str:
    return "–" if value is None else f"{value:.2f} m"


def _count(value) -> str:
    return "–" if value is None else str(value)


def _report(out_dir: Path, agg: dict, plots: bool = True) -> None:
    def fmt(v):
        return "fail" if v is None else (f"{v:.0f}" if float(v).is_integer() else f"{v:.2f}")

    lines = [
        f"# Localization benchmark: {agg['source']}",
        "",
        f"{agg['runs']} runs × {agg['scans_per_run']} scans, {agg['particles']} particles, "
        f"{'preset ' + agg['preset'] + ', ' if agg['preset'] else ''}"
        f"S2M {'on' if agg['s2m'] else 'off'}, replay clock. Metrics in scans (lidarloc.core.runs.metrics).",
        *([f"World of the drive: {_world_text(agg['world'])}."] if agg.get("world") else []),
        "",
        "| metric | median | 75th pct | max | success | paper 75th | paper max |",
        "|---|---|---|---|---|---|---|",
    ]
    for k in METRIC_KEYS:
        a, p = agg[k], PAPER[k]
        lines.append(
            f"| {k} | {fmt(a['median'])} | {fmt(a['p75'])} | {fmt(a['max'])} | {100 * a['success']:.0f}% | "
            f"{p['p75'] if p['p75'] is not None else '–'} | {p['max'] if p['max'] is not None else '–'} |"
        )
    r, ry = agg["rmse_pos_after_D_m"]["median"], agg["rmse_yaw_after_D_deg"]["median"]
    rmse = (
        f"no median: D met in {100 * agg['D']['success']:.0f}% of runs"
        if r is None
        else f"position median {fmt(r)} m, yaw median {fmt(ry)}°"
    )
    s2m = f"S2M median {fmt(agg['s2m_ms_median'])} ms." if agg["s2m_ms_median"] is not None else "S2M off."
    w5 = agg["within_5m_to_end_ratio"]
    ral = agg["rmse_after_localized_m_median"]
    cons, ff = agg["consistency_2sigma"], agg["false_fire_rate"]
    lines += [
        "",
        f"RMSE after D: {rmse}.",
        f"Runs localized and within 5 m of the truth from then to the end of the drive: "
        f"{'–' if w5 is None else f'{100 * w5:.0f}%'}; position RMSE from the rule's first "
        f"firing on, median over runs: {'–' if ral is None else f'{ral:.2f} m'}; evo over every scan, "
        f"median over runs: APE RMSE {_metres(agg.get('ape_rmse_m_median'))}, "
        f"RPE RMSE {_metres(agg.get('rpe_rmse_m_median'))}.",
        f"PF latency median {fmt(agg['pf_ms_median'])} ms per scan (paper: {PAPER['latency_s'] * 1000:.0f} ms "
        f"per scan on 8 cores); {s2m}",
        f"Truth inside the filter's 2σ ellipse, median over runs of the share of localized scans: "
        f"{'–' if cons is None else f'{100 * cons:.0f}%'} (an honest covariance: ~86%); runs whose rule "
        f"fired more than 5 m from the truth: {'–' if ff is None else f'{100 * ff:.0f}%'}.",
        f"Scans called localized more than 5 m from the truth, all runs: {_count(agg['localized_wrong_scans'])}; "
        f"relocalizations by the whole-map check: {_count(agg['relocalizations'])}, of a correct estimate "
        f"(spurious): {_count(agg['spurious_relocalizations'])}.",
        "",
    ]
    if plots:
        lines += ["![metrics](metrics_boxplot.png)", "", "![latency](latency_hist.png)", ""]
    (out_dir / "report.md").write_text("\n".join(lines))

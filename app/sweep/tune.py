"""``lidarloc tune``: a search for the settings that localize best — Optuna's TPE through Ray Tune's
Optuna searcher, not a search of our own.

A trial is one setting of the ``--param`` entries, run on seeds 0…R−1 one after the other. Its
objective is the median RMSE after localization over its seeds, subject to every seed succeeding
(localized and within 5 m of the truth to the end) without a false fire: a seed that fails ends the
trial at once with a penalty (hopeless: the constraint cannot be met any more), and Ray Tune's
ASHA scheduler stops trials whose RMSE after their first seeds is already worse than most others'.
The settings the run started from (the defaults, or ``--preset`` / ``--config`` / ``--set``) are the
first trial, so the best found is compared with them on the same seeds.

Writes ``trials.csv`` (one row per trial), ``best.yaml`` (for ``--config``), ``importance.png``
(Optuna's PED-ANOVA importance of each entry: how far the best trials' values of it stand apart
from the others'; it needs no scikit-learn, unlike fANOVA), ``tune.json``, and each trial's runs
under ``trials/``.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass
from pathlib import Path

from ...core.errors import LidarlocError
from ..bench.localize import numba_threads_for, run_one
from ..bench.localize_report import _within_5m_to_end
from .bookkeeping import Run, call_run
from .results import overrides_dict, settings_yaml, write_table
from .world import ensure_world

#: the objective of a trial that broke the constraint: above any RMSE, lower the later it failed
PENALTY = 1000.0


@dataclass(frozen=True)
class Param:
    """A searched entry: its key and range; integers (``pf.n_particles=200:2000``) stay integers."""

    key: str
    low: float
    high: float
    integer: bool

    def fmt(self, value) -> str:
        return str(int(round(value))) if self.integer else f"{float(value):.6g}"


def parse_params(items: list[str] | None) -> list[Param]:
    """``KEY=LOW:HIGH`` items; each bound checked as ``--set`` would check it by the caller."""
    params = []
    for item in items or []:
        key, sep, rng = item.partition("=")
        low, colon, high = rng.partition(":")
        try:
            lo, hi = float(low), float(high)
        except ValueError:
            lo = hi = math.nan
        if not sep or not colon or not key.strip() or not lo < hi:
            raise LidarlocError(f"--param {item}: expected KEY=LOW:HIGH with LOW < HIGH (e.g. --param pf.sigma=0.2:3)")
        integer = bool(re.fullmatch(r"-?\d+", low.strip()) and re.fullmatch(r"-?\d+", high.strip()))
        params.append(Param(key.strip(), lo, hi, integer))
    if not params:
        raise LidarlocError("give at least one --param KEY=LOW:HIGH (e.g. --param pf.sigma=0.2:3)")
    if len({p.key for p in params}) < len(params):
        raise LidarlocError("--param: each entry once")
    return params


def trial_name(params: list[Param], values: dict) -> str:
    return ",".join(f"{p.key}={p.fmt(values[p.key])}" for p in params)


def evaluate(
    values: dict, params: list[Param], settings, runs: int, out_dir: str, threads: int, run_fn, prepare, report
) -> dict:
    """One trial: the seeds one after the other, ``report`` after each (the scheduler may stop
    the trial there); a failed seed ends it. Runs already in its folder are kept (resume)."""
    overrides = [f"{p.key}={p.fmt(values[p.key])}" for p in params]
    cfg_d = settings.config_for(overrides).to_dict()
    cfg_d.pop("seed", None)
    spec_d = settings.spec.to_dict()
    folder = Path(out_dir) / "trials" / trial_name(params, values)
    prepare(spec_d, cfg_d, settings.cache, threads)
    rmses: list[float] = []
    result = {}
    for seed in range(runs):
        run_dir = str(folder / f"seed_{seed:03d}")
        args = (spec_d, cfg_d, seed, settings.cache, run_dir, threads, settings.preset, False)
        status, value = call_run(run_fn, Run((seed,), f"seed {seed}", run_dir, args))
        ok = status != "failed" and bool(_within_5m_to_end(Path(run_dir))) and not value.get("false_fire")
        rmse = None if status == "failed" else value.get("rmse_after_localized_m")
        if ok and rmse is not None:
            rmses.append(float(rmse))
        median = sorted(rmses)[len(rmses) // 2] if rmses else None
        result = {
            "objective": median if ok and median is not None else PENALTY + (runs - seed),
            "rmse_median": median,
            "seeds_done": seed + 1,
            "met": ok and seed + 1 == runs,
            "failed_seed": None if ok else seed,
            "error": value if status == "failed" else None,
        }
        report(result)
        if not ok:
            break
    return result


def _trial(config: dict, params=None, settings=None, runs=1, out_dir="", threads=0, run_fn=None, prepare=None):
    from ray import tune  # pyright: ignore[reportMissingImports]  (an optional extra)

    values = {p.key: config[f"p{i}"] for i, p in enumerate(params)}
    evaluate(values, params, settings, runs, out_dir, threads, run_fn or run_one, prepare or ensure_world, tune.report)


def run_tune(
    settings,
    params: list[Param],
    trials: int,
    runs: int,
    workers: int,
    out_dir: Path,
    ray: str | None = None,
    run_fn=None,
    prepare=None,
    seed: int = 0,
) -> dict:
    """Search ``trials`` settings of ``params`` (Ray Tune + Optuna's TPE, ASHA early stopping), the
    starting settings the first;
    write the results into ``out_dir``; returns the summary (tune.json). ``run_fn`` and
    ``prepare``: a seed's run and a world's preparation (default: a localizer's run, the world
    made sure of in this machine's cache)."""
    from .cluster import connect, import_ray

    if trials < 1 or runs < 1 or workers < 1:
        raise LidarlocError("--trials, --runs and --workers must be ≥ 1")
    base = settings.config_for([])
    for p in params:  # each bound as --set would check it
        settings.config_for([f"{p.key}={p.fmt(p.low)}", f"{p.key}={p.fmt(p.high)}"])
    import_ray()
    from ray import tune  # pyright: ignore[reportMissingImports]
    from ray.tune.schedulers import ASHAScheduler  # pyright: ignore[reportMissingImports]
    from ray.tune.search.optuna import OptunaSearch  # pyright: ignore[reportMissingImports]

    out_dir = Path(out_dir).absolute()
    out_dir.mkdir(parents=True, exist_ok=True)
    connect(ray, workers)
    space = {
        f"p{i}": tune.randint(int(p.low), int(p.high) + 1) if p.integer else tune.uniform(p.low, p.high)
        for i, p in enumerate(params)
    }
    defaults = {p.key: _current(base, p.key) for p in params}
    trainable = tune.with_resources(
        tune.with_parameters(
            _trial,
            params=params,
            settings=settings,
            runs=runs,
            out_dir=str(out_dir),
            threads=numba_threads_for(workers),
            run_fn=run_fn,
            prepare=prepare,
        ),
        {"cpu": 1},
    )
    storage = str(out_dir / "ray")
    # The starting settings first, on every seed and never stopped early: the yardstick the best
    # is measured against. Its objective then seeds the search (when it lies inside the ranges).
    start = {f"p{i}": defaults[p.key] for i, p in enumerate(params)}
    first = tune.Tuner(
        trainable,
        param_space=start,
        tune_config=tune.TuneConfig(metric="objective", mode="min", num_samples=1),
        run_config=tune.RunConfig(name="start", storage_path=storage, verbose=0),
    ).fit()
    rows = [_row(params, first[0], defaults=True)]
    inside = all(p.low <= defaults[p.key] <= p.high for p in params) and rows[0]["objective"] is not None
    searcher = OptunaSearch(
        metric="objective",
        mode="min",
        seed=seed,
        points_to_evaluate=[start] if inside else None,
        evaluated_rewards=[rows[0]["objective"]] if inside else None,
    )
    if trials > 1:
        tuner = tune.Tuner(
            trainable,
            param_space=space,
            tune_config=tune.TuneConfig(
                search_alg=searcher,
                scheduler=ASHAScheduler(time_attr="seeds_done", max_t=runs, grace_period=1, reduction_factor=2),
                metric="objective",
                mode="min",
                num_samples=trials - 1,
                max_concurrent_trials=workers,
                reuse_actors=True,
            ),
            run_config=tune.RunConfig(name="search", storage_path=storage, verbose=0),
        )
        rows += [_row(params, r, defaults=False) for r in tuner.fit()]
    return _write(out_dir, params, settings, rows, defaults, runs)


def _row(params: list[Param], result, defaults: bool) -> dict:
    """A trial's row: its settings, then what it reported last."""
    m = result.metrics or {}
    cfg = result.config or {}
    row = {p.key: cfg.get(f"p{i}") for i, p in enumerate(params)}
    row.update({k: m.get(k) for k in ("objective", "rmse_median", "seeds_done", "met", "failed_seed", "error")})
    row["stopped_early"] = bool(m) and not m.get("met") and m.get("failed_seed") is None
    row["defaults"] = defaults
    return row


def _current(cfg, key: str):
    section, _, name = key.partition(".")
    return getattr(getattr(cfg, section), name)


def _write(out_dir: Path, params: list[Param], settings, rows: list[dict], defaults: dict, runs: int) -> dict:
    write_table(out_dir / "trials.csv", rows)
    met = [r for r in rows if r["met"] and r["rmse_median"] is not None]
    best = min(met, key=lambda r: r["rmse_median"]) if met else None
    base = next((r for r in rows if r["defaults"]), None)
    entries = None
    if best is not None:
        entries = {**overrides_dict(settings.overrides), **{p.key: _plain(best[p.key], p) for p in params}}
        preset = f" --preset {settings.preset}" if settings.preset else ""
        header = (
            f"# Best of {len(rows)} trials in {out_dir}: every one of {runs} seeds localized, no false fire, "
            f"median RMSE after localization {best['rmse_median']:.3f} m.\n"
            f"# Use it with: lidarloc run{preset} --config best.yaml\n"
        )
        (out_dir / "best.yaml").write_text(settings_yaml(entries, header))
    importance = _importance(out_dir / "importance.png", params, rows)
    summary = {
        "params": {p.key: [p.low, p.high] for p in params},
        "trials": len(rows),
        "runs_per_trial": runs,
        "met": len(met),
        "stopped_early": sum(r["stopped_early"] for r in rows),
        "best": best,
        "best_settings": entries,
        "defaults": {"settings": defaults, "trial": base},
        "improvement_m": (
            None
            if best is None or base is None or not base["met"]
            else float(base["rmse_median"]) - float(best["rmse_median"])
        ),
        "importance": importance,
        "out": str(out_dir),
    }
    (out_dir / "tune.json").write_text(json.dumps(summary, indent=1, default=str))
    return summary


def _plain(value, p: Param):
    return int(round(value)) if p.integer else round(float(value), 6)


def _importance(path: Path, params: list[Param], rows: list[dict]) -> dict | None:
    """Optuna's importance of each entry for the objective over the finished trials (None: too
    few, or only one entry), drawn as bars."""
    import optuna

    done = [r for r in rows if r["objective"] is not None and all(r[p.key] is not None for p in params)]
    if len(params) < 2 or len(done) < 3:
        return None
    dists = {
        p.key: optuna.distributions.IntDistribution(int(p.low), int(p.high))
        if p.integer
        else optuna.distributions.FloatDistribution(p.low, p.high)
        for p in params
    }
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.create_study(direction="minimize")
    for r in done:
        values = {p.key: int(r[p.key]) if p.integer else float(r[p.key]) for p in params}
        study.add_trial(optuna.trial.create_trial(params=values, distributions=dists, value=float(r["objective"])))
    importance = optuna.importance.get_param_importances(
        study, evaluator=optuna.importance.PedAnovaImportanceEvaluator()
    )
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 0.5 + 0.5 * len(importance)))
    keys = list(importance)[::-1]
    ax.barh(keys, [importance[k] for k in keys], color="tab:blue")
    ax.set_xlabel("importance for the objective (PED-ANOVA)")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return {k: float(v) for k, v in importance.items()}

"""The runs as Ray Tune trials: Ray Tune's grid search over the sweep's axes, its trial bookkeeping
(``ray/`` in the sweep's folder) and its resume (``Tuner.restore``) — not a scheduler of our own.

Each trial is one point of the grid; its function calls the sweep's run function through
:func:`.bookkeeping.call_run`, so a trial of a finished run returns at once and a run that raises is a
trial that reports the error (Ray's own trial error is kept for what kills the worker: a lost node,
an out-of-memory kill; Ray then retries the trial). A callback in this process keeps the progress
bar and hands each summary to the sweep as it arrives.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

from ray import tune  # pyright: ignore[reportMissingImports]  (an optional extra: see cluster.import_ray)

from .bookkeeping import WORKER_DIED, Board, Run, Tally, call_run, is_done, read_error
from .cluster import connect

# a trial that dies with its worker (a lost node, a kill) is tried again this many times
RAY_RETRIES = 2


# The sweep this process runs now, for the callback: Ray Tune pickles its callbacks with the
# experiment's state (and unpickles them on restore), and a progress bar does not pickle.
_HOOKS: dict = {}


def _run_of(trial) -> Run | None:
    """The run a trial is, None for a run finished before this call (in the tally already)."""
    run = _HOOKS["by_index"][tuple(trial.config[f"a{i}"] for i in range(len(_HOOKS["names"])))]
    return None if run.run_dir in _HOOKS["kept"] else run


class Progress(tune.Callback):
    """Trials as the sweep sees them, in this process: started, finished (kept, done, failed), died."""

    def __getstate__(self):
        return {}

    def on_trial_start(self, iteration, trials, trial, **info):
        if _run_of(trial) is not None:
            _HOOKS["board"].started()

    def on_trial_complete(self, iteration, trials, trial, **info):
        run = _run_of(trial)
        if run is None:
            return
        result = trial.last_result or {}
        status, value = result.get("status"), json.loads(result.get("value", "null"))
        if status == "failed":
            _HOOKS["board"].ended(run.label, value)
        else:
            tally = _HOOKS["tally"]
            tally.done += status == "done"
            tally.kept += status == "kept"
            _HOOKS["on_done"](run, value)
            _HOOKS["board"].ended()

    def on_trial_error(self, iteration, trials, trial, **info):
        run = _run_of(trial)
        if run is not None:
            _HOOKS["board"].ended(run.label, WORKER_DIED)


def _trial(config: dict, fn=None, runs_by_index=None):
    """One Ray Tune trial: the run at the grid point ``config`` names (axis → value index)."""
    run = runs_by_index[tuple(config[f"a{i}"] for i in range(len(config)))]
    status, value = call_run(fn, run)
    return {"status": status, "value": json.dumps(value, default=str)}


def run_grid(
    fn, axes: dict, runs: list[Run], workers: int, address, ray_dir: Path, tally: Tally, board: Board, on_done
):
    """Every run of ``runs`` (one per point of ``axes``, in the grid's order) as a Ray Tune trial;
    ``ray_dir`` keeps the experiment's state, restored when it holds the same grid."""
    connect(address, workers)

    names = list(axes)
    index = {name: {repr(v): i for i, v in enumerate(values)} for name, values in axes.items()}
    by_index = {tuple(index[n][repr(v)] for n, v in zip(names, run.point)): run for run in runs}
    param_space = {f"a{i}": tune.grid_search(list(range(len(axes[n])))) for i, n in enumerate(names)}

    # runs finished before this call are in the tally already: their (instant) trials are not shown
    kept_before = {r.run_dir for r in runs if is_done(r.run_dir)}

    _HOOKS.update(board=board, tally=tally, on_done=on_done, names=names, by_index=by_index, kept=kept_before)

    ray_dir = Path(ray_dir).absolute()
    signature = json.dumps({n: [repr(v) for v in axes[n]] for n in names})
    marker = ray_dir / "grid.json"
    experiment = ray_dir / "trials"
    trainable = tune.with_resources(tune.with_parameters(_trial, fn=fn, runs_by_index=by_index), {"cpu": 1})
    run_config = tune.RunConfig(
        name=experiment.name,
        storage_path=str(ray_dir),
        verbose=0,
        callbacks=[Progress()],
        failure_config=tune.FailureConfig(max_failures=RAY_RETRIES),
    )
    os.environ.setdefault("RAY_CHDIR_TO_TRIAL_DIR", "0")  # runs write only their own folders
    # Ray Tune's resume picks up the trials a crash, Ctrl-C or a lost node left unfinished; a failed
    # run is a finished trial to it, so a sweep with failed runs (or another grid) starts afresh
    # (the finished runs are still skipped, by their folders)
    failed_before = any(read_error(r.run_dir) is not None for r in runs if r.run_dir not in kept_before)
    same = marker.is_file() and marker.read_text() == signature
    if same and not failed_before and tune.Tuner.can_restore(str(experiment)):
        tuner = tune.Tuner.restore(str(experiment), trainable, resume_unfinished=True, restart_errored=True)
    else:
        shutil.rmtree(experiment, ignore_errors=True)
        ray_dir.mkdir(parents=True, exist_ok=True)
        marker.write_text(signature)
        tuner = tune.Tuner(
            trainable,
            param_space=param_space,
            tune_config=tune.TuneConfig(max_concurrent_trials=workers, num_samples=1, reuse_actors=True),
            run_config=run_config,
        )
    try:
        tuner.fit()
    finally:
        _HOOKS.clear()
    if tally.kept + tally.done + len(tally.failed) < tally.total:
        tally.interrupted = True  # Ctrl-C: Ray Tune saved the experiment and returned

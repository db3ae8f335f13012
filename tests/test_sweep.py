"""The sweep executor: the same runs on the process pool and on Ray, a failed run reported while
the others finish, a killed sweep resumed with no run done twice; the grid's parsing."""

from __future__ import annotations

import itertools
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from helpers import wait_for
from lidarloc.app.sweep.bookkeeping import Run
from lidarloc.app.sweep.executor import execute
from lidarloc.app.sweep.grid import parse_grid
from lidarloc.core.errors import LidarlocError
from ray_local import TESTS, ray_local  # noqa: F401  (a fixture)
from rich.console import Console
from sweep_fakes import fake_run

AXES = {"a": [0.5, 1.0], "b": [1.0, 2.0], "seed": [0, 1]}


def grid_runs(out: Path, work_s: float = 0.0, fail_at: float | None = None) -> list[Run]:
    runs = []
    for a, b, seed in itertools.product(*AXES.values()):
        d = str(out / "runs" / f"a={a},b={b}" / f"seed_{seed:03d}")
        runs.append(Run((a, b, seed), f"a={a} b={b} seed {seed}", d, (d, a, b, seed, work_s, fail_at)))
    return runs


def sweep(out: Path, ray: str | None, **kw):
    results: dict = {}
    tally = execute(
        fake_run,
        AXES,
        grid_runs(out, **kw),
        2,
        on_done=lambda run, s: results.__setitem__(run.point, s["rmse_after_localized_m"]),
        ray=ray,
        ray_dir=out / "ray",
        console=Console(file=open(os.devnull, "w")),
    )
    return tally, results


def done_log(out: Path) -> list[str]:
    return (out / "runs" / "done.log").read_text().split()


@pytest.mark.slow
def test_ray_gives_the_pool_results_and_reports_a_failed_run(tmp_path, ray_local):
    pool, pool_results = sweep(tmp_path / "pool", None, fail_at=1.0)
    on_ray, ray_results = sweep(tmp_path / "ray", "local", fail_at=1.0)
    for tally in (pool, on_ray):
        # the two runs that raise are reported with their one line; the six others finish
        assert tally.done == 6 and not tally.interrupted
        assert tally.failed == {
            "a=1.0 b=1.0 seed 0": "ValueError: a = 1.0 is out of range",
            "a=1.0 b=2.0 seed 0": "ValueError: a = 1.0 is out of range",
        }
    assert ray_results == pool_results and len(pool_results) == 6
    for out in (tmp_path / "pool", tmp_path / "ray"):
        assert (out / "runs" / "a=1.0,b=1.0" / "seed_000" / "error.txt").read_text().startswith("ValueError")
        assert sorted(done_log(out)) == sorted(set(done_log(out)))
    # the next call runs the failed runs again (and only them)
    again, again_results = sweep(tmp_path / "ray", "local")
    assert (again.kept, again.done, again.failed) == (6, 2, {})
    assert set(again_results) == {(1.0, 1.0, 0), (1.0, 2.0, 0)}
    assert len(done_log(tmp_path / "ray")) == 8


KILLED_SWEEP = """
import os, sys
sys.path.insert(0, {tests!r})
os.environ["PYTHONPATH"] = os.pathsep.join(p for p in ({tests!r}, os.environ.get("PYTHONPATH")) if p)
from pathlib import Path
from test_sweep import sweep
if __name__ == "__main__":
    sweep(Path({out!r}), {ray!r}, work_s={work_s!r})
"""


def _session_pids(sid: int) -> list[int]:
    """Processes of session ``sid`` that still run (zombies excluded)."""
    pids = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[3]) == sid and fields[0] != "Z":  # state, ppid, pgrp, session
            pids.append(int(stat.parent.name))
    return pids


def session_alive(sid: int) -> bool:
    return bool(_session_pids(sid))


def kill_session(sid: int) -> None:
    for pid in _session_pids(sid):
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


def kill_half_way(out: Path, script: Path, ray: str | None, work_s: float) -> int:
    """Start the 8-run sweep in a process of its own (its own Ray instance with ``ray``), SIGKILL
    it and everything it started once three runs are done; returns the runs finished."""
    script.write_text(KILLED_SWEEP.format(tests=TESTS, out=str(out), ray=ray, work_s=work_s))
    proc = subprocess.Popen([sys.executable, str(script)], start_new_session=True, stderr=subprocess.DEVNULL)
    try:
        wait_for(lambda: len(list(out.glob("runs/*/*/summary.json"))) >= 3, timeout=300, what="three runs done")
    finally:
        # the machine dies half-way: every process of the sweep's session (Ray's workers have
        # process groups of their own, and a killed driver's workers finish the run they are in)
        kill_session(proc.pid)
        proc.wait()
        wait_for(lambda: not session_alive(proc.pid), timeout=30, what="the session's processes gone")
    finished = len(list(out.glob("runs/*/*/summary.json")))
    assert 3 <= finished < 8
    return finished


def test_killed_sweep_resumes_without_doing_a_run_twice(tmp_path):
    out = tmp_path / "sweep"
    finished = kill_half_way(out, tmp_path / "killed.py", None, 0.4)
    tally, results = sweep(out, None, work_s=0.4)
    assert (tally.kept, tally.done, tally.failed) == (finished, 8 - finished, {})
    # every run done once: the killed ones' were cut short before their summary
    log = done_log(out)
    assert sorted(log) == sorted(set(log)) and len(log) == 8
    assert all(json.loads(p.read_text())["seed"] in (0, 1) for p in out.glob("runs/*/*/summary.json"))


@pytest.mark.slow
def test_killed_ray_sweep_resumes_without_doing_a_run_twice(tmp_path, ray_local):
    """On Ray: the killed sweep's Ray Tune experiment is restored (Tuner.restore) on another Ray
    instance; the runs finished before the kill are not run again, the others once."""
    out = tmp_path / "sweep"
    finished = kill_half_way(out, tmp_path / "killed.py", "local", 1.0)
    trials = out / "ray" / "trials"
    killed_ids = {p.name.split("_")[2] for p in trials.glob("_trial_*")}  # _trial_<experiment>_<n>_…
    assert len(killed_ids) == 1
    tally, results = sweep(out, "local", work_s=0.1)
    # Ray Tune restored the killed experiment (a fresh one would name its trials anew)
    assert {p.name.split("_")[2] for p in trials.glob("_trial_*")} == killed_ids
    assert (tally.kept, tally.done, tally.failed, tally.interrupted) == (finished, 8 - finished, {}, False)
    assert len(results) == 8 - finished
    log = done_log(out)
    assert sorted(log) == sorted(set(log)) and len(log) == 8
    assert len(list(out.glob("runs/*/*/summary.json"))) == 8


def test_grid_is_parsed_and_checked():
    grid = parse_grid(["pf.sigma=0.5,1,2", "pf.d_max=1, 2"])
    assert grid.axes == {"pf.sigma": ("0.5", "1", "2"), "pf.d_max": ("1", "2")}
    assert len(grid.combinations()) == 6
    assert grid.name(("0.5", "1")) == "pf.sigma=0.5,pf.d_max=1"
    for bad, message in (
        ([], "give at least one --grid"),
        (["pf.sigma"], "expected KEY=V1,V2"),
        (["pf.sigma=1", "pf.sigma=2"], "given twice"),
        (["seed=1,2"], "--runs"),
    ):
        with pytest.raises(LidarlocError, match=message):
            parse_grid(bad)


@pytest.mark.parametrize(
    "args, needle",
    [
        (["sweep", "--grid", "pf.sigmx=1,2"], "unknown key 'pf.sigmx'"),
        (["sweep", "--grid", "pf.sigma=1", "--ray", "nowhere"], "--ray nowhere"),
        (["tune", "--param", "pf.sigma=3:1"], "LOW < HIGH"),
    ],
)
def test_bad_sweep_and_tune_options_are_one_line(tmp_path, args, needle):
    env = {"LIDARLOC_CACHE": str(tmp_path / "cache"), "PATH": "/usr/bin:/bin"}
    r = subprocess.run(
        [sys.executable, "-m", "lidarloc.app.cli", *args, "--out", str(tmp_path / "out")],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )
    assert r.returncode == 2, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and needle in lines[0], r.stderr

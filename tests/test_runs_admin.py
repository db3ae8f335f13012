"""The viewer's recordings under a budget (app/viewer/budget.py) and ``lidarloc runs list|prune``:
oldest removed first, never a live run or the run a kept branch starts from, nothing outside the
runs folder."""

from __future__ import annotations

import json
import os
import time

import pytest
from lidarloc.app.viewer import budget
from lidarloc.app.viewer.budget import KnownRuns, find_runs, plan_prune, remove_runs
from lidarloc.core.errors import LidarlocError
from typer.testing import CliRunner


def fake_run(folder, mb: float, age_s: float, branch_of=None):
    """A run folder as the recorder leaves it: recording/index.json, steps.bin, a data file."""
    rec = folder / "recording"
    rec.mkdir(parents=True)
    meta = {"branch_of": None if branch_of is None else {"run": str(branch_of), "step": 3}}
    (rec / "index.json").write_text(json.dumps({"format": "lidarloc-recording", "meta": meta}))
    (rec / "steps.bin").write_bytes(b"\0" * 8 * 10)
    (rec / "particles.bin").write_bytes(b"\0" * int(mb * 1e6))
    t = time.time() - age_s
    for f in [folder, rec, *rec.iterdir()]:
        os.utime(f, (t, t))
    return folder


@pytest.fixture
def runs_root(tmp_path):
    root = tmp_path / "runs"
    fake_run(root / "2026-01-01T10-00-00" / "run", 2.0, 5000)
    fake_run(root / "2026-01-01T10-00-00" / "run-2", 2.0, 4000)
    original = fake_run(root / "2026-01-02T10-00-00" / "run", 2.0, 3000)
    fake_run(root / "2026-01-02T10-00-00" / "branch-scan-3", 2.0, 2000, branch_of=original)
    fake_run(root / "2026-01-03T10-00-00" / "run", 2.0, 10)  # being written now (another viewer)
    return root


def test_the_periodic_check_walks_only_runs_that_may_have_changed(runs_root, monkeypatch):
    """With what it learnt (KnownRuns), the budget check finds the same runs but walks again only
    the live run and runs whose folders changed; runs removed from disk are forgotten."""
    walked = []
    scan = budget._scan_folder
    monkeypatch.setattr(budget, "_scan_folder", lambda path: walked.append(path) or scan(path))
    known = KnownRuns()
    first = find_runs(runs_root, known)
    assert len(walked) == 5
    key = lambda runs: [(r.path, r.bytes, r.written, r.steps, r.branch_of) for r in runs]  # noqa: E731
    plain = find_runs(runs_root)
    walked.clear()
    again = find_runs(runs_root, known)
    assert key(again) == key(first) == key(plain)
    live = runs_root / "2026-01-03T10-00-00" / "run"
    assert walked == [live]  # only the run written in the last two minutes
    # a quiet run that changes (a rolling window drops a segment: its folder's time moves)
    changed = runs_root / "2026-01-01T10-00-00" / "run-2"
    (changed / "recording" / "particles.bin").unlink()
    walked.clear()
    runs = {r.path: r for r in find_runs(runs_root, known)}
    assert sorted(walked) == sorted([live, changed]) and runs[changed].bytes < 1000  # the 2 MB file gone
    # a run removed from disk is neither listed nor remembered
    remove_runs([runs[changed]], runs_root)
    assert changed not in {r.path for r in find_runs(runs_root, known)} and changed not in known._runs


def test_oldest_runs_go_first_never_a_live_one_or_a_kept_branchs_original(runs_root):
    runs = find_runs(runs_root)
    assert [r.steps for r in runs] == [10] * 5 and runs[0].path.name == "run" and runs[-1].written > runs[0].written
    # keep 2: the three oldest would go, but a branch reads its first steps from its original:
    # the original stays while the branch exists (the next prune takes it)
    plan = plan_prune(runs, keep_runs=2, max_bytes=None)
    assert [str(r.path.relative_to(runs_root)) for r in plan] == [
        "2026-01-01T10-00-00/run",
        "2026-01-01T10-00-00/run-2",
        "2026-01-02T10-00-00/branch-scan-3",
    ]
    # a size budget of 5 MB (5 runs of 2 MB): the oldest go until it fits; the live run never does
    plan = plan_prune(runs, keep_runs=None, max_bytes=5e6)
    assert len(plan) == 3 and all(r.path != runs[-1].path for r in plan)
    # a protected run (the one playing) stays even when everything else is gone
    plan = plan_prune(runs, keep_runs=0, max_bytes=None, protect={runs[0].path})
    assert runs[0].path not in {r.path for r in plan} and runs[-1].path not in {r.path for r in plan}
    removed = remove_runs(plan_prune(runs, keep_runs=2, max_bytes=None), runs_root)
    assert len(removed) == 3 and not (runs_root / "2026-01-01T10-00-00").exists()  # its empty folder too
    assert len(find_runs(runs_root)) == 2


def test_runs_list_and_prune_commands(runs_root, tmp_path):
    from lidarloc.app.cli.groups import app

    cli = CliRunner()
    listed = cli.invoke(app, ["runs", "list", "--dir", str(runs_root), "--json"])
    assert listed.exit_code == 0, listed.output
    data = json.loads(listed.output)
    assert len(data["runs"]) == 5 and data["total_mb"] == pytest.approx(10.0, abs=0.1)
    dry = cli.invoke(app, ["runs", "prune", "--dir", str(runs_root), "--keep-runs", "1", "--dry-run", "--json"])
    assert dry.exit_code == 0 and len(json.loads(dry.output)["removed"]) == 3 and len(find_runs(runs_root)) == 5
    done = cli.invoke(app, ["runs", "prune", "--dir", str(runs_root), "--max-gb", "0.005"])
    assert done.exit_code == 0 and "removed 3 runs" in done.output and len(find_runs(runs_root)) == 2
    nothing = cli.invoke(app, ["runs", "prune", "--dir", str(runs_root)])
    # errors the user can fix are LidarlocErrors (main() prints them as one line, exit status 2)
    assert isinstance(nothing.exception, LidarlocError) and "--keep-runs" in str(nothing.exception)
    missing = cli.invoke(app, ["runs", "list", "--dir", str(tmp_path / "nope")])
    assert isinstance(missing.exception, LidarlocError) and "no such folder" in str(missing.exception)


def test_remove_runs_never_leaves_the_runs_folder(runs_root, tmp_path):
    outside = fake_run(tmp_path / "elsewhere" / "run", 0.1, 9000)
    runs = find_runs(tmp_path / "elsewhere")
    assert remove_runs(runs, runs_root) == [] and outside.exists()


def test_the_viewers_recorder_keeps_its_runs_folder_to_the_budget(runs_root):
    from lidarloc.app.viewer.recorder import Budget, Recorder

    notices = []
    rec = Recorder(
        runs_root / "2026-01-04T10-00-00", spec=None, budget=Budget(runs_root, 3, None), on_notice=notices.append
    )
    removed = rec.keep_to_budget()
    # the two oldest go (the branch's original stays while its branch exists; the live run stays)
    assert [p.name for p in removed] == ["run", "run-2"] and rec.removed == removed
    assert len(notices) == 1 and "removed 2 oldest run(s)" in notices[0]
    assert rec.keep_to_budget() == [] and len(notices) == 1  # within the budget: nothing more said

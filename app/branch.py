"""``lidarloc run --branch DIR:K [--set …] --out NEW``: continue a recorded run from its step K,
with other parameters if wished, into a folder of its own.

The branch is the recorded run's exact state after step K (:func:`lidarloc.core.runs.branch.open_branch`),
stepped to the end of the sequence by the same loop as ``lidarloc run``; ``NEW`` gets the same
files (trajectories and per-scan CSV from scan 0: the recorded run's up to K, the branch's after)
and a recording of the branch's own steps (numbered from K + 1; its index names the run and step
it branched from). The recorded run's folder is only read.
"""

from __future__ import annotations

from pathlib import Path

from rich.console import Console

from ..core.errors import LidarlocError
from .console import preparing
from .headless import check_recording_target, localize


def parse_branch(text: str) -> tuple[Path, int]:
    """``DIR:K`` → (DIR, K)."""
    run, sep, step = str(text).rpartition(":")
    if not sep or not run:
        raise LidarlocError(f"--branch {text}: expected RUN_DIR:STEP (e.g. out/run0:412)")
    try:
        return Path(run), int(step)
    except ValueError:
        raise LidarlocError(f"--branch {text}: the step after ':' must be a whole number") from None


def run_branch(
    run_dir: Path,
    step: int,
    overrides: list[str] | dict | None,
    out: Path,
    cache_root: Path | None = None,
    console: Console | None = None,
    stop_after: int | None = None,
    record: bool = True,
) -> tuple[dict, bool]:
    """Branch the recorded run in ``run_dir`` at its step ``step`` with ``overrides`` (``--set``
    strings or live parameters) and run it to the end into ``out``; returns (summary, interrupted).
    ``stop_after``: stop once this many steps are done in all (the recorded ones up to ``step``
    included)."""
    from ..core.runs.branch import continue_recording, open_branch, open_recording
    from ..core.runs.recording import RecordingWriter
    from ..core.runs.results import make_out_dir

    console = console or Console(stderr=True)
    rec = open_recording(run_dir)
    out = Path(out)
    if out.resolve() == rec.run_dir.resolve() or rec.run_dir.resolve() in out.resolve().parents:
        raise LidarlocError(f"{out}: a branch needs a folder of its own, outside the recorded run {rec.run_dir}")
    make_out_dir(out)
    if record:
        check_recording_target(out)
    loc = preparing(
        lambda progress: open_branch(rec, step, overrides, cache_root=cache_root, progress=progress),
        "preparing the branch",
    )
    writer = None
    try:
        if record:
            writer = RecordingWriter(
                out,
                rec.source_spec(),
                loc.cfg,
                loc.seq,
                preset=rec.meta.get("preset"),
                branch_of=dict(loc.branch_of),
                first_step=step + 1,
            )
            continue_recording(writer, loc)
    except BaseException:
        loc.close()
        if writer is not None:
            writer.close()
        raise
    title = (
        f"branching {rec.run_dir} at step {step} (scan {loc.snapshot().scan_index}): "
        f"{len(loc.seq) - loc.k} scans left of {loc.seq.name}"
    )
    return localize(loc, out, console, writer=writer, stop_after=stop_after, preset=rec.meta.get("preset"), title=title)

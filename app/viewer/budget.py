"""The viewer's recordings under a budget: at most ``keep_runs`` run folders and ``max_bytes`` on
disk under the runs root (the cache's ``runs/`` or ``--record-dir``), the oldest removed first.

A run that alone outgrows the size budget keeps a rolling window of its newest steps (see
:mod:`.recorder`); here it counts as any run, with the steps it holds.

A run folder is any folder holding a recording (``recording/index.json``): the viewer's ``run``,
``run-2``, …, ``branch-scan-K`` inside each start's ``<date-time>`` folder. "Oldest" is the last
time a run was written to. Never removed: the runs the caller protects (the one recording now),
the runs they branch from (a branch reads its first steps from its original), and any run written
to in the last ``LIVE_S`` seconds (another viewer may be recording it right now).
"""

from __future__ import annotations

import json
import os
import shutil
import stat
import threading
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from ...core.runs.recording import segments

#: A run written to this recently may be another viewer's live recording: never pruned.
LIVE_S = 120.0
#: Defaults of ``view`` / ``demo``: a day of looping the town's drive stays well under them.
DEFAULT_KEEP_RUNS = 50
DEFAULT_MAX_RECORD_GB = 5.0
INDEX = Path("recording") / "index.json"


@dataclass(frozen=True)
class RunFolder:
    """One recorded run on disk: its folder, its size, when it was last written, its steps (the
    ones on disk) and, for a run kept as a rolling window, the window's steps."""

    path: Path
    bytes: int
    written: float  # newest file modification time (s since the epoch)
    steps: int
    branch_of: Path | None  # the run a branch reads its first steps from
    window: tuple[int, int] | None = None  # (first, last) step kept, where the budget dropped the first

    @property
    def mb(self) -> float:
        return self.bytes / 1e6


def _walk_sizes(folder: str) -> tuple[int, float]:
    """The regular files' bytes and the newest modification time of anything under ``folder``:
    one ``lstat`` per entry (a recording holds hundreds of segment files)."""
    size, newest = 0, 0.0
    try:
        entries = list(os.scandir(folder))
    except OSError:  # removed meanwhile
        return 0, 0.0
    for entry in entries:
        try:
            st = entry.stat(follow_symlinks=False)
        except OSError:  # removed meanwhile (a writer's temporary file)
            continue
        newest = max(newest, st.st_mtime)
        if entry.is_dir(follow_symlinks=False):
            sub_size, sub_newest = _walk_sizes(entry.path)
            size, newest = size + sub_size, max(newest, sub_newest)
        elif stat.S_ISREG(st.st_mode):
            size += st.st_size
    return size, newest


def _scan_folder(path: Path) -> RunFolder:
    size, newest = _walk_sizes(str(path))
    steps, window = 0, None
    held = segments.window(path / INDEX.parent)
    if held is not None:
        start, first, end = held
        steps = end - first
        if first > start and end > first:
            window = (first, end - 1)
    branch_of = None
    try:
        meta = json.loads((path / INDEX).read_text()).get("meta", {})
        origin = (meta.get("branch_of") or {}).get("run")
        branch_of = Path(origin) if origin else None
    except (OSError, ValueError, AttributeError):  # a damaged index: the run is still listed and prunable
        pass
    return RunFolder(path, size, newest, int(steps), branch_of, window)


def _stamp(path: Path) -> tuple[int, ...] | None:
    """What changes when a recording changes other than by a write into a file it already has:
    the modification times of the run's folder, its recording folder and its index."""
    try:
        return tuple(os.stat(p).st_mtime_ns for p in (path, path / INDEX.parent, path / INDEX))
    except OSError:
        return None


class KnownRuns:
    """What :func:`find_runs` learnt of the runs that were quiet: a viewer checks its budget every
    30 s, and walking every file of every kept run each time (50 runs of hundreds of segment
    files) is Python holding the GIL for a good part of a second, long enough to make the filter's
    real-time scans late. A run quiet for :data:`LIVE_S` (no writer: its recorder finished or
    rolled on) whose folders' and index's modification times are unchanged is not walked again;
    anything newer always is."""

    def __init__(self):
        self._runs: dict[Path, tuple[tuple[int, ...], RunFolder]] = {}
        self._lock = threading.Lock()  # a new run's check and the periodic one may overlap

    def scan(self, path: Path, now: float) -> RunFolder:
        """The run at ``path``: as last seen if it was quiet and has not changed since, else
        walked (and remembered)."""
        stamp = _stamp(path)  # before any walk: a change during it is seen next time
        with self._lock:
            held = self._runs.get(path)
        if held is not None and held[0] == stamp and now - held[1].written >= LIVE_S:
            return held[1]
        run = _scan_folder(path)
        if stamp is not None:
            with self._lock:
                self._runs[path] = (stamp, run)
        return run

    def forget_all_but(self, seen: set[Path]) -> None:
        """Drop what is no longer on disk (pruned, removed by hand)."""
        with self._lock:
            for path in [p for p in self._runs if p not in seen]:
                del self._runs[path]


def find_runs(root: Path, known: KnownRuns | None = None) -> list[RunFolder]:
    """Every recorded run under ``root`` (up to three folders deep), oldest first; with
    ``known``, a run that was quiet and has not changed since the last call is not walked again."""
    root = Path(root)
    if not root.is_dir():
        return []
    found, seen, now = [], set(), time.time()
    for depth in ("*", "*/*", "*/*/*"):
        for index in root.glob(f"{depth}/{INDEX.as_posix()}"):
            path = index.parent.parent
            seen.add(path)
            found.append(known.scan(path, now) if known is not None else _scan_folder(path))
    if known is not None:
        known.forget_all_but(seen)
    return sorted(found, key=lambda r: (r.written, str(r.path)))


def total_bytes(runs: list[RunFolder]) -> int:
    return sum(r.bytes for r in runs)


def plan_prune(
    runs: list[RunFolder],
    keep_runs: int | None,
    max_bytes: float | None,
    protect: Iterable[Path] = (),
    now: float | None = None,
) -> list[RunFolder]:
    """The runs to remove, oldest first, until at most ``keep_runs`` are left and they take at
    most ``max_bytes`` (either None: no limit of that kind); protected, live and branched-from
    runs are kept even if the budget is then still exceeded."""
    now = time.time() if now is None else now
    keep = {Path(p).resolve() for p in protect}
    keep |= {r.path.resolve() for r in runs if now - r.written < LIVE_S}
    # a branch reads its first steps from its original: an original stays while a branch of it
    # exists (a branch is newer than its original, so the original would otherwise go first)
    keep |= {r.branch_of.resolve() for r in runs if r.branch_of is not None}
    count, size = len(runs), total_bytes(runs)
    remove = []
    for r in runs:  # oldest first
        over = (keep_runs is not None and count > keep_runs) or (max_bytes is not None and size > max_bytes)
        if not over:
            break
        if r.path.resolve() in keep:
            continue
        remove.append(r)
        count -= 1
        size -= r.bytes
    return remove


def remove_runs(runs: list[RunFolder], root: Path) -> list[RunFolder]:
    """Delete the run folders (and the start folders they leave empty under ``root``); returns
    those removed (a folder that could not be removed is skipped)."""
    root = Path(root).resolve()
    removed = []
    for r in runs:
        path = r.path.resolve()
        if root not in path.parents:  # never anything outside the runs root
            continue
        try:
            shutil.rmtree(path)
        except OSError:
            continue
        removed.append(r)
        parent = path.parent
        while parent != root and root in parent.parents:
            try:
                parent.rmdir()  # only if empty
            except OSError:
                break
            parent = parent.parent
    return removed


def enforce(
    root: Path,
    keep_runs: int | None,
    max_bytes: float | None,
    protect: Iterable[Path] = (),
    known: KnownRuns | None = None,
) -> list[RunFolder]:
    """Prune ``root`` to the budget now; returns the runs removed."""
    runs = find_runs(root, known)
    return remove_runs(plan_prune(runs, keep_runs, max_bytes, protect), root)

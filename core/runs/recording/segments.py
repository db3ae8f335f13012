"""A recording in segments, and one folder of a recording read back.

A run recorded under a size budget (the viewer's ``--max-record-gb``) keeps a rolling window of
its newest steps instead of stopping when it alone reaches the budget. The files are append-only
(one raw file per field, ``particles.bin`` addressed by ``particle_rows``, the ``steps.bin``
commit log), so the oldest steps cannot be cut off a file without rewriting it, which would cost
the filter a copy of the whole recording each time. Instead the run is written in segments:

- ``recording/`` holds the run's first segment, exactly as a recording without a budget;
- ``recording/segments/FIRST/`` (``FIRST``: its first step, nine digits) each hold a later one:
  a complete recording of the same format (:mod:`.format`) whose ``meta.first_step`` is the step
  it starts at and ``meta.segment.events_before`` the events of the run before it. Each segment
  starts with a checkpoint (its own step 0), so any kept step can be resumed or branched from;
  it carries the S2M view its first step shows as ``s2m/-00001`` (a display's need: the match
  itself landed in an earlier segment).

A segment is dropped whole, oldest first: its ``steps.bin`` is truncated to nothing first (from
that moment no reader counts its steps: a drop is atomic), then its files are removed (the first
segment's ``index.json`` stays: it names the run). A reader takes the newest segment that has
steps and the ones before it that end exactly where the next begins; so a recording cut at any
moment, even in the middle of a drop or of a new segment's start, opens up to its last complete
step. The row numbers of :class:`~.reader.Recording` count the kept steps; its ``first_step``
says which step of the run row 0 is.

:class:`Part` reads one folder: its index, its own steps (committed rows that every field holds),
its fields, particles, events, S2M views and resume files.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np

from .format import FIELDS, FORMAT, INDEX, LOG_WEIGHTS, PARTICLES, STEPS, VERSION, RecordingError, load_s2m, named_field

SEGMENTS = "segments"
#: the step a segment's carried S2M view is saved under (shown before the segment's first landing)
CARRIED = -1


def segment_folder(recording_folder: Path, first_step: int) -> Path:
    return Path(recording_folder) / SEGMENTS / f"{int(first_step):09d}"


def continuation_folders(recording_folder: Path) -> list[Path]:
    """The later segments of a recording folder, in step order (none: a recording in one piece)."""
    d = Path(recording_folder) / SEGMENTS
    found = []
    try:
        entries = list(d.iterdir())
    except OSError:
        return []
    for f in entries:
        try:
            first = int(f.name)
        except ValueError:
            continue
        if f.is_dir():
            found.append((first, f))
    return [f for _, f in sorted(found)]


def kept(parts: list[tuple[int, int]]) -> list[int]:
    """Which of the parts, given as (first step, steps) in order, a reader holds: the newest one
    with steps and those before it that end exactly where the next one begins."""
    idx = [i for i, (_, n) in enumerate(parts) if n > 0]
    if not idx:
        return []
    out = [idx[-1]]
    for i in reversed(idx[:-1]):
        first, n = parts[i]
        if first + n != parts[out[0]][0]:
            break
        out.insert(0, i)
    return out


def folder_bytes(folder: Path) -> int:
    """Bytes on disk of one segment's files (a first segment's later segments not counted)."""
    total = 0
    for root, dirs, files in os.walk(folder):
        if Path(root) == Path(folder) and SEGMENTS in dirs:
            dirs.remove(SEGMENTS)
        for name in files:
            try:
                total += os.lstat(os.path.join(root, name)).st_size
            except OSError:  # removed meanwhile
                pass
    return total


def drop_commit(folder: Path) -> None:
    """Drop a segment's steps: its commit log truncated to nothing (atomic for readers)."""
    steps = Path(folder) / STEPS
    if steps.is_file():
        os.truncate(steps, 0)


def remove_files(folder: Path, first: bool) -> None:
    """Remove a dropped segment's files; the first segment keeps its index (it names the run),
    its empty commit log (no new recording may start there) and its later segments."""
    folder = Path(folder)
    if not first:
        shutil.rmtree(folder, ignore_errors=True)
        return
    for f in list(folder.iterdir()):
        if f.name in (INDEX, STEPS, SEGMENTS):
            continue
        if f.is_dir():
            shutil.rmtree(f, ignore_errors=True)
        else:
            try:
                f.unlink()
            except OSError:
                pass


def window(recording_folder: Path) -> tuple[int, int, int] | None:
    """(the run's first step, the first kept step, the step after the last one) from the index
    and the commit logs alone (a listing's figure; :class:`~.reader.Recording` checks every
    field), or None where the index is unreadable."""
    folder = Path(recording_folder)
    try:
        top_first = int(json.loads((folder / INDEX).read_text()).get("meta", {}).get("first_step", 0) or 0)
    except (OSError, ValueError, TypeError, AttributeError):
        return None
    parts = [(top_first, _committed(folder))]
    for f in continuation_folders(folder):
        try:
            parts.append((int(f.name), _committed(f)))
        except ValueError:
            continue
    keep = kept(parts)
    if not keep:
        return top_first, parts[-1][0], parts[-1][0]
    return top_first, parts[keep[0]][0], parts[keep[-1]][0] + parts[keep[-1]][1]


def _committed(folder: Path) -> int:
    try:
        return (folder / STEPS).stat().st_size // 8
    except OSError:
        return 0


def read_index(path: Path) -> dict:
    """A recording folder's index, checked (one-line RecordingError otherwise)."""
    index_file = path / INDEX
    try:
        index = json.loads(index_file.read_text())
    except (OSError, ValueError) as exc:
        raise RecordingError(f"{index_file}: unreadable recording index ({exc})") from None
    if not isinstance(index, dict) or index.get("format") != FORMAT:
        raise RecordingError(f"{index_file}: not a lidarloc recording")
    if index.get("version") != VERSION:
        raise RecordingError(
            f"{index_file}: recording format version {index.get('version')}, this lidarloc reads version {VERSION}"
        )
    return index


class RecordingGone(RecordingError):
    """A recording's file went between its check and its read: the rolling window dropped it."""


def gone(f: Path) -> RecordingGone:
    return RecordingGone(
        f"{f}: no longer on disk (the recording budget dropped these steps since the recording was opened)"
    )


class Part:
    """One folder of a recording: its own steps 0 … :attr:`n` − 1, read on demand."""

    def __init__(self, path: Path, index: dict):
        self.path = Path(path)
        self.meta: dict = index.get("meta", {})
        self.fields: dict = index.get("fields", {})
        index_file = self.path / INDEX
        try:
            self.first_step = int(self.meta.get("first_step", 0) or 0)
            self.events_before = int((self.meta.get("segment") or {}).get("events_before", 0))
        except (TypeError, ValueError, AttributeError) as exc:
            raise RecordingError(f"{index_file}: corrupt recording index ({exc})") from None
        # A part of a rolling window can be dropped while it is opened (the recorder removes its
        # files): a file gone between here and its read counts as no rows, never as a failure.
        n = _committed(self.path)
        self._cache: dict[str, np.ndarray] = {}
        try:
            for name, info in self.fields.items():  # a step counts only if every field has its row
                if name in (PARTICLES[0], LOG_WEIGHTS[0]):
                    continue
                rows = self._rows_on_disk(name, info)
                n = min(n, info["first_step"] + rows) if rows >= 0 else n
            if n > 0:  # the particles of the last steps may be cut short too
                n_rows = min(
                    self._rows_on_disk(*named_field(self.fields, PARTICLES[0])),
                    self._rows_on_disk(*named_field(self.fields, LOG_WEIGHTS[0])),
                )
                while n > 0 and self.field("particle_rows", n)[n - 1].sum() > n_rows:
                    n -= 1
        except RecordingGone:  # a field's file went meanwhile: the part was dropped
            n = 0
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise RecordingError(f"{index_file}: corrupt recording index ({exc})") from None
        self.n = int(n)
        self._cache.clear()
        self._s2m_steps: list[int] | None = None
        self._events: list | None = None

    # ------------------------------------------------------------------ fields
    def _rows_on_disk(self, name: str, info: dict) -> int:
        f = self.path / f"{name}.bin"
        size = np.dtype(info["dtype"]).itemsize * int(np.prod(info["shape"], dtype=np.int64))
        try:
            return f.stat().st_size // size
        except FileNotFoundError:  # not written yet, or dropped with its part meanwhile
            return 0

    def field(self, name: str, n: int | None = None) -> np.ndarray:
        """A per-step field of this part's first ``n`` steps (default: all); steps before the
        field first appeared are NaN (floats) or 0."""
        n = self.n if n is None else n
        key = f"{name}:{n}"
        if key in self._cache:
            return self._cache[key]
        info = self.fields[name]
        dtype, shape, first = np.dtype(info["dtype"]), tuple(info["shape"]), int(info["first_step"])
        count = max(n - first, 0)
        f = self.path / f"{name}.bin"
        try:
            raw = np.fromfile(f, dtype=dtype, count=count * int(np.prod(shape, dtype=np.int64)))
        except FileNotFoundError:
            raise gone(f) from None
        arr = raw.reshape((count,) + shape)
        if first > 0:
            head = np.full((min(first, n),) + shape, np.nan if dtype.kind == "f" else 0, dtype=dtype)
            arr = np.concatenate([head, arr])
        if dtype == np.dtype("|u1") and name in FIELDS:
            arr = arr.astype(bool)
        self._cache[key] = arr
        return arr

    def _memmap(self, name: str) -> np.ndarray:
        if name not in self._cache:
            dtype, shape = (
                (np.dtype(PARTICLES[1]), PARTICLES[2]) if name == PARTICLES[0] else (np.dtype(LOG_WEIGHTS[1]), ())
            )
            f = self.path / f"{name}.bin"
            try:
                size = f.stat().st_size if f.is_file() else 0
                rows = size // (dtype.itemsize * int(np.prod(shape, dtype=np.int64)))
                self._cache[name] = (
                    np.memmap(f, dtype=dtype, mode="r", shape=(rows,) + shape)
                    if rows
                    else np.zeros((0,) + shape, dtype)
                )
            except FileNotFoundError:
                raise gone(f) from None
        return self._cache[name]

    def rows(self, name: str, j: int) -> np.ndarray:
        """Step j's rows of ``particles`` or ``log_weights``."""
        start, count = self.field("particle_rows")[j]
        return np.asarray(self._memmap(name)[start : start + count])

    # ------------------------------------------------------------------ events, S2M, resume
    @property
    def events(self) -> list[tuple[int, object]]:
        """(own step, Event) of every event of this part's steps; step -1: before its first step."""
        from ...snapshot import Event

        if self._events is None:
            out = []
            f = self.path / "events.jsonl"
            if f.is_file():
                # a damaged byte must not cost the events before it (a UnicodeDecodeError did)
                try:
                    text = f.read_text(encoding="utf-8", errors="replace")
                except FileNotFoundError:
                    raise gone(f) from None
                for line in text.splitlines():
                    try:
                        d = json.loads(line)
                        if d["step"] >= self.n:
                            break
                        event = Event(int(d["scan"]), str(d["kind"]), str(d.get("detail", "")))
                        out.append((int(d["step"]), event))
                    except (ValueError, KeyError, TypeError, AttributeError):
                        break  # a line cut short by a crash (or damaged): the steps after it are not complete
            self._events = out
        return self._events

    @property
    def s2m_steps(self) -> list[int]:
        """Own steps with a stored S2M view (-1: the view the part starts with), sorted."""
        if self._s2m_steps is None:
            steps = []
            try:
                files = list((self.path / "s2m").glob("*.json"))
            except OSError:
                files = []
            for f in files:
                try:
                    step = int(f.stem)
                except ValueError:
                    continue
                if step < self.n:
                    steps.append(step)
            self._s2m_steps = sorted(steps)
        return self._s2m_steps

    def s2m(self, step: int):
        f = self.path / "s2m" / f"{step:06d}.json"
        try:
            return load_s2m(self.path / "s2m", step)
        except FileNotFoundError:
            raise gone(f) from None
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise RecordingError(f"{f}: unreadable ({exc})") from None

    def resume_steps(self, name: str) -> list[int]:
        steps = []
        for f in (self.path / "resume").glob(f"*-{name}.npz"):
            try:
                step = int(f.name.split("-", 1)[0])
            except ValueError:
                continue
            if step < self.n:
                steps.append(step)
        return sorted(steps)

    def resume_file(self, step: int, name: str) -> dict[str, np.ndarray] | None:
        f = self.path / "resume" / f"{step:06d}-{name}.npz"
        if step >= self.n or not f.is_file():
            return None
        try:
            with np.load(f, allow_pickle=False) as z:
                return {k: z[k] for k in z.files}
        except FileNotFoundError:
            raise gone(f) from None
        except (OSError, ValueError) as exc:
            raise RecordingError(f"{f}: unreadable ({exc})") from None

"""The on-disk cache of maps and tables: where it lives, how entries are written, and what a
"load it, or build and cache it" function returns.

Entries are directories under the cache root (``$LIDARLOC_CACHE``, default ``~/.cache/lidarloc``;
``--cache`` on the CLI): a prior map per sequence and map configuration, and beside it the
tables derived from that map (lookup tables, BEV pyramids, recorded odometry). Every entry and
file is written under a temporary name and renamed into place, so a crash, Ctrl-C or a killed
child process never leaves a half-written one, and readers never see one. An entry found
unreadable all the same (cut short by an older version, a foreign file put in its place) is built
again, and the user is told (:func:`cache_rebuilt`).
"""

from __future__ import annotations

import hashlib
import logging
import os
import shutil
import tempfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Generic, TypeVar

T = TypeVar("T")


def default_cache_root() -> Path:
    """``$LIDARLOC_CACHE``, or ``~/.cache/lidarloc``."""
    return Path(os.environ.get("LIDARLOC_CACHE", Path.home() / ".cache" / "lidarloc"))


@dataclass(frozen=True)
class Cached(Generic[T]):
    """What a ``load_or_build_*`` function returns: the value, the cache directory it was read
    from or written to (None when not cached), and whether it came from the cache. Unpacks as
    ``value, directory, cached = load_or_build_...(...)``."""

    value: T
    directory: Path | None
    cached: bool

    def __iter__(self) -> Iterator:
        return iter((self.value, self.directory, self.cached))


def atomic_write_dir(final: Path, write: Callable[[Path], None]) -> None:
    """Write a directory's content into a temporary sibling and rename it into place, so a crash or
    Ctrl-C never leaves a half-written cache entry."""
    final = Path(final)
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=final.name + ".tmp-", dir=final.parent))
    try:
        write(tmp)
        if final.exists():
            shutil.rmtree(final)
        os.replace(tmp, final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def atomic_write_file(final: Path, write: Callable[[Path], None]) -> None:
    """Write a file under a temporary name beside it (unique per process and thread, with the
    final suffix, which ``np.save`` needs) and rename it into place: a reader sees the old file
    or the whole new one, never a part, also with several writers at once."""
    final = Path(final)
    final.parent.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(prefix=final.name + ".tmp-", suffix=final.suffix, dir=final.parent)
    os.close(fd)
    tmp = Path(name)
    try:
        write(tmp)
        os.chmod(tmp, _new_file_mode())  # mkstemp's 0600 would hide a run's results from others
        os.replace(tmp, final)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


#: Where a cache entry found unreadable is reported; without a configured handler Python's
#: last-resort handler prints the bare message on stderr (what the command line shows).
log = logging.getLogger("lidarloc.cache")


def cache_rebuilt(directory: Path, why: str) -> None:
    """Tell the user that the cache entry ``directory`` was unreadable (cut short by a crash
    before atomic writes, written by another version, replaced by a foreign file) and is being
    built again."""
    log.warning("lidarloc: warning: %s: unreadable cache entry (%s); building it again", directory, why)


def check_points(points, name: str, values: bool = True):
    """``points`` as a cache keeps them: a finite (N, 3) float array, else ValueError.
    ``values=False``: the shape and type only (a memory-mapped map is not read whole here)."""
    import numpy as np

    if not isinstance(points, np.memmap):
        points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 3 or points.dtype.kind != "f":
        raise ValueError(f"{name}: {points.dtype} array of shape {points.shape}, not (N, 3) floats")
    if values and not np.isfinite(points).all():
        raise ValueError(f"{name}: non-finite coordinates")
    return points


def _new_file_mode() -> int:
    """The mode ``open()`` gives a new file: 0666 less the process's umask (read from /proc:
    setting it to read it back is not thread-safe)."""
    umask = 0o022
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("Umask:"):
                    umask = int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    return 0o666 & ~umask


def file_identity(path) -> str:
    """A file's (or a folder's files') path, sizes and modification times: a source re-recorded
    under the same name is another source, and its cached map another entry."""
    p = Path(path)
    try:
        files = sorted(p.iterdir()) if p.is_dir() else [p]
        stats = [(f.name, f.stat().st_size, f.stat().st_mtime_ns) for f in files if f.is_file()]
    except OSError:
        stats = []
    return f"{p.resolve()}|{hashlib.sha1(repr(stats).encode()).hexdigest()[:12]}"


def array_digest(array) -> str:
    """A short digest of an array's bytes ("" for None), for cache keys."""
    if array is None:
        return ""
    import numpy as np

    return hashlib.sha1(np.ascontiguousarray(array).tobytes()).hexdigest()[:12]

"""A run's world on the machine that runs it: map, lookup table, pyramid, the town's scans and the
recorded odometry, built into that machine's cache once and then only loaded (memory-mapped).

On this machine the parent fills the cache before the runs start (a progress bar for the one long
build); a Ray cluster's other nodes have no cache yet, so the first run of a configuration on a
node builds it there, under a file lock, while that node's other runs of it wait, and leaves a
marker so later runs skip the check. Two processes building one entry at once would replace each
other's directory.
"""

from __future__ import annotations

import fcntl
import hashlib
import json
from pathlib import Path

from ...core.cache import default_cache_root

MARKERS = "sweep-worlds"


def world_key(spec_d: dict, cfg_d: dict) -> str:
    """What decides a world's cache entries: the source and the configuration (the seed aside)."""
    text = json.dumps({"source": spec_d, "config": {k: v for k, v in cfg_d.items() if k != "seed"}}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:24]


def ensure_world(spec_d: dict, cfg_d: dict, cache: str | None, numba_threads: int = 0) -> None:
    """The world of (``spec_d``, ``cfg_d``) in this machine's cache, built here once if missing."""
    from ..bench.localize import prepare_one

    root = Path(cache) if cache else default_cache_root()
    folder = root / MARKERS
    folder.mkdir(parents=True, exist_ok=True)
    key = world_key(spec_d, cfg_d)
    marker = folder / f"{key}.ready"
    if marker.is_file():
        return
    with open(folder / f"{key}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes, also if this process dies
        if not marker.is_file():
            prepare_one(spec_d, cfg_d, cache, numba_threads)
            marker.write_text("")


def mark_ready(spec_d: dict, cfg_d: dict, cache: str | None) -> None:
    """The parent built this world itself: the runs need not check it again."""
    root = Path(cache) if cache else default_cache_root()
    (root / MARKERS).mkdir(parents=True, exist_ok=True)
    (root / MARKERS / f"{world_key(spec_d, cfg_d)}.ready").write_text("")

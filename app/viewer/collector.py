"""Keep the garbage collector's full collections short in the long-running viewer, and time them.

A full collection walks every object the collector tracks, holding the GIL: in the playing demo
that is ~219 k objects (the modules of numpy, scipy, numba, open3d and viser, the map's and the
server's objects), 106–110 ms a collection on the reference machine, long enough to make a scan
of the real-time clock late when it lands as the scan is due. Nearly all of them are made while
the viewer starts and live as long as the process, so once the localizer is ready they are moved
out of the collector's reach (:func:`freeze_startup`, ``gc.freeze()``); a full collection then
walks what was made since, 0.5–0.9 ms for the same process (docs/benchmarks/long-running.md).

The price: a frozen object is never collected. What becomes garbage by reference counts is freed
as always; only garbage held in reference cycles among the frozen objects stays. The frozen ones
are the process's start-up state (modules, the map, the tables, the server, and the first run as
it stands when the localizer is ready); later runs' state is made after the freeze and is
collected as before. It is called once, so what it can keep is bounded by the start-up state,
not by how long the viewer runs or how many times it loops.

:class:`FullCollections` times the full collections (a ``gc.callbacks`` hook) so that each loop's
line can say how many ran and the longest.
"""

from __future__ import annotations

import gc
import threading
import time


def freeze_startup() -> int:
    """Move every object the collector tracks now out of its reach (see the module docstring);
    how many objects are frozen in all."""
    gc.freeze()
    return gc.get_freeze_count()


def release_at_exit() -> None:
    """Called once the viewer has stopped and the command is about to return (the process ends
    with it): the objects made so far are frozen out of the garbage collector. The interpreter's
    last collections otherwise walk all of them (the map, the tables, the server's state) on the
    way out: 0.9 s of a 1.2 s Ctrl-C with both cores busy; the memory goes back with the process."""
    gc.freeze()


class FullCollections:
    """Counts the full (oldest-generation) collections and the longest one, from :meth:`take` to
    :meth:`take`; :meth:`close` unhooks it."""

    def __init__(self) -> None:
        # re-entrant: a collection can start while take() holds the lock on the same thread
        self._lock = threading.RLock()
        self._began: float | None = None  # the running collection's start (the interpreter runs one at a time)
        self._count = 0
        self._longest_s = 0.0
        gc.callbacks.append(self._on_collection)

    def _on_collection(self, phase: str, info: dict) -> None:
        if info.get("generation") != 2:
            return
        now = time.perf_counter()
        with self._lock:
            if phase == "start":
                self._began = now
                return
            if self._began is not None:
                self._count += 1
                self._longest_s = max(self._longest_s, now - self._began)
                self._began = None

    def take(self) -> dict:
        """``{"count": n, "longest_ms": t}`` since the last call (or the start); starts again from zero."""
        with self._lock:
            out = {"count": self._count, "longest_ms": round(1000.0 * self._longest_s, 1)}
            self._count, self._longest_s = 0, 0.0
        return out

    def close(self) -> None:
        try:
            gc.callbacks.remove(self._on_collection)
        except ValueError:  # closed already
            pass

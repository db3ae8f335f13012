"""Give the memory a closed tab or a finished run freed back to the system.

Each tab that connects is sent the whole scene (the map's points, the panel), and each restart
drops a localizer's run; Python frees those objects, but glibc's allocator keeps the freed heap
pages for later and the process's resident memory stays up. Measured on the live viewer with a
websocket tab connecting and disconnecting 20 times a second: every connection's objects were
freed (no client handle left, nothing traced), yet the resident memory rose ~33 MB over the first
650 connections and ~4 kB a connection after that; ``malloc_trim`` gave all of it back in
1.4–4.3 ms of CPU. So after a tab leaves or a run restarts the viewer trims the heap, at most
once per :data:`MIN_INTERVAL_S`, on a thread of its own (never on the server's event loop or the
filter's threads). Where the C library is not glibc there is nothing to call and nothing is done.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import threading

#: At most one trim per this many seconds (a tab reloading in a loop must not cost a trim each).
MIN_INTERVAL_S = 5.0


#: glibc's mallopt parameter for the most malloc arenas (malloc.h: M_ARENA_MAX).
M_ARENA_MAX = -8
#: The viewer's arenas. glibc gives threads that contend for the heap arenas of their own, up to
#: 8 a core, and each keeps its freed pages: with five tabs and one connecting and disconnecting
#: 30 times a second, the viewer's memory rose 239 MB over the first half of 1908 connections
#: with glibc's default, 48 MB over 1790 with two arenas (``MALLOC_ARENA_MAX=2``; 10.0 scans/s
#: both times, the display update 2.1–3.2 ms median per phase against 2.0–2.5, at a load of 6.4
#: against 4.9). Over the second half the figure moves from run to run either way (−13 to +28 MB).
VIEWER_ARENAS = 2


def _libc():
    try:
        return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    except OSError:
        return None


def _malloc_trim():
    """glibc's ``malloc_trim``, or None where the C library has none."""
    return getattr(_libc(), "malloc_trim", None)


def limit_arenas(arenas: int = VIEWER_ARENAS) -> bool:
    """Cap glibc's malloc arenas for this process (see :data:`VIEWER_ARENAS`); call it before the
    process starts threads. A ``MALLOC_ARENA_MAX`` the user set wins. True if the cap was set."""
    if os.environ.get("MALLOC_ARENA_MAX"):
        return False
    mallopt = getattr(_libc(), "mallopt", None)
    return bool(mallopt is not None and mallopt(M_ARENA_MAX, arenas) == 1)


class HeapTrimmer:
    """A daemon thread that trims the heap when :meth:`request` ed, at most once per
    ``min_interval_s``; :meth:`stop` ends it."""

    def __init__(self, min_interval_s: float = MIN_INTERVAL_S):
        self._trim = _malloc_trim()
        self._interval = min_interval_s
        self._wanted = threading.Event()
        self._stopping = threading.Event()
        self.trims = 0  # how many trims ran (tests)
        self._thread = threading.Thread(target=self._loop, name="lidarloc-heap-trim", daemon=True)
        if self._trim is not None:
            self._thread.start()

    @property
    def available(self) -> bool:
        return self._trim is not None

    def request(self, *_args) -> None:
        """Trim soon (callable as a viser callback: its arguments are ignored)."""
        self._wanted.set()

    def stop(self) -> None:
        self._stopping.set()
        self._wanted.set()
        if self._thread.is_alive():
            self._thread.join(timeout=5.0)

    def _loop(self) -> None:
        while True:
            self._wanted.wait()
            if self._stopping.is_set():
                return
            self._wanted.clear()
            self._trim(0)
            self.trims += 1
            if self._stopping.wait(self._interval):  # requests meanwhile wait for the next turn
                return

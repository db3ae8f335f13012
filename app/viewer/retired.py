"""Localizers the viewer switched away from (a branch took over) while they close on threads of
their own: closing one waits for its child processes, which a busy machine can make slow, and the
page must not wait for that. When the viewer stops, the children of any still closing are killed,
so that none outlives the viewer's process."""

from __future__ import annotations

import threading


class Retired:
    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._closing: list[tuple[object, threading.Thread]] = []

    def close(self, localizer) -> threading.Thread:
        """Close ``localizer`` on a thread of its own, returned (it holds its map and tables until
        then; entries whose close has finished are let go here)."""
        closer = threading.Thread(target=localizer.close, name="lidarloc-close", daemon=True)
        with self._lock:
            self._closing = [(loc, t) for loc, t in self._closing if t.is_alive()]
            self._closing.append((localizer, closer))
        closer.start()
        return closer

    def kill_unfinished(self) -> int:
        """Kill the child processes of every localizer still closing (safe while its close runs);
        returns how many there were."""
        with self._lock:
            unfinished = [loc for loc, t in self._closing if t.is_alive()]
            self._closing = []
        for loc in unfinished:
            loc.kill_processes()
        return len(unfinished)

"""The "why" views' background thread: heavy work (a likelihood surface, a particle's rank among all
particles) runs here, never on the display thread or a GUI callback's thread.

Only the newest job of each kind matters: a new one replaces a pending one of its kind, and a
running one's result is dropped when a newer job of its kind (or :meth:`LatestOnly.cancel`) came
in meanwhile — unless it was submitted with ``superseded_ok``: when the surface on every scan takes
longer than a scan (a loaded machine at 10 scans/s), dropping each result because the next scan's
job had arrived left none drawn while playing. Results are delivered under a lock that ``cancel``
also takes, so once ``cancel`` returns no stale result reaches the scene (a restart must leave
nothing of the old run)."""

from __future__ import annotations

import sys
import threading
import traceback
from collections.abc import Callable

from ...core.errors import LidarlocError


class LatestOnly:
    def __init__(self, name: str = "lidarloc-why"):
        self._cv = threading.Condition()
        self._deliver = threading.RLock()  # done() may cancel (a restart from a callback)
        self._pending: dict[str, tuple] = {}
        self._ticket: dict[str, int] = {}
        self._epoch: dict[str, int] = {}  # bumped by cancel: no result from before it counts
        self._running: str | None = None
        self._stopped = False
        self._thread = threading.Thread(target=self._loop, name=name, daemon=True)
        self._thread.start()

    def submit(
        self,
        kind: str,
        work: Callable[[], object],
        done: Callable[[object], None],
        failed: Callable[[str], None],
        superseded_ok: bool = False,
    ) -> None:
        """Run ``work()`` on the thread, then ``done(result)`` if no newer job of ``kind`` came in
        (with ``superseded_ok``: unless ``cancel`` was called); ``failed(message)`` if it raised."""
        with self._cv:
            if self._stopped:
                return
            ticket = self._ticket.get(kind, 0) + 1
            self._ticket[kind] = ticket
            self._pending.pop(kind, None)  # re-inserted last: kinds take turns
            self._pending[kind] = (ticket, self._epoch.get(kind, 0), superseded_ok, work, done, failed)
            self._cv.notify()

    def cancel(self, kind: str | None = None) -> None:
        """Forget pending jobs of ``kind`` (every kind if None) and drop a running one's result."""
        with self._deliver, self._cv:
            for k in list(self._ticket) if kind is None else [kind]:
                self._ticket[k] = self._ticket.get(k, 0) + 1
                self._epoch[k] = self._epoch.get(k, 0) + 1
                self._pending.pop(k, None)

    @property
    def idle(self) -> bool:
        """Nothing pending and nothing running."""
        with self._cv:
            return not self._pending and self._running is None

    def stop(self, timeout: float = 0.2) -> None:
        """End the thread. A computation in progress is not waited for beyond ``timeout`` (the
        viewer's stop is bounded): it finishes on the daemon thread and its result is dropped."""
        with self._cv:
            self._stopped = True
            self._pending.clear()
            self._cv.notify()
        self._thread.join(timeout)

    def _loop(self) -> None:
        while True:
            with self._cv:
                while not self._pending and not self._stopped:
                    self._cv.wait()
                if self._stopped:
                    return
                kind = next(iter(self._pending))
                ticket, epoch, superseded_ok, work, done, failed = self._pending.pop(kind)
                self._running = kind
            try:
                try:
                    result, error = work(), None
                except LidarlocError as exc:
                    result, error = None, str(exc)
                except Exception as exc:  # keep the thread alive and say what went wrong
                    traceback.print_exc(file=sys.stderr)
                    result, error = None, f"internal error: {type(exc).__name__}: {exc}"
                with self._deliver:
                    with self._cv:
                        current = not self._stopped and (
                            self._ticket.get(kind) == ticket or (superseded_ok and self._epoch.get(kind, 0) == epoch)
                        )
                    if current:
                        try:
                            done(result) if error is None else failed(error)
                        except Exception:  # a failed drawing must not end the thread
                            traceback.print_exc(file=sys.stderr)
            finally:
                with self._cv:
                    self._running = None

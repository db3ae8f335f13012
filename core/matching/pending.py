"""What stands in for the S2M block while its tables are still being built in the background.

A viewer started on an empty cache can play as soon as the particle filter's map and lookup table
exist; the road-removed map, the BEV pyramid and the S2M process follow in the background
(``Localizer(defer_s2m=True)``). Until they are there the localizer holds a :class:`S2MNotReady`
in place of its :class:`~lidarloc.core.matching.schedule.S2MScheduler`: no match is ever due, none
lands, and nothing needs cancelling.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from concurrent.futures import Future


class S2MNotReady:
    """The :class:`~lidarloc.core.matching.schedule.S2MScheduler` interface, doing nothing."""

    matcher = None
    job = None
    last = None
    acceptance = 0.0
    protected_particle = None
    n_landed = 0
    n_accepted = 0
    verdict = None

    def restart(self) -> None:
        pass

    def checkpoint(self) -> tuple[dict, dict]:
        return {"pending": True, "generation": 0, "last_start": None, "n_landed": 0, "n_accepted": 0, "job": None}, {}

    def restore(self, state: dict, arrays, scan_of) -> None:
        pass

    def held_back(self, k: int) -> bool:
        return True

    def due(self, k: int, localized: bool, check: bool = False) -> bool:
        return False

    def land(self, k, prepared, pf, odometry, fits_better=None, land_by=None) -> None:
        return None

    def cancel(self, k: int, why: str) -> None:
        pass

    def follow_particle(self, index) -> None:
        pass

    def follow_clock(self, k: int) -> None:
        pass

    def use_pyramid(self, k: int, pyramid) -> None:
        pass

    def close_processes(self) -> None:
        pass

    def kill_processes(self) -> None:
        pass


def in_daemon_thread(work: Callable[[], object], name: str) -> Future:
    """Run ``work`` on a daemon thread and return its Future. Not a pool: a pool's threads are
    joined when Python exits, and Ctrl-C in the first seconds of a viewer would then wait for the
    road removal (~10 s) to finish; the result is cached only once it is whole, so dropping it
    loses nothing."""
    future: Future = Future()

    def run():
        if not future.set_running_or_notify_cancel():
            return
        try:
            future.set_result(work())
        except BaseException as exc:  # handed to whoever waits for it
            future.set_exception(exc)

    threading.Thread(target=run, name=name, daemon=True).start()
    return future

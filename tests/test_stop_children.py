"""The viewer's process never ends with a child process of its localizer still running: when the
localizer's orderly close does not finish in the short time a stop allows (a busy machine), its
children are killed outright before the process returns."""

from __future__ import annotations

import threading

from helpers import process_gone, wait_for
from lidarloc.app.viewer.serve import serve


def test_a_stop_whose_close_is_late_kills_the_children(street, cache_root):
    from helpers import make_localizer

    built = []

    def factory(progress=None):
        built.append(make_localizer(street, cache_root))
        return built[0]

    handle = serve(factory, port=0, autoplay=False)
    stuck = threading.Event()
    try:
        assert handle.wait_ready(300)
        loc = built[0]
        loc.wait_ready()  # both children have started and finished their set-up
        pids = [loc.odometry.process.pid, loc.s2m.matcher.pid]
        loc.close = stuck.wait  # an orderly close that does not end in time (the instance's own)
        handle.stop()
        # killed, not left to notice the parent's end (they would idle, waiting on their pipe)
        wait_for(lambda: all(process_gone(p) for p in pids), timeout=5, what=f"children {pids} gone")
    finally:
        stuck.set()
        handle.stop()
        for loc in built:
            vars(loc).pop("close", None)  # the class's close again
            loc.close()

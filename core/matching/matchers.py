"""The S2M matcher an :class:`~lidarloc.core.matching.schedule.S2MScheduler` drives: the child process
(or, with ``localize.s2m_process`` off, a matcher on the S2M thread), started when first needed,
replaced by a fresh one when the clock changes its priority or when it died, and closed at the end.

A dead child is found by :meth:`MatcherMixin.check_matcher` at the start of each step, or by the
landing of the match it was running; either way the match in flight is cancelled and a
``restarted`` event says what happened (see the scheduler's module docstring).
"""

from __future__ import annotations

from .worker import S2MProcess


class MatcherMixin:
    """The scheduler's matcher (see the module docstring). A part of
    :class:`~lidarloc.core.matching.schedule.S2MScheduler`, which sets the attributes used here."""

    def start_matcher(self) -> None:
        """Start the matcher unless it runs already (the S2M child process loads the cached map and
        pyramid and builds its GICP target while the caller goes on)."""
        if self.matcher is not None:
            return
        if self.cfg.localize.s2m_process:
            self.matcher = self._process(self._nice())
        else:
            self.matcher = self._in_process(self._pyramid)

    def _process(self, nice: int) -> S2MProcess:
        """A new S2M child process at ``nice``; on a map held as point tiles, told where they are."""
        tiles = getattr(self._prior_map, "tiles", None)
        return S2MProcess(
            self._map_dir, self.cfg.map, self.cfg.s2m, nice, point_tiles=None if tiles is None else tiles.directory
        )

    def _nice(self) -> int:
        """The S2M process's priority offset for the current clock (see s2m.replay_process_nice)."""
        return self.cfg.s2m.replay_process_nice if self.cfg.localize.clock == "replay" else 0

    def follow_clock(self, k: int) -> None:
        """After a clock change: a process niced for replay cannot be raised back (that needs
        privileges), so real time gets a fresh one at nice 0 (the match in flight is cancelled
        at scan k). The old one finishes its match on the S2M thread, which then closes it; the
        caller does not wait."""
        nice = self._nice()
        # same nice, or back to replay (a higher priority there changes no result): keep it
        if not isinstance(self.matcher, S2MProcess) or nice >= self.matcher.nice:
            return
        self.cancel(k, "clock changed: new S2M process")
        old, self.matcher = self.matcher, self._process(nice)
        self._retired_matchers.append(old)  # close() kills it if its match is still running
        self._pool.submit(old.close)

    def use_pyramid(self, k: int, pyramid) -> None:
        """A rebuilt BEV pyramid (new d_m) from now on; the match in flight is cancelled at scan k."""
        self.cancel(k, "map pyramid rebuilt")
        self._pyramid = pyramid
        if self.matcher is not None and not isinstance(self.matcher, S2MProcess):
            # (the S2M process reloads it from the cache itself)
            self.matcher = self._in_process(pyramid)

    def _in_process(self, pyramid):
        """A matcher in this process, with the place index from the map's cache (or built there)."""
        from ..maps.places import places_for_pyramid, uses_places
        from .s2m import ScanToMapMatcher

        s2m = self.cfg.s2m
        places = None
        if uses_places(s2m, pyramid.shape):
            places = places_for_pyramid(pyramid, self._prior_map.points, self._map_dir, s2m)
        return ScanToMapMatcher(self._prior_map, pyramid, s2m, self.cfg.map, places=places)

    def check_matcher(self, k: int) -> None:
        """The start of step k: if the S2M child died, cancel the match in flight, start a new
        child and record a ``restarted`` event (see the module docstring). Raises BlockError when
        the child died again at once."""
        if isinstance(self.matcher, S2MProcess) and (
            not self.matcher.alive or self.matcher.restarts != self._restarts_seen
        ):
            self._matcher_died(k)

    def _matcher_died(self, k: int, died=None) -> None:
        matcher = self.matcher
        self.cancel(k, "its S2M process died")
        words = matcher.revive(died) if isinstance(matcher, S2MProcess) else None
        if isinstance(matcher, S2MProcess) and matcher.restarts != self._restarts_seen:
            self._restarts_seen = matcher.restarts
            self._event(k, "restarted", f"S2M: {words or 'the S2M process died; a new one was started'}")

    def _processes(self) -> list[S2MProcess]:
        """The S2M child processes: the current matcher's and the retired ones'."""
        return [m for m in (self.matcher, *self._retired_matchers) if isinstance(m, S2MProcess)]

    def close_processes(self) -> None:
        """Close the S2M child processes (a busy one is killed: its match would be thrown away)."""
        for process in self._processes():
            process.close()

    def kill_processes(self) -> None:
        """Kill the S2M child processes at once, without waiting (the process is about to exit)."""
        for process in self._processes():
            process.kill()

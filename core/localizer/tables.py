"""The localizer's tables in the background: S2M's road-removed map and BEV pyramid on a viewer's
cold start (S2M joins at the first scan after they are ready), and a lookup table or pyramid rebuilt
after a live d_max or d_m change (swapped in at the next scan; the old one serves meanwhile)."""

from __future__ import annotations

from dataclasses import replace

from ..matching.schedule import S2MScheduler

#: The ``s2m_ready`` event's detail: S2M joins once its tables are built (``defer_s2m``).
S2M_READY_DETAIL = "road-removed map and BEV pyramid built in the background"


class TablesMixin:
    """Background builds and what S2M can do meanwhile (see the module docstring). A part of :class:`~lidarloc.core.localizer.Localizer`."""

    @property
    def s2m_pending(self) -> bool:
        """Whether S2M is still waiting for its tables (road-removed map, BEV pyramid) to be built
        in the background (``defer_s2m``); it joins at the first scan after they are ready."""
        return self._pending_s2m is not None

    def s2m_status(self, k: int | None = None) -> tuple[str, str]:
        """Whether S2M can give its word at scan ``k`` (default: the next scan), and why not:
        ("ready", ""), ("building", "road removal 40 %"), ("held", "held back until scan 100") or
        ("off", "switched off"). Safe from any thread (a viewer asks while a cold start builds
        the tables)."""
        k = self.k if k is None else k
        if self._pending_s2m is not None:
            removal = self._road_removal
            if removal is not None and removal.progress < 1.0:
                return "building", f"road removal {100 * removal.progress:.0f} %"
            return "building", "road removal" if removal is None else "BEV pyramid"
        if not self.cfg.s2m.enabled:
            return "off", "switched off"
        if k < self.cfg.s2m.join_at_scan:
            return "held", f"held back until scan {self.cfg.s2m.join_at_scan}"
        return "ready", ""

    @property
    def s2m_tables_built(self) -> bool:
        """Whether S2M's tables are there (built in the background on a cold start, ``defer_s2m``):
        S2M joins at the next scan."""
        return self._pending_s2m is None or self._pending_s2m.done()

    @property
    def rebuilding(self) -> bool:
        """Whether a lookup table or BEV pyramid is still being rebuilt in the background (after a
        live d_max or d_m change); a finished one is swapped in at the next scan."""
        return any(f is not None and not f.done() for f in (self._pending_lookup, self._pending_pyramid))

    def _rebuild_lookup(self, d_max: float) -> None:
        from ..maps.lookup import load_or_build_lookup

        if self._pending_lookup is not None and not self._pending_lookup.done():
            return
        self.rebuild_progress = 0.0

        def build():
            def progress(f):
                self.rebuild_progress = float(f)

            return load_or_build_lookup(
                self.prior_map, self.map_dir, self.cfg.pf.lookup_resolution, d_max, progress=progress
            ).value

        self._pending_lookup = self._rebuild_pool.submit(build)

    def _s2m_scheduler(self) -> S2MScheduler:
        return S2MScheduler(
            self.cfg,
            self.prior_map,
            self.pyramid,
            self.map_dir,
            self._bounds,
            self._s2m_pool,
            wait=self._wait,
            event=self._event,
            start_matcher=not self._lazy_s2m,
        )

    def _build_s2m_tables(self):
        """The road-removed map and the BEV pyramid (cached both), on a background thread; the
        road removal itself in a child process (:mod:`~lidarloc.core.maps.road_removal`: open3d would
        hold the GIL for its whole run)."""
        from ..maps.bev import load_or_build_pyramid
        from ..maps.mapping import BEV_FILE, load_or_build_road_removed
        from ..maps.road_removal import RoadRemovalProcess

        if not (self.map_dir / BEV_FILE).is_file():
            self._road_removal = RoadRemovalProcess(self.map_dir, self.cfg.map)
            if self._closed:  # closed meanwhile: nobody needs it
                self._road_removal.kill()
            self._road_removal.wait()
        prior = load_or_build_road_removed(self.prior_map, self.map_dir, self.cfg.map)  # reads the child's file
        return prior.points_bev, load_or_build_pyramid(prior, self.map_dir, replace(self.cfg.s2m)).value

    def _join_s2m(self) -> None:
        """S2M's tables are ready (``defer_s2m``): the real scheduler takes over from this scan."""
        fut, self._pending_s2m = self._pending_s2m, None
        bev, self.pyramid = self._wait(fut, "road removal and BEV pyramid", self.k)
        self.prior_map.points_bev = bev  # in place: a viewer holding the map sees it too
        self.s2m = self._s2m_scheduler()
        self._event(self.k, "s2m_ready", S2M_READY_DETAIL)
        if abs(self.pyramid.resolution - self.cfg.s2m.match_resolution) > 1e-9:  # changed meanwhile
            self._rebuild_pyramid()

    def _rebuild_pyramid(self) -> None:
        from ..maps.bev import load_or_build_pyramid

        if self._pending_s2m is not None:  # the pyramid being built follows the new value on arrival
            return
        self.rebuild_progress = 0.0
        cfg = replace(self.cfg.s2m)
        self._pending_pyramid = self._rebuild_pool.submit(
            lambda: load_or_build_pyramid(self.prior_map, self.map_dir, cfg).value
        )

    def _swap_rebuilt_tables(self) -> None:
        if self._pending_s2m is not None and self._pending_s2m.done():
            self._join_s2m()
        if self._pending_lookup is not None and self._pending_lookup.done():
            fut, self._pending_lookup = self._pending_lookup, None
            self.lookup = self._wait(fut, "lookup rebuild", self.k)
            self.pf.set_lookup(self.lookup)
            self.pf.set_d_max(self.effective_d_max)
            if not self.lookup.covers(self.cfg.pf.d_max):  # raised again meanwhile
                self._rebuild_lookup(self.cfg.pf.d_max)
        if self._pending_pyramid is not None and self._pending_pyramid.done():
            fut, self._pending_pyramid = self._pending_pyramid, None
            self.pyramid = self._wait(fut, "pyramid rebuild", self.k)
            self.s2m.use_pyramid(self.k, self.pyramid)
        if self._pending_lookup is None and self._pending_pyramid is None:
            self.rebuild_progress = None

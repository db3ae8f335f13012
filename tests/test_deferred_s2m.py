"""A viewer's first start on an empty cache plays before S2M's tables exist
(``Localizer(defer_s2m=True)``): the particle filter runs from scan 0, the road-removed map and the
BEV pyramid are built in the background and cached, and S2M joins at the next scan."""

from __future__ import annotations

import threading

import numpy as np
import pytest
from helpers import short_town, wait_for
from lidarloc.core.config import Config
from lidarloc.core.localizer import Localizer
from lidarloc.core.maps.mapping import BEV_FILE, load_or_build_map


@pytest.fixture
def held_tables(monkeypatch):
    """The background build of S2M's tables waits until the test sets the returned event, so the
    test sees the state before and after it whatever the machine's speed."""
    go = threading.Event()
    build = Localizer._build_s2m_tables

    def held(self):
        assert go.wait(300), "the test never released the background build"
        return build(self)

    monkeypatch.setattr(Localizer, "_build_s2m_tables", held)
    return go


def test_s2m_joins_once_its_tables_are_built_and_the_cache_keeps_them(tmp_path, held_tables):
    seq = short_town(20)
    cfg = Config()
    cfg.pf.n_particles = 300
    shown = []
    loc = Localizer(seq, cfg, tmp_path, on_map=shown.append, defer_s2m=True)
    try:
        # the map reached the viewer before the tables were built, without its road-removed copy
        assert len(shown) == 1 and shown[0] is loc.prior_map and len(shown[0].points) > 100_000
        assert loc.s2m_pending and loc.pyramid is None
        snap = loc.step()  # the filter plays meanwhile
        assert snap.scan_index == 0 and np.isfinite(snap.mean_pose).all() and snap.s2m_pending
        assert loc.s2m_pending and not any(e.kind.startswith("s2m") for e in loc.events)
        held_tables.set()
        wait_for(lambda: loc.s2m_tables_built, timeout=300, what="road removal and pyramid")
        loc.step()
        assert not loc.s2m_pending and loc.pyramid is not None
        assert loc.prior_map.points_bev is not None and 0 < len(loc.prior_map.points_bev) < len(loc.prior_map.points)
        kinds = [e.kind for e in loc.events]
        assert "s2m_ready" in kinds and "s2m_started" in kinds  # S2M works from then on
        assert kinds.index("s2m_ready") < kinds.index("s2m_started")
        assert (loc.map_dir / BEV_FILE).is_file()
    finally:
        loc.close()
    # the next start finds everything cached: the same road-removed map, no deferral
    again = load_or_build_map(seq.map_source, cfg.map, tmp_path).value
    np.testing.assert_array_equal(again.points_bev, loc.prior_map.points_bev)
    loc2 = Localizer(seq, cfg, tmp_path, defer_s2m=True)
    try:
        assert not loc2.s2m_pending and loc2.pyramid is not None
    finally:
        loc2.close()


def test_viewer_plays_while_s2m_tables_are_built_then_shows_them(tmp_path, held_tables):
    """The viewer's first start (the demo's factory defers S2M): playback and the status do not
    wait for road removal; the road-removed map layer and the BEV level control appear once it
    is done."""
    from lidarloc.app.viewer.serve import serve

    seq = short_town(40)
    cfg = Config()
    cfg.pf.n_particles = 300

    def factory(progress=None, on_map=None):
        return Localizer(seq, cfg, tmp_path, progress=progress, on_map=on_map, defer_s2m=True)

    handle = serve(factory, port=0, autoplay=False)
    try:
        v = handle.viewer
        assert handle.wait_ready(300)
        loc = v.localizer
        assert loc.s2m_pending
        v.step_once()
        wait_for(lambda: v.latest is not None and v.latest.scan_index == 0, timeout=60, what="scan 0")
        v.update_display()
        status = v.controls.status.content
        assert "building in the background" in status and "S2M not ready" in status and "**localized**" not in status
        assert not v.scene.has_map_bev and not v.controls.bev_level.visible
        held_tables.set()
        wait_for(lambda: loc.s2m_tables_built, timeout=300, what="road removal and pyramid")
        v.step_once()
        wait_for(lambda: v.latest.scan_index == 1, timeout=60, what="scan 1")
        v.update_display()
        assert not loc.s2m_pending and v.scene.has_map_bev and v.controls.bev_level.visible
        assert "being built" not in v.controls.status.content
    finally:
        handle.stop()

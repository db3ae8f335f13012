"""The S2M inspection (app/viewer/s2m_detail.py) against a real viser server: the nodes it creates
for a landed match, what it leaves out when the match never got that far, hiding and showing,
clearing after a restart; and the panel's markdown for accepted, rejected and no match."""

import math

import numpy as np
import pytest
import viser
from lidarloc.app.viewer.s2m_detail import ROOT, WINNER_ARROW, S2MDetailView, carried_pose, s2m_detail_markdown
from lidarloc.core.geometry import pose_matrix
from lidarloc.core.snapshot import S2MView

DEG = math.pi / 180


@pytest.fixture(scope="module")
def server():
    srv = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    yield srv
    srv.stop()


def scene_nodes(server) -> set:
    """Names of the nodes under ROOT that the server itself holds (what a browser would receive).
    viser has no public listing of scene nodes, so this one check reads its registry; everything
    else goes through the view's own handles."""
    return {n for n in server.scene._handle_from_node_name if n == ROOT or n.startswith(ROOT + "/")}


def accepted_view(started_at=10) -> S2MView:
    start = pose_matrix(100.0, 50.0, 1.7, 30 * DEG, 0.0, 0.0)
    match = pose_matrix(104.0, 47.0, 1.7, 40 * DEG, 0.0, 0.0)
    gicp = pose_matrix(104.3, 46.8, 1.72, 41 * DEG, 0.0, 0.0)
    carried = pose_matrix(107.0, 46.0, 1.72, 41 * DEG, 0.0, 0.0)
    candidates = np.array(
        [
            [104.0, 47.0, 40 * DEG, 5200.0],
            [105.0, 47.0, 40 * DEG, 4900.0],
            [104.0, 48.0, 37.5 * DEG, 4100.0],
            [90.0, 60.0, -170 * DEG, 3000.0],
        ]
    )
    return S2MView(
        started_at=started_at,
        landed_at=started_at + 2,
        accepted=True,
        score=5200.0,
        start_score=4000.0,
        pose=carried,
        scan_world=np.zeros((0, 3), np.float32),
        region=(75.0, 25.0, 125.0, 75.0),
        ms=180.0,
        mode="local",
        start_pose=start,
        candidates=candidates,
        nodes_per_level=(0, 1, 3, 40, 12),
        match_pose=match,
        gicp_pose=gicp,
        gicp_fitness=0.83,
        gicp_correction=(0.36, 1.0 * DEG),
        stage="m3rsm",
    )


def refused_before_gicp() -> S2MView:
    start = pose_matrix(10.0, 5.0, 1.7, 0.0, 0.0, 0.0)
    return S2MView(
        started_at=3,
        landed_at=5,
        accepted=False,
        score=0.0,
        start_score=0.0,
        pose=start.copy(),
        scan_world=np.zeros((0, 3), np.float32),
        region=(-15.0, -20.0, 35.0, 30.0),
        ms=20.0,
        reason="too few road-removed scan points to match",
        mode="global",
        start_pose=start,
    )


def test_draws_each_part_of_a_landed_match_and_clears_it(server):
    view = S2MDetailView(server.scene)
    v = accepted_view()
    view.draw(v, visible=True)
    parts = {
        ROOT + "/" + p for p in ("candidates", "winner", "start", "refined", "refine_line", "carried", "carried_ring")
    }
    assert scene_nodes(server) == {ROOT} | parts
    assert set(view.node_names) == {ROOT} | parts
    h = {name: view.handle(name) for name in view.node_names}
    # the winner: the best candidate, drawn bigger than the others; the others one arrow each
    winner = np.asarray(h[ROOT + "/winner"].points)
    assert winner.shape == (1, 2, 3)
    assert winner[0, 0, :2] == pytest.approx(v.candidates[0, :2])
    assert np.linalg.norm(winner[0, 1] - winner[0, 0]) == pytest.approx(WINNER_ARROW, rel=1e-5)
    others = h[ROOT + "/candidates"]
    assert np.asarray(others.points).shape == (len(v.candidates) - 1, 2, 3)
    assert h[ROOT + "/winner"].shaft_radius > others.shaft_radius
    colors = np.asarray(others.colors).reshape(-1, 3).astype(int)
    assert np.all(np.diff(colors.sum(axis=1)) <= 0)  # dimmer down the ranking
    # the line from the 2D match to GICP's pose, both at their own heights
    line = np.asarray(h[ROOT + "/refine_line"].points)[0]
    assert line[0] == pytest.approx(v.match_pose[:3, 3], abs=1e-5)
    assert line[1] == pytest.approx(v.gicp_pose[:3, 3], abs=1e-5)
    assert np.asarray(h[ROOT + "/carried"].points)[0, 0] == pytest.approx(v.pose[:3, 3], abs=1e-5)

    # the same view again sends nothing new; a new one replaces the old nodes
    before = h[ROOT + "/winner"]
    view.draw(v, visible=True)
    assert view.handle(ROOT + "/winner") is before
    view.draw(accepted_view(started_at=12), visible=True)
    assert view.handle(ROOT + "/winner") is not before
    assert scene_nodes(server) == {ROOT} | parts

    view.clear()
    assert scene_nodes(server) == set() and view.node_names == []
    view.draw(None, visible=True)  # after a restart no match has landed
    assert scene_nodes(server) == set()


def test_a_match_refused_before_the_search_shows_only_its_start(server):
    view = S2MDetailView(server.scene)
    view.draw(accepted_view(), visible=True)
    view.draw(refused_before_gicp(), visible=True)
    # nothing was searched, refined or carried: those nodes are gone, the start stays
    assert scene_nodes(server) == {ROOT, ROOT + "/start"}
    assert carried_pose(refused_before_gicp()) is None
    view.clear()
    assert scene_nodes(server) == set()


def test_hidden_view_sends_nothing_until_shown(server):
    view = S2MDetailView(server.scene)
    view.draw(accepted_view(), visible=False)
    assert scene_nodes(server) == set()  # nothing drawn while hidden
    view.set_visible(True)
    assert ROOT + "/winner" in scene_nodes(server)
    root = view.handle(ROOT)
    assert root.visible
    view.draw(accepted_view(started_at=20), visible=False)
    assert not root.visible  # one switch hides every part
    view.set_visible(True)
    assert root.visible
    view.clear()
    assert scene_nodes(server) == set()


def test_markdown_names_the_verdict_and_what_the_match_did():
    assert "no match has landed yet" in s2m_detail_markdown(None)
    text = s2m_detail_markdown(accepted_view())
    assert "**accepted**" in text and "5200 > the start's 4000" in text
    assert "started 10 → landed 12" in text
    assert "50 × 50 m" in text and "around the particle" in text
    assert "L1 1 · L2 3 · L3 40 · L4 12 (total 56)" in text
    assert "5200 · 4900 · 4100 · 3000" in text and "only 4 scored at the finest level" in text
    assert "moved 0.36 m, turned 1.0°" in text and "83 %" in text
    assert "107.0, 46.0 m, 41.0°" in text  # the carried-forward pose, in degrees
    refused = s2m_detail_markdown(refused_before_gicp())
    assert "**rejected**: too few road-removed scan points to match" in refused
    assert "whole map" in refused and "not run" in refused
    # every row of the table has its two cells, whatever the reason says
    odd = S2MView(**{**accepted_view().__dict__, "accepted": False, "reason": "a | b"})
    rows = [r for r in s2m_detail_markdown(odd).splitlines() if r.startswith("| ")]
    assert all(r.count("|") == 3 for r in rows)
    assert "(not written)" in s2m_detail_markdown(odd)

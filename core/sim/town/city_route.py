"""Drives through a city: routes that cross districts.

A route starts mid-block on a street of at least 40 m (not the highway), then heads for one
district after another: each leg's goal is a junction 300 m to 1.5 km away (less in a small
city) in a district of a style the drive has not passed lately, reached by the quickest way
(time at each street's speed limit plus 8 s per turn, never turning back), so that drives use
the arterials and the highway ring as a driver would. Legs follow each other until the route
is long enough for the drive.
"""

from __future__ import annotations

import heapq

import numpy as np

from .city_layout import RING, CityGrid
from .districts import DistrictMap
from .drive import choose_next_node

TURN_PENALTY = 8.0  # s: what a turn costs a driver choosing the way


def _quickest(grid: CityGrid, prev, here, goal) -> list | None:
    """The nodes after ``here`` on the quickest way to ``goal``, arriving at ``here`` from
    ``prev`` (so never turning back), or None if there is none."""
    start = (prev, here)
    best = {start: 0.0}
    parent = {start: None}
    heap = [(0.0, 0, start)]
    count = 1
    while heap:
        d, _, state = heapq.heappop(heap)
        if d > best[state]:
            continue
        p, n = state
        if n == goal:
            nodes = []
            while state is not None and state != start:
                nodes.append(state[1])
                state = parent[state]
            return nodes[::-1]
        heading = grid.node_xy(n) - grid.node_xy(p)
        for m in grid.neighbours(n):
            if m == p:
                continue
            step = grid.node_xy(m) - grid.node_xy(n)
            length = float(np.linalg.norm(step))
            turn = 0.0 if float(step @ heading) > 0.99 * length * float(np.linalg.norm(heading)) else TURN_PENALTY
            nd = d + length / grid.edge_street(n, m)[1] + turn
            s2 = (n, m)
            if nd < best.get(s2, np.inf):
                best[s2] = nd
                parent[s2] = state
                heapq.heappush(heap, (nd, count, s2))
                count += 1
    return None


def city_route(grid: CityGrid, districts: DistrictMap, extent: float):
    """A ``plan_route(rng, grid, length_needed)`` for :func:`~.drive.grid_drive` (see the module)."""
    present = grid.present()
    style_of = {n: int(districts.style_at(*grid.node_xy(n))) for n in present}
    far = min(1500.0, 0.6 * extent)
    near = min(300.0, 0.25 * extent)

    def plan(rng, grid_, length_needed):
        starts = [
            (n, m)
            for n in present
            for m in grid.neighbours(n)
            if np.linalg.norm(grid.node_xy(m) - grid.node_xy(n)) >= 40.0 and grid.edge_kind(n, m) != RING
        ]
        before_start, here = starts[int(rng.integers(len(starts)))]
        start_xy = 0.5 * (grid.node_xy(before_start) + grid.node_xy(here))
        nodes = [here]
        length = 0.5 * float(np.linalg.norm(grid.node_xy(here) - grid.node_xy(before_start)))
        recent = [style_of[before_start]]
        while length < length_needed:
            prev = nodes[-2] if len(nodes) >= 2 else before_start
            here = nodes[-1]
            d = np.array([np.linalg.norm(grid.node_xy(n) - grid.node_xy(here)) for n in present])
            fresh = [n for n, dn in zip(present, d) if near <= dn <= far and style_of[n] not in recent[-2:]]
            pool = fresh or [n for n, dn in zip(present, d) if near <= dn <= far] or present
            goal = pool[int(rng.integers(len(pool)))]
            leg = _quickest(grid, prev, here, goal) if goal != here else None
            if not leg:  # no way there without turning back: one step on, then try again
                options = [m for m in grid.neighbours(here) if m != prev] or [prev]
                leg = [choose_next_node(rng, grid, prev, here, options)]
            for node in leg:
                length += float(np.linalg.norm(grid.node_xy(node) - grid.node_xy(nodes[-1])))
                nodes.append(node)
            recent.append(style_of[goal])
        return start_xy, before_start, nodes

    return plan

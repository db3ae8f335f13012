"""The second drive through a town (``town.route = 2``): another way through the streets the
mapping drive (route 1) drove, so that the prior map covers it.

- Grid town: another random walk through the grid on the streets route 1 drove. It starts
  mid-block on the mapped street farthest from route 1's start, against the way route 1 drove
  it (in the other lane), then goes on at random — straight three times as often as
  turning, never U-turning — preferring the mapped streets that lie on a loop, so that it does
  not run into the dead end route 1's last stretch is; where no mapped street goes on it takes
  the shortest detour back onto them. Its speeds, stops and body sway are drawn anew.
- Town laid along a recorded drive: the same road driven the other way, in the opposite lane
  (2·LANE_OFFSET to the left of the recorded path), with the recorded timing reversed (the
  speed at each place is the recorded one; stops stay stops). A recorded drive is the only
  road known to exist everywhere along it, and driving it backwards makes every view new.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from .constants import LANE_OFFSET, ROUTE2_STREAM, SWAY2_STREAM
from .drive import choose_next_node, grid_drive
from .world import Town, drive_poses


def second_route(town: Town) -> tuple[np.ndarray, np.ndarray]:
    """(poses (n, 4, 4) in the town frame, times (n,) from 0) of the town's second drive."""
    rng = np.random.default_rng([town.seed, *ROUTE2_STREAM])
    sway_rng = np.random.default_rng([town.seed, *SWAY2_STREAM])
    if town.grid is None:
        return _reversed_drive(town, sway_rng)
    if town.is_city:  # the whole city is mapped: another route across its districts
        from .city_route import city_route

        drive = grid_drive(
            rng, town.grid, town.n_scans, town.rate_hz, plan_route=city_route(town.grid, town.districts, town.extent_m)
        )
        return drive_poses(drive, town.ground, sway_rng), drive.times
    drive = grid_drive(rng, town.grid, town.n_scans, town.rate_hz, plan_route=_walk_on_mapped_streets(town))
    return drive_poses(drive, town.ground, sway_rng), drive.times


def _hops_to(grid, targets: set) -> dict:
    """Fewest grid edges from every node to one of ``targets``."""
    hops = {n: 0 for n in targets}
    todo = list(targets)
    while todo:
        nxt = []
        for n in todo:
            for m in grid.neighbours(n):
                if m not in hops:
                    hops[m] = hops[n] + 1
                    nxt.append(m)
        todo = nxt
    return hops


def _core(mapped: set) -> set:
    """The mapped streets that lie on a loop: the mapped network with its dead-end branches
    (route 1's stretches that lead nowhere else mapped) pruned off, leaf by leaf."""
    core = set(mapped)
    while True:
        degree: dict = {}
        for edge in core:
            for n in edge:
                degree[n] = degree.get(n, 0) + 1
        leaves = {edge for edge in core if any(degree[n] == 1 for n in edge)}
        if not leaves:
            return core
        core -= leaves


def _walk_on_mapped_streets(town: Town):
    grid = town.grid
    mapped = {frozenset(edge) for edge in town.route_edges}
    core = _core(mapped)
    hops = _hops_to(grid, {n for edge in mapped for n in edge})
    route_1 = town.route_edges

    def plan(rng, grid_, length_needed):
        # Start mid-block on the mapped street (at least 40 m long, as route 1's start) farthest
        # from route 1's start, facing against the way route 1 last drove it.
        start_1 = 0.5 * (grid.node_xy(route_1[0][0]) + grid.node_xy(route_1[0][1]))
        long_enough = [e for e in route_1 if np.linalg.norm(grid.node_xy(e[0]) - grid.node_xy(e[1])) >= 40.0]
        candidates = long_enough or route_1
        far = [np.linalg.norm(0.5 * (grid.node_xy(a) + grid.node_xy(b)) - start_1) for a, b in candidates]
        before_start, here = candidates[int(np.argmax(far))][::-1]
        start_xy = 0.5 * (grid.node_xy(before_start) + grid.node_xy(here))
        nodes = [here]
        length = 0.5 * float(np.linalg.norm(grid.node_xy(here) - grid.node_xy(before_start)))
        while length < length_needed:
            here = nodes[-1]
            prev = nodes[-2] if len(nodes) >= 2 else before_start
            options = [m for m in grid.neighbours(here) if m != prev] or [prev]
            on_loop = [m for m in options if frozenset((here, m)) in core]
            on_map = [m for m in options if frozenset((here, m)) in mapped]
            if on_loop or on_map:
                options = on_loop or on_map
            else:  # a detour: the shortest way back onto the mapped streets
                nearest = min(hops[m] for m in options)
                options = [m for m in options if hops[m] == nearest]
            nxt = choose_next_node(rng, grid, prev, here, options)
            length += float(np.linalg.norm(grid.node_xy(nxt) - grid.node_xy(here)))
            nodes.append(nxt)
        return start_xy, before_start, nodes

    return plan


def _reversed_drive(town: Town, sway_rng) -> tuple[np.ndarray, np.ndarray]:
    P = town.poses_town
    yaw = np.arctan2(P[:, 1, 0], P[:, 0, 0])
    left = np.stack([-np.sin(yaw), np.cos(yaw)], axis=1)
    xy = (P[:, :2, 3] + 2.0 * LANE_OFFSET * left)[::-1]
    times = town.times[-1] - town.times[::-1]
    drive = SimpleNamespace(x=xy[:, 0].copy(), y=xy[:, 1].copy(), yaw=np.unwrap(yaw[::-1] + np.pi), times=times)
    return drive_poses(drive, town.ground, sway_rng), times

"""A whole-map scan-to-map match by candidates (``s2m.global_search``): the place index's look-up
(:mod:`.candidates`) names places, M3RSM verifies a window around each, GICP refines the distinct
answers, and two distinct places verified with close scores make an ambiguous answer (rejected,
both named) instead of a guess between look-alikes."""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

from ..geometry import levelled, pose_matrix
from ..maps.bev import BEVPyramid
from ..maps.places import uses_places
from . import m3rsm
from .candidates import combined, look_up, verify
from .candidates import distinct as distinct_answers
from .outcome import S2MOutcome

#: Whole-map answers farther apart than this are distinct places (the metrics' own "within 5 m",
#: ``localize.confirm_distance``): two of them verified with close scores make an ambiguous answer.
DISTINCT_M = 5.0
#: Yaw half-window of the exact search around a place from the look-up: its yaw comes from a
#: 5° sector shift (measured off by at most 5° on the town), plus the lattice's step.
CANDIDATE_YAW_WINDOW = math.radians(12.5)


class CandidateMatchMixin:
    """Whole-map matches by candidates. A part of
    :class:`~lidarloc.core.matching.s2m.ScanToMapMatcher`, which sets the attributes (``cfg``,
    ``map_cfg``, ``pyramid``, ``prior_map``, ``places``, ``_l0``) and gives the steps every match
    shares (``_near``, ``_height_under``, ``_refine``, ``_reject``) used here."""

    @property
    def by_candidates(self) -> bool:
        """Whether whole-map matches go through the place index (``s2m.global_search``: always,
        never, or "auto": on a map of :data:`~lidarloc.core.maps.places.AUTO_MIN_CELLS` cells or more)."""
        return uses_places(self.cfg, self.pyramid.shape)

    def _finest(self):
        """The map's finest BEV level whole, with its origin and d_m, for the look-up's re-ranking:
        a city held in tiles is read into one array once (one byte a cell: 16 MB for 16 km²)."""
        pyr = self.pyramid
        if self._l0 is None or self._l0[0] is not pyr:  # (a new pyramid: a new d_m)
            if isinstance(pyr, BEVPyramid):
                self._l0 = (pyr, (pyr.levels[0], pyr.origin, pyr.resolution))
            else:
                whole = pyr.window(0, 0, pyr.shape[0], pyr.shape[1])
                self._l0 = (pyr, (np.ascontiguousarray(whole.levels[0]), whole.origin, whole.resolution))
        return self._l0[1]

    def place_index(self):
        """The place index, built from the map on first use where the caller gave none."""
        if self.places is None:
            from ..maps.places import index_of_pyramid, index_of_tiles

            if isinstance(self.pyramid, BEVPyramid):
                self.places = index_of_pyramid(self.pyramid, self.prior_map.points)
            else:
                self.places = index_of_tiles(self.pyramid, self.prior_map.points)
        return self.places

    def _by_candidates(self, prep, B, z, pitch, roll, start_pose, start_score, t0, timings):
        """A whole-map match by the place index's candidates (module :mod:`.candidates`).

        Returns ``(outcome, None)`` when decided: a place verified by M3RSM and GICP, or
        "ambiguous" (two distinct places verified with close scores: rejected, both named);
        ``(None, result)`` when no place beat the start's score (``result`` says so, for the
        refinement of the start as after any unbeaten search); ``(None, None)`` when the exact
        whole-map search must decide (the look-up found nothing to compare, or no verified place
        passed GICP)."""
        cfg = self.cfg
        index = self.place_index()
        lu = look_up(
            index, levelled(prep.points, pitch, roll), cfg.global_candidates, 2.0 * cfg.candidate_window,
            self._finest(), B, cfg.angle_step,
        )  # fmt: skip
        timings["look_up"] = lu.ms
        if not lu.places:
            return None, None
        t1 = time.perf_counter()
        beat = start_score if math.isfinite(start_score) else None
        reach = float(self.map_cfg.scan_max_range)
        windows = verify(
            self.pyramid, B, lu.places, cfg.candidate_window, CANDIDATE_YAW_WINDOW, cfg.angle_step, reach, beat
        )
        timings["m3rsm"] = (time.perf_counter() - t1) * 1e3
        found = [r for r in windows if math.isfinite(r.x)]
        if not found:
            if beat is None:
                return None, None
            # nothing beat the start: the inspection shows the places' own scores beside it
            scored = [
                (p.x, p.y, p.yaw, m3rsm.score_pose(self._near(p.x, p.y, 0.0), B, p.x, p.y, p.yaw)) for p in lu.places
            ]
            return None, combined(windows, None, timings["m3rsm"], beat, scored)
        answers = distinct_answers(found, DISTINCT_M)
        home = start_pose

        def refined(r):
            zz = z if math.isfinite(z) else self._height_under(r.x, r.y, prep)
            init = pose_matrix(r.x, r.y, zz, r.yaw, pitch, roll)
            return self._refine(init, prep, r, start_score, init if home is None else home, t0, timings, True)

        tried: dict[int, S2MOutcome] = {}
        best = None
        for i, r in enumerate(answers):
            tried[i] = refined(r)
            if tried[i].accepted:
                best = i
                break
        if best is None:
            return None, None
        winner = tried[best]
        # the inspection sees the windows' searches as one: nodes, leaves scored, the rectangle
        whole = combined(windows, answers[best], timings["m3rsm"], -1.0 if beat is None else beat)
        winner = dataclasses.replace(winner, match=whole, region=whole.region)
        rivals = []
        for i, r in enumerate(answers):
            if i == best or r.score < cfg.ambiguity_ratio * winner.score:
                continue
            out = tried[i] if i in tried else refined(r)
            if out.accepted:
                rivals.append(r)
                tried[i] = out
        ms = (time.perf_counter() - t0) * 1e3
        if rivals and home is not None:
            # The start's own place among places that cannot be told apart: the filter's evidence
            # (a second opinion from its estimate, or a particle already there) decides for it,
            # as the exact search's unbeaten start would. The others stay named.
            sx, sy = float(home[0, 3]), float(home[1, 3])
            for i in [best] + [answers.index(r) for r in rivals]:
                r = answers[i]
                if math.hypot(r.x - sx, r.y - sy) <= DISTINCT_M:
                    whole = combined(windows, r, timings["m3rsm"], -1.0 if beat is None else beat)
                    best, winner, rivals = i, dataclasses.replace(tried[i], match=whole, region=whole.region), []
                    break
        others = tuple((r.x, r.y, r.yaw, r.score) for i, r in enumerate(answers) if i != best)
        if rivals:
            w = answers[best]
            n = len(rivals) + 1
            low = min(r.score for r in rivals) / w.score
            reason = (
                f"ambiguous: {n} places verify with scores within {100 * (1 - low):.0f}% of each other "
                f"(best {w.score:.0f} at {w.x:.1f}, {w.y:.1f}; next {rivals[0].score:.0f} at "
                f"{rivals[0].x:.1f}, {rivals[0].y:.1f})"
            )
            rejected = self._reject(
                winner.pose if home is None else home, w.score, start_score, whole, prep, t0, timings, reason,
                init=winner.match_pose, gicp=winner.gicp, stage="m3rsm",
            )  # fmt: skip
            return dataclasses.replace(rejected, search="candidates", ambiguous=True, alternatives=others, ms=ms), None
        return dataclasses.replace(winner, search="candidates", alternatives=others, ms=ms), None

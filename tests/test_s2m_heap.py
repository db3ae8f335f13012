"""The scan-to-map process gives back what its matches freed (core/heap.py): its request handler
asks the heap trimmer after every match, a failed one included."""

from __future__ import annotations

import pytest
from helpers import StreetSequence
from lidarloc.core import heap
from lidarloc.core.config import Config
from lidarloc.core.maps.mapping import load_or_build_map
from lidarloc.core.matching import worker
from lidarloc.core.matching.s2m import ScanToMapMatcher


class CountingTrimmer:
    made: list[CountingTrimmer] = []

    def __init__(self):
        self.requests = 0
        CountingTrimmer.made.append(self)

    def request(self, *_args):
        self.requests += 1


def test_every_match_in_the_s2m_process_asks_for_a_trim(cache_root, monkeypatch):
    street = StreetSequence(n=12)
    cfg = Config()
    map_dir = load_or_build_map(street, cfg.map, cache_root).directory
    monkeypatch.setattr(heap, "HeapTrimmer", CountingTrimmer)
    CountingTrimmer.made.clear()
    handle = worker._make_handler((str(map_dir), cfg.map, cfg.s2m, 0, None))  # what the child runs
    [trimmer] = CountingTrimmer.made
    scan, pose = street.scan(3)[:, :3], street.pose(3)
    handle(("match", scan, pose, cfg.s2m, False))
    assert trimmer.requests == 1

    def broken(*_args, **_kwargs):
        raise RuntimeError("a match that fails half-way")

    monkeypatch.setattr(ScanToMapMatcher, "match_local", broken)
    with pytest.raises(RuntimeError, match="half-way"):
        handle(("match", scan, pose, cfg.s2m, False))
    assert trimmer.requests == 2  # what it allocated before failing is given back too

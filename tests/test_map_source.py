"""The prior map comes from the sequence's map source (core/localizer.py): the first N scans of a
drive (``--scans N``) are localized inside the map of the whole drive, and each drive that
shares a map keeps its own recorded odometry."""

import numpy as np
from helpers import StreetSequence
from lidarloc.core.config import Config
from lidarloc.core.localizer import Localizer
from lidarloc.core.maps.mapping import load_or_build_map
from lidarloc.core.sequences.base import Limited


def small_cfg(**localize) -> Config:
    cfg = Config()
    cfg.pf.n_particles = 100
    cfg.s2m.enabled = False
    for key, value in localize.items():
        setattr(cfg.localize, key, value)
    return cfg


def test_limited_sequence_localizes_inside_the_full_map(cache_root):
    street = StreetSequence(n=24)
    full = load_or_build_map(street, Config().map, cache_root).value
    short = load_or_build_map(Limited(street, 6), Config().map, cache_root).value
    assert len(short.points) < len(full.points), "the first 6 scans alone make a smaller map"
    with Localizer(Limited(street, 6), small_cfg(), cache_root) as loc:
        assert loc.n_scans == 6
        assert len(loc.prior_map.points) == len(full.points)
        for got, want in zip(loc.prior_map.bounds, full.bounds):
            np.testing.assert_array_equal(got, want)
        # the particles spread over the whole drive's map, not over the first scans' part of it
        np.testing.assert_array_equal(loc.pf.bounds_max, np.asarray(full.bounds[1], float))
        loc.run()
        assert len(loc.records) == 6


def test_drives_sharing_a_map_keep_their_own_recorded_odometry(cache_root):
    street = StreetSequence(n=24)
    dirs, odometry = [], []
    for n in (5, 8):
        with Localizer(Limited(street, n), small_cfg(recorded_odometry=True), cache_root) as loc:
            dirs.append((loc.map_dir, loc.odometry_cache_dir))
            odometry.append(np.load(next(loc.odometry_cache_dir.glob("*/poses.npy"))))
    (map_a, odo_a), (map_b, odo_b) = dirs
    assert map_a == map_b and odo_a != odo_b
    assert [len(o) for o in odometry] == [5, 8]
    # KISS-ICP is causal: the shorter drive's odometry is the longer one's first scans
    np.testing.assert_allclose(odometry[1][:5], odometry[0], atol=1e-9)

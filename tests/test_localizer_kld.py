"""The localizer with the filter's options beyond the paper (core/localizer.py): KLD-sampling
changes the particle count under a match in flight without cancelling it, the match lands on
the particle it started from wherever resampling moved it, and dynamic-point rejection runs
inside the localizer's steps."""

import numpy as np
import pytest
from helpers import instant_matcher, short_town
from lidarloc.core.config import Config
from lidarloc.core.localizer import Localizer


@pytest.fixture(scope="module")
def town():
    return short_town(20)


def test_kld_moves_the_protected_particle_and_the_match_follows(town, cache_root):
    cfg = Config()
    cfg.pf.kld = True
    cfg.pf.n_particles = 1000
    cfg.pf.kld_min = 400  # a converged cloud shrinks (the default keeps all 1000)
    cfg.localize.s2m_process = False
    cfg.s2m.n_s2m = 3
    with Localizer(town, cfg, cache_root) as loc:
        instant_matcher(loc, accepted=True)
        real_start, real_resample, real_set = loc.s2m.start, loc.pf.resample_if_needed, loc.pf.set_particle
        # the match starts from the last particle: the slot a shrinking count takes away first
        loc.s2m.start = lambda k, j, state, scan, localized, *rest: real_start(
            k, loc.pf.n - 1, loc.pf.states[-1], scan, localized, *rest
        )
        protected = {}

        def resample_if_needed(protect=None):
            before = None if protect is None else loc.pf.states[protect].copy()
            resampled = real_resample(protect=protect)
            if protect is not None:
                protected[loc.k] = (before, loc.pf.protected_index, loc.pf.n)
            return resampled

        written = []
        loc.pf.resample_if_needed = resample_if_needed
        loc.pf.set_particle = lambda j, state: (written.append((loc.k, j, loc.s2m.job)), real_set(j, state))[1]
        loc.reset(pose=town.poses[0])
        loc.step()
        job = loc.s2m.job
        assert job is not None and job.started_at == 0
        before, index, n = protected[0]
        assert n < 1000, "a converged cloud is resampled to fewer particles"
        assert index == n - 1 and job.particle == index  # moved into the last slot, and followed
        np.testing.assert_array_equal(loc.pf.states[index], before)  # the same particle
        loc.run(cfg.s2m.n_s2m)
        landed = [e for e in loc.events if e.kind in ("s2m_accepted", "s2m_rejected", "s2m_cancelled")]
        assert [(e.scan, e.kind) for e in landed][:1] == [(cfg.s2m.n_s2m, "s2m_accepted")]
        # written into the slot the particle was in when the match landed: the last protected one
        k, j, _ = written[0]
        assert k == cfg.s2m.n_s2m and j == protected[k - 1][1]


def test_dynamic_rejection_runs_in_the_localizer(town, cache_root):
    """With the option on, the filter's dynamic-point filter sees every scan of the run (the
    localizer hands the PF the scan the way its API asks), and the run goes on."""
    cfg = Config()
    cfg.pf.dynamic_rejection = True
    cfg.pf.n_particles = 300
    cfg.s2m.enabled = False
    with Localizer(town, cfg, cache_root) as loc:
        seen = []
        real = loc.pf.dynamic.keep_mask
        loc.pf.dynamic.keep_mask = lambda pts, pose: (seen.append(len(pts)), real(pts, pose))[1]
        loc.reset(pose=town.poses[0])
        loc.run(6)
        assert len(loc.records) == 6
        assert len(seen) >= 5  # every scan whose prior cloud was tight enough to judge by

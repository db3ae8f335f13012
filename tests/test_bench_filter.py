"""``lidarloc bench filter``: the tracking study that tells a likelihood whose uncertainty means
something from one whose weights collapse."""

import pytest
from lidarloc.core.config import Config
from lidarloc.core.sequences.factory import SourceSpec, open_sequence


@pytest.mark.slow
def test_the_per_point_mean_keeps_the_weights_off_the_floor_and_the_truth_inside_the_ellipse(cache_root):
    from helpers import MAPPING_SCANS
    from lidarloc.app.bench.filter import BURN_IN, run

    cfg = Config()
    cfg.pf.n_particles = 300
    cfg.town.n_scans = MAPPING_SCANS
    result = run(
        SourceSpec(scans=BURN_IN + 15),
        lambda s: open_sequence(s, cfg),
        cfg,
        seeds=1,
        options=["paper", "per-point mean", "T=1000", "default"],
        cache_root=cache_root,
    )
    paper, mean = result["options"]["paper"], result["options"]["per-point mean"]
    assert result["particles"] == 300 and result["scans"] == BURN_IN + 15
    # the paper's sum over ~10⁴ points leaves one particle with all the weight …
    assert paper["n_eff_share"] < 0.01
    # … the per-point mean keeps many, and its 2σ ellipse holds the truth more often
    assert mean["n_eff_share"] > 0.05
    assert mean["consistency_2sigma"] > paper["consistency_2sigma"]
    assert result["options"]["T=1000"]["set"] == ["pf.temperature=1000"]  # any temperature, for a sweep
    # the default likelihood keeps the truth inside its ellipse as well
    assert result["options"]["default"]["consistency_2sigma"] > paper["consistency_2sigma"]
    assert cfg.pf.temperature == Config().pf.temperature  # the study left the caller's configuration alone


def test_an_unknown_option_is_one_line():
    from lidarloc.app.bench.filter import run
    from lidarloc.core.errors import LidarlocError

    with pytest.raises(LidarlocError, match="unknown filter option 'T=0.5'"):
        run(SourceSpec(), lambda s: None, Config(), options=["T=0.5"])

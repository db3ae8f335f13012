"""``lidarloc bench viewer``'s figures taken in a real (headless) Chromium: the first likelihood
surface, Kidnap's display resume and the Top-down view's answer (app/bench/viewer.py), one press
of each on the short town. The figures themselves are the benchmark's to measure; this checks
that each is taken, timed on the page's clock, and named with its target."""

from __future__ import annotations

import pytest

pytestmark = [pytest.mark.browser, pytest.mark.slow]


def test_each_browser_figure_is_measured_once_per_press(town_cache):
    from browser import CHROMIUM

    if not CHROMIUM.exists():
        pytest.skip(f"{CHROMIUM} not found (apt-get install -y chromium)")
    from lidarloc.app.bench.viewer import browser_figures

    fig = browser_figures(cache_root=town_cache, n_particles=300, repeats=1)
    assert fig["browser"].startswith("headless Chromium"), fig
    # one press each: the median is that press, and every figure is a time after its press
    assert fig["first_surface_ms_each"] == [fig["first_surface_ms"]], fig
    assert 0 < fig["first_surface_ms"] <= fig["full_surface_ms"], fig
    assert 0 < fig["kidnap_display_resume_s"] < 120, fig
    assert 0 < fig["top_down_ms"] < 120_000, fig
    targets = (fig["first_surface_ms_target"], fig["kidnap_display_resume_s_target"], fig["top_down_ms_target"])
    assert targets == (1000.0, 2.0, 500.0), fig

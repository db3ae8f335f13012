"""``lidarloc bench startup``'s watch of the first start: when S2M first confirmed the estimate,
and whether any step until then was a false fire (a localized step more than 5 m from the truth,
or a recorded ``false_fire`` event), read from the demo's growing recording."""

from __future__ import annotations

import time

import numpy as np
import pytest
from lidarloc.app.bench import startup
from lidarloc.core.snapshot import Event


class FakeRecording:
    """The fields the watch reads, growing by ``grow`` steps per open."""

    def __init__(self, localized, error, confirmed_at=None, events=()):
        self.all = {"localized": np.asarray(localized, np.uint8), "error_m": np.asarray(error, float)}
        if confirmed_at is not None:
            self.all["confirmed_at"] = np.asarray(confirmed_at, np.int64)
        self.events = list(events)
        self.n = 0

    @property
    def field_names(self):
        return list(self.all)

    def field(self, name, n=None):
        return self.all[name][: self.n if n is None else n]


class Running:
    def poll(self):
        return None


@pytest.fixture
def opened(monkeypatch):
    """recording.open(...) hands out the fake, two more steps each time (a demo that plays on)."""
    from lidarloc.core.runs import recording

    holder = {}

    def fake_open(path):
        rec = holder["rec"]
        rec.n = min(rec.n + 2, len(rec.all["localized"]))
        return rec

    monkeypatch.setattr(recording, "open", fake_open)
    monkeypatch.setattr(startup, "POLL_S", 0.001)
    return holder


def watch(holder, rec, timeout=5.0):
    holder["rec"] = rec
    return startup.first_steps("run", time.perf_counter(), timeout, Running())


def test_confirmation_time_and_no_false_fire(opened):
    out = watch(opened, FakeRecording([0, 0, 0, 0, 1, 1, 1, 1], [30, 20, 9, 3, 0.5, 0.4, 0.3, 0.2]))
    assert out["s2m_confirmed_s"] is not None and out["false_fire"] is False and out["steps_watched"] == 5
    # a confirmation by S2M counts before the rule's localized
    out = watch(opened, FakeRecording([0, 0, 0, 0], [3, 2, 1, 1], confirmed_at=[-1, -1, 2, 2]))
    assert out["s2m_confirmed_s"] is not None and out["steps_watched"] == 3


def test_a_localized_step_far_from_the_truth_is_a_false_fire(opened):
    out = watch(opened, FakeRecording([0, 1, 1, 1], [40, 60, 50, 40]))
    assert out["false_fire"] is True
    out = watch(opened, FakeRecording([0, 0, 0, 1], [2, 2, 2, 1], events=[(1, Event(1, "false_fire"))]))
    assert out["false_fire"] is True


def test_never_confirmed_gives_no_time(opened):
    out = watch(opened, FakeRecording([0] * 6, [50] * 6), timeout=0.2)
    assert out["s2m_confirmed_s"] is None and out["false_fire"] is False


def test_a_demo_that_never_gets_ready_and_never_prints_is_stopped(tmp_path, monkeypatch):
    import sys

    from lidarloc.app.bench import startup
    from lidarloc.core.errors import LidarlocError

    silent = tmp_path / "silent"
    silent.write_text("#!/bin/sh\nexec sleep 120\n")
    silent.chmod(0o755)
    monkeypatch.setattr(sys, "executable", str(silent))
    with pytest.raises(LidarlocError, match="did not become ready"):
        startup._one_start(["demo"], str(tmp_path / "cache"), timeout_s=1.0)

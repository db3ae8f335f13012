"""The viewer trusts no client: every GUI value a tab sends (a modified page can send anything)
is checked on the server — type, range, NaN and infinities — and refused with a message; nothing a
client sends is evaluated or used as a path; the HTTP server serves its own assets and nothing
else."""

from __future__ import annotations

import http.client
import math

import pytest
from helpers import wait_for

# What survives viser's own cast of a client's value to the field's type (float("nan") does,
# int("…") does not: viser drops those before any callback runs), and a huge whole number.
BAD = [float("nan"), float("inf"), -float("inf"), 10**30, -(10**30)]


def send(field, value) -> bool:
    """Set a field as a client's message would; False if viser's cast already refused it."""
    try:
        field.value = value
    except (ValueError, TypeError, OverflowError, AssertionError):
        return False
    return True


@pytest.mark.parametrize("bad", BAD, ids=["nan", "inf", "-inf", "huge", "-huge"])
def test_every_number_the_page_sends_is_checked_on_the_server(viewer, bad):
    v, loc = viewer.viewer, viewer.localizer
    before = loc.cfg.to_dict()
    fields = [(key, field, v.params.applied[key]) for key, field in v.controls.params.items()]
    fields += [(f"q[{i}]", field, field.value) for i, field in enumerate(v.controls.q)]
    refused = 0
    for key, field, good in fields:
        if send(field, bad):
            v.controls.apply.value = True
            # a huge value may be a valid one for a parameter without an upper limit
            if not (abs(bad) == 10**30 and bad > 0 and not v.message.startswith("refused:")):
                assert v.message.startswith("refused:"), (key, v.message)
                refused += 1
            field.value = good
            v.controls.apply.value = True
    assert refused > 0
    if not (abs(bad) == 10**30 and bad > 0):
        assert loc.cfg.to_dict() == before  # nothing reached the localizer
    # the seed (a restart)
    if send(v.controls.seed, bad):
        v.controls.restart.value = True
        assert v.message.startswith("refused:"), v.message
    v.controls.seed.value = 0
    # and the viewer still works
    k = loc.k
    v.controls.step.value = True
    wait_for(lambda: v.player.idle and loc.k == k + 1, what="a step after the refusals")


@pytest.mark.parametrize("control", ["speed", "clock"])
def test_a_choice_outside_the_menu_is_refused(viewer, control):
    v = viewer.viewer
    handle = getattr(v.controls, control)
    before = (v.player.clock, v.controls.speed.value)
    if send(handle, "../../etc/passwd; rm -rf /"):
        assert v.message.startswith("refused:"), v.message
    assert v.player.clock in ("replay", "realtime") and v.player.clock == before[0]


@pytest.mark.parametrize(
    "path",
    [
        "/../../../../etc/passwd",
        "/%2e%2e/%2e%2e/%2e%2e/etc/passwd",
        "/..%2f..%2f..%2fetc%2fpasswd",
        "/assets/..\\..\\..\\etc\\passwd",
        "//etc/passwd",
        "/index.html/../../../pyproject.toml",
    ],
)
def test_the_server_serves_nothing_beyond_its_own_assets(viewer, path):
    conn = http.client.HTTPConnection("127.0.0.1", viewer.port, timeout=10)
    conn.request("GET", path)
    resp = conn.getresponse()
    body = resp.read()
    assert resp.status == 404 and b"root:" not in body and b"[project]" not in body
    conn.close()


def test_the_viewer_binds_loopback_by_default(viewer):
    conn = viewer.server  # serve()'s default host
    assert viewer.url.startswith("http://127.0.0.1:") and math.isfinite(conn.get_port())

"""The "why" views in a real (headless) Chromium: the scan residuals, a likelihood surface, a
particle inspected by a click in the scene, and the last S2M match in detail — each shown in the
page, checked by its numbers in the panel and its colours on the canvas, and saved as
test-artifacts/why-<view>.png.

WebGL is software-rendered here (no GPU), so waits are generous; every wait polls for a
condition, none sleeps for a fixed time."""

from __future__ import annotations

import io
import re

import numpy as np
import pytest
from browser import ARTIFACTS, JS_SCAN, LOAD_TIMEOUT, STEP_TIMEOUT
from helpers import browser_localizer, wait_for

PANEL_LEFT = 0.72  # share of the canvas's width left of the panel (1400 px viewport)
LINE_TOL = 40  # lines are drawn with some shading: their pixels stray further from the colour
SCANS_BEFORE = 4  # scans stepped before the page opens: an S2M match has landed by then

pytestmark = [pytest.mark.browser, pytest.mark.slow]


@pytest.fixture(scope="module")
def served(cache_root):
    from lidarloc.app.viewer.serve import serve

    loc = browser_localizer(cache_root)
    handle = serve(loc, port=0, autoplay=False)
    viewer = handle.viewer
    for k in range(SCANS_BEFORE):
        viewer.step_once()
        wait_for(lambda: viewer.drawn is not None and viewer.drawn.scan_index == k, 60, f"scan {k} drawn")
    assert viewer.drawn.s2m is not None, "no S2M match landed in the first scans"
    yield handle
    handle.stop()
    loc.close()


def pixels(png: bytes) -> np.ndarray:
    """The canvas left of the panel (which floats over its right side) as int RGB."""
    from PIL import Image

    img = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(np.int32)
    return img[:, : int(img.shape[1] * PANEL_LEFT)]


def count_near(img: np.ndarray, rgb, tol: int = 14) -> int:
    """Pixels within ``tol`` of ``rgb`` in every channel."""
    return int((np.abs(img - np.asarray(rgb)).max(axis=-1) <= tol).sum())


def surface_yellows(img: np.ndarray) -> int:
    """Pixels in the bright end of the surface's colour map (yellow-green: no other node of the
    default scene has it — the scan is pure green, the map blue to white)."""
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    return int(((r > 150) & (g > 170) & (b < 110)).sum())


def look_down_at(handle, target, height: float) -> None:
    """Every tab's camera straight down onto ``target`` (+y up on the screen)."""
    target = np.asarray(target, float)
    for client in handle.server.get_clients().values():
        with client.atomic():
            client.camera.position = target + np.array([0.0, -1e-3 * height, height])
            client.camera.look_at = target


def canvas_png(page) -> bytes:
    return page.locator("canvas").first.screenshot(timeout=LOAD_TIMEOUT)


def test_why_views_in_chromium(browser, served, monkeypatch):
    import threading

    from lidarloc.app.viewer import why as why_module
    from lidarloc.app.viewer.s2m_detail import CANDIDATE_COLOR, WINNER_COLOR
    from lidarloc.app.viewer.why_style import RESIDUAL_GOOD, SELECTED_COLOR
    from lidarloc.core.filter.surface import CELL

    ARTIFACTS.mkdir(exist_ok=True)
    viewer, why = served.viewer, served.viewer.why
    page = browser.new_page(viewport={"width": 1400, "height": 900})
    page.goto(served.url, timeout=LOAD_TIMEOUT)
    page.wait_for_selector("canvas", timeout=LOAD_TIMEOUT)
    page.wait_for_function(f"{JS_SCAN} === {SCANS_BEFORE - 1}", timeout=LOAD_TIMEOUT)
    wait_for(lambda: len(served.server.get_clients()) == 1, 30, "the tab's connection")
    snap = viewer.drawn
    est = np.asarray(snap.mean_pose)[:3, 3]
    look_down_at(served, est, 70.0)
    page.get_by_text("Why", exact=True).click()

    # --- scan residuals: the panel gives the share beyond d_max, the canvas shows the ramp's green
    before = count_near(pixels(canvas_png(page)), RESIDUAL_GOOD)
    page.get_by_text("Show residuals", exact=True).click()
    page.wait_for_function(
        "/at the estimate: \\*?\\*?[\\d.]+%/.test(document.body.innerText) || "
        "/at the estimate: [\\d.]+% of [\\d,]+ points beyond d_max/.test(document.body.innerText)",
        polling=250,
        timeout=STEP_TIMEOUT,
    )
    wait_for(
        lambda: count_near(pixels(canvas_png(page)), RESIDUAL_GOOD) > before + 300,
        STEP_TIMEOUT / 1000,
        "the residual colours on the canvas",
    )
    text = page.evaluate("document.body.innerText")
    share = float(re.search(r"at the estimate: ([\d.]+)% of ([\d,]+) points beyond d_max", text).group(1))
    assert share == pytest.approx(100 * why.residuals.last.share_beyond, abs=0.051)
    page.get_by_text(re.compile(r"at the estimate: [\d.]+%")).scroll_into_view_if_needed()
    page.screenshot(path=str(ARTIFACTS / "why-residuals.png"))

    # --- likelihood surface: the read-out with its numbers, the colour map's bright end on the ground
    # (seen from 15 m above the estimate: the default likelihood's peak is a few 0.5 m cells wide)
    estimate = np.asarray(snap.mean_pose, float)[:3, 3]
    look_down_at(served, estimate, 15.0)
    wait_for(
        lambda: np.allclose(next(iter(served.server.get_clients().values())).camera.look_at, estimate, atol=0.05),
        STEP_TIMEOUT / 1000,
        "the camera over the estimate",
    )
    before = surface_yellows(pixels(canvas_png(page)))
    # a first look comes at once in coarse cells; the full surface follows (held here until the
    # page has shown the coarse one: while the scans play, the full one takes seconds)
    full_pass, compute = threading.Event(), why_module.compute_surface

    def full_held(snap, model, over_yaw, cell=CELL):
        if cell == CELL:
            full_pass.wait(STEP_TIMEOUT / 1000)
        return compute(snap, model, over_yaw, cell)

    monkeypatch.setattr(why_module, "compute_surface", full_held)
    page.get_by_role("button", name="Likelihood surface here").click()
    page.wait_for_function(
        f"document.body.innerText.includes('scan {snap.scan_index}: maximum at (')", polling=250, timeout=STEP_TIMEOUT
    )
    text = page.evaluate("document.body.innerText")
    assert re.search(r"41×41 cells of 1 m, one yaw: \d+ ms", text) and "0.5 m cells follows" in text, text
    full_pass.set()
    page.wait_for_function(
        "document.body.innerText.includes('81×81 cells of 0.5 m')", polling=250, timeout=STEP_TIMEOUT
    )
    text = page.evaluate("document.body.innerText")
    assert re.search(r"81×81 cells of 0\.5 m, one yaw: \d+ ms", text), text
    best = re.search(r"maximum at \((-?[\d.]+), (-?[\d.]+)\)", text).groups()
    np.testing.assert_allclose([float(v) for v in best], why.surface.last.argmax_xy, atol=0.051)
    wait_for(
        lambda: surface_yellows(pixels(canvas_png(page))) > before + 500,
        STEP_TIMEOUT / 1000,
        "the surface's colours on the canvas",
    )
    page.get_by_text(re.compile(r"one yaw: \d+ ms")).scroll_into_view_if_needed()
    page.screenshot(path=str(ARTIFACTS / "why-surface.png"))

    # --- a particle: a click on it in the scene (camera straight down onto it, click the centre)
    j = int(snap.best_index)
    target = np.asarray(snap.particles[j][:3], float)
    look_down_at(served, target, 45.0)
    canvas = page.locator("canvas").first
    wait_for(
        lambda: np.allclose(next(iter(served.server.get_clients().values())).camera.look_at, target, atol=0.05),
        30,
        "the camera over the particle",
    )
    box = canvas.bounding_box()
    before = count_near(pixels(canvas_png(page)), SELECTED_COLOR, LINE_TOL)
    page.mouse.click(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
    page.wait_for_function(
        "/particle \\d+ of \\d+ at scan \\d+: rank \\d+ by log-likelihood/.test(document.body.innerText)",
        polling=250,
        timeout=STEP_TIMEOUT,
    )
    text = page.evaluate("document.body.innerText")
    picked = int(re.search(r"particle (\d+) of \d+ at scan", text).group(1))
    assert np.linalg.norm(snap.particles[picked][:2] - target[:2]) < 2.0
    assert re.search(r"yaw\s+-?[\d.]+ deg", text) and re.search(r"v\s+-?[\d.]+ m/s", text)
    assert "at the inspected particle:" in text  # the residual view switched to it
    wait_for(
        lambda: count_near(pixels(canvas_png(page)), SELECTED_COLOR, LINE_TOL) > before + 100,
        STEP_TIMEOUT / 1000,
        "the inspected particle's marker",
    )
    page.get_by_text(re.compile(r"rank \d+ by log-likelihood")).scroll_into_view_if_needed()
    page.screenshot(path=str(ARTIFACTS / "why-particle.png"))

    # --- the last S2M match in detail: its table in the panel, its candidates in the scene
    s2m = viewer.drawn.s2m
    look_down_at(served, np.asarray(s2m.pose)[:3, 3], 70.0)
    page.get_by_text("S2M details", exact=True).click()
    page.wait_for_function(
        f"/started {s2m.started_at} → landed {s2m.landed_at}, \\d+ ms/.test(document.body.innerText)",
        polling=250,
        timeout=STEP_TIMEOUT,
    )
    text = page.evaluate("document.body.innerText")
    assert re.search(r"total \d+", text) and ("accepted" in text or "rejected" in text)
    if len(s2m.candidates):
        wait_for(
            lambda: (
                count_near(pixels(canvas_png(page)), CANDIDATE_COLOR, LINE_TOL)
                + count_near(pixels(canvas_png(page)), WINNER_COLOR, LINE_TOL)
                > 30
            ),
            STEP_TIMEOUT / 1000,
            "the S2M candidates' arrows",
        )
    page.screenshot(path=str(ARTIFACTS / "why-s2m.png"))
    page.close()

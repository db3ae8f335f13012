"""The page's controls and read-outs, built in order, folder by folder. Nothing here reacts to
them: :class:`~lidarloc.app.viewer.app.Viewer` wires each control to what it does."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import viser

from .legend import legend_markdown
from .params import CLOCK, NUMBER_FIELDS, Q_STD, S2M_ENABLED, q_labels
from .plots import Plots
from .scene import Layers
from .style import GT_NAME, SPEEDS

STATUS_WIDTH_PX = 400  # the status window's width (CSS pixels): its table's rows on one line each
STATUS_MARGIN_PX = 15  # its gap from the top left corner of the 3D view
NOTIFICATIONS_LEFT_PX = STATUS_WIDTH_PX + 2 * STATUS_MARGIN_PX  # notifications start right of it
NOTIFICATIONS_CSS = f"<style>.mantine-Notifications-root {{ left: {NOTIFICATIONS_LEFT_PX}px !important; }}</style>"

LAYER_LABELS = (
    ("map", "Map"),
    ("map_bev", "Map, road removed"),
    ("particles", "Particles"),
    ("scan", "Current scan (green)"),
    ("s2m", "Last S2M match"),
    ("trajectories", f"Trajectories ({GT_NAME}: truth, orange: estimate)"),
    ("vehicles", f"Vehicles ({GT_NAME}: truth, orange: estimate)"),
    ("ellipse", "2σ ellipse"),
    ("bev_level", "BEV pyramid level"),
    ("staleness", "Stale places (corpus staleness)"),
)
#: layers whose checkbox shows once the layer has content
LATE_LAYERS = ("bev_level", "staleness")


@dataclass
class Controls:
    """Handles of every control and read-out, for the viewer and for tests that drive them."""

    # read-outs, in a panel of their own (see build_panel)
    status_panel: object = None
    progress: object = None
    progress_text: object = None
    status: object = None
    realtime: object = None  # one click to the real-time clock
    message: object = None
    # Playback
    playback_folder: object = None
    play: object = None
    step: object = None
    speed: object = None
    clock: object = None
    seed: object = None
    restart: object = None
    # Overview
    overview: object = None  # the whole map from above (minimap.Overview draws it)
    # Particles
    particles_folder: object = None
    reset: object = None
    kidnap_skip: object = None
    kidnap: object = None
    # Parameters
    params: dict = field(default_factory=dict)  # set_params key → number handle
    q: list = field(default_factory=list)  # 11 number handles, paper units
    s2m_enabled: object = None
    apply: object = None
    # Layers
    layers: dict = field(default_factory=dict)
    bev_level: object = None
    # Legend
    legend: object = None
    # Plots
    plots: Plots | None = None


@dataclass
class CameraControls:
    """One tab's camera folder."""

    follow: object = None  # "follow the vehicle" checkbox
    top_down: object = None
    fit: object = None


def build_panel(gui, *, speed: str, layers: Layers) -> Controls:
    """Every control of the shared panel, disabled where it needs a localizer."""
    c = Controls()
    gui.configure_theme(dark_mode=True, control_width="medium", show_share_button=False)
    gui.set_panel_label("lidarloc")
    # The read-outs change height with every scan (events come and go, warnings appear): in the
    # control panel they pushed every control below them up and down, and a click aimed at a
    # button landed on another. They float in a window of their own at the top left, which the
    # user can move or minimise; the controls stay where they are.
    c.status_panel = gui.add_panel()
    with c.status_panel.add_tab("Status", viser.Icon.INFO_CIRCLE):
        c.progress = gui.add_progress_bar(0.0, animated=True, visible=True)
        c.progress_text = gui.add_markdown("Starting the localizer…")
        c.status = gui.add_markdown("")
        # shown while the replay clock holds playback for S2M (the status says why)
        c.realtime = gui.add_button(
            "Switch to the real-time clock (do not wait for S2M)",
            icon=viser.Icon.CLOCK_PLAY,
            visible=False,
            hint="Faster, but the run no longer repeats exactly: its results then depend on the machine's load",
        )
        c.message = gui.add_markdown("", visible=False)
    c.status_panel.float(x=STATUS_MARGIN_PX, y=STATUS_MARGIN_PX, width=STATUS_WIDTH_PX)
    # viser stacks its notifications at the top left of the 3D view, over the status window:
    # they go beside it instead (a rule the page applies; nothing to see in the panel)
    gui.add_html(NOTIFICATIONS_CSS)

    c.playback_folder = gui.add_folder("Playback")
    with c.playback_folder:
        c.play = gui.add_button("Pause", icon=viser.Icon.PLAYER_PAUSE, disabled=True)
        c.step = gui.add_button(
            "Step", icon=viser.Icon.PLAYER_TRACK_NEXT, disabled=True, hint="Pause and process exactly one scan"
        )
        c.speed = gui.add_dropdown(
            "Speed (scans/s)", SPEEDS, initial_value=speed, hint="Replay clock: at most this many scans per second"
        )
        c.clock = gui.add_dropdown(CLOCK.label, ("replay", "realtime"), initial_value="replay", hint=CLOCK.hint)
        c.seed = gui.add_number("Seed", 0, step=1)
        c.restart = gui.add_button("Restart from scan 0", icon=viser.Icon.REFRESH, disabled=True)
    with gui.add_folder("Overview"):
        # hidden until the map is drawn into it
        c.overview = gui.add_image(np.zeros((8, 8, 3), np.uint8), format="png", visible=False)
    c.particles_folder = gui.add_folder("Particles")
    with c.particles_folder:
        c.reset = gui.add_button("Reset globally", disabled=True, hint="Re-initialise the particles over the whole map")
        gui.add_markdown(
            "**Shift+click** the ground: reset around that point.  \n**Shift+drag** a rectangle: reset inside it."
        )
        c.kidnap_skip = gui.add_number("Kidnap skip (scans)", 100, step=1)
        c.kidnap = gui.add_button("Kidnap", disabled=True, hint="Jump the vehicle ahead without telling the filter")
    with gui.add_folder("Parameters", expand_by_default=False):
        for p in NUMBER_FIELDS:
            c.params[p.key] = gui.add_number(p.label, 1 if p.integer else 1.0, step=p.step, hint=p.hint or None)
        c.s2m_enabled = gui.add_checkbox(S2M_ENABLED.label, True, hint=S2M_ENABLED.hint)
        with gui.add_folder(Q_STD.label, expand_by_default=False):
            for label in q_labels():
                c.q.append(gui.add_number(label, 0.0, step=Q_STD.step))
        c.apply = gui.add_button("Apply", disabled=True, hint="Numbers take effect from the next scan")
    with gui.add_folder("Layers", expand_by_default=False):
        for name, label in LAYER_LABELS:
            c.layers[name] = gui.add_checkbox(label, getattr(layers, name), visible=name not in LATE_LAYERS)
        c.bev_level = gui.add_slider("BEV level", 0, 8, 1, 0, visible=False)
    with gui.add_folder("Legend"):
        c.legend = gui.add_markdown(legend_markdown())
    with gui.add_folder("Plots"):
        c.plots = Plots(gui)
    return c


def add_camera_folder(gui, order: float) -> CameraControls:
    """One tab's camera folder (``gui`` is the tab's own), placed at ``order`` in the panel."""
    c = CameraControls()
    with gui.add_folder("Camera (this tab)", order=order):
        c.follow = gui.add_checkbox(
            "Follow the vehicle",
            True,
            hint="Keep the camera on the vehicle: the estimate once the filter converged, the truth before it (where known)",
        )
        c.top_down = gui.add_button("Top-down view", icon=viser.Icon.ARROW_DOWN)
        c.fit = gui.add_button("Whole map")
    return c

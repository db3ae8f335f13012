"""The Foxglove layout that opens an exported run ready to read (``NAME.layout.json`` beside
``NAME.mcap``; Foxglove: Layouts → Import from file): the 3D scene following the estimate, the
plots the viewer has (position std and error, N_eff as a share of the particles, the PF, RPE and
S2M latencies) and the event log.

Built with the layout types of ``foxglove-sdk`` (``foxglove.layouts``) rather than kept as a
hand-written JSON file: the SDK's types are Foxglove's own layout format, so a field name that
Foxglove renames fails here, at build time, instead of giving a panel that silently shows nothing.
"""

from __future__ import annotations

from . import foxglove_channels as T
from .run_steps import LIDAR_FRAME

#: (title, [(message path, label, colour)]) of the plots, top to bottom
PLOTS = (
    (
        "position std and error (m)",
        [(f"{T.FIGURES}.std_m", "position std", "#4e98e2"), (f"{T.FIGURES}.error_m", "error to the truth", "#f5774d")],
    ),
    ("N_eff (share of the particles)", [(f"{T.FIGURES}.n_eff_share", "N_eff / N", "#61cbff")]),
    (
        "latency (ms)",
        [
            (f"{T.FIGURES}.pf_ms", "PF", "#b6e880"),
            (f"{T.FIGURES}.rpe_ms", "RPE (KISS-ICP)", "#ffa15a"),
            (f"{T.FIGURES}.s2m_ms", "S2M", "#ff6692"),
        ],
    ),
)


def layout():
    """The layout (a ``foxglove.layouts.Layout``)."""
    import foxglove.layouts as fl

    topics = {
        T.MAP: fl.BaseRendererPointCloudTopicSettings(
            visible=True, point_size=2, color_mode="colormap", color_field="z", color_map="turbo"
        ),
        T.SCAN: fl.BaseRendererPointCloudTopicSettings(
            visible=True, point_size=3, color_mode="flat", flat_color="#ffffff"
        ),
        T.PARTICLE_CLOUD: fl.BaseRendererPointCloudTopicSettings(
            visible=True, point_size=4, color_mode="colormap", color_field="weight", color_map="turbo"
        ),
        T.PARTICLES: fl.BaseRendererPosesTopicSettings(visible=False, type="arrow"),
        T.POSE: fl.BaseRendererPoseTopicSettings(visible=True, type="arrow", color="#ff9f1a"),
        T.TRUTH: fl.BaseRendererPoseTopicSettings(visible=True, type="arrow", color="#ffffff"),
        T.SCENE: fl.BaseRendererSceneUpdateTopicSettings(visible=True),
    }
    scene = fl.ThreeDeePanel(
        title="lidarloc",
        config=fl.ThreeDeeConfig(topics=topics, follow_tf=LIDAR_FRAME, follow_mode="follow-position"),
    )
    plots = [
        fl.SplitItem(
            content=fl.PlotPanel(
                title=title,
                config=fl.PlotConfig(
                    paths=[
                        fl.PlotSeries(
                            value=path, label=label, color=colour, enabled=True, timestamp_method="receiveTime"
                        )
                        for path, label, colour in series
                    ],
                    show_legend=True,
                ),
            )
        )
        for title, series in PLOTS
    ]
    log = fl.SplitItem(content=fl.LogPanel(title="events", config=fl.LogConfig(topic_to_render=T.LOG)))
    side = fl.SplitContainer(direction="column", items=plots + [log])
    return fl.Layout(
        content=fl.SplitContainer(
            direction="row", items=[fl.SplitItem(proportion=2, content=scene), fl.SplitItem(proportion=1, content=side)]
        )
    )


def layout_json() -> str:
    return layout().to_json()

"""The Layers folder: a checkbox per layer of the scene, and the two layers that arrive after the
map — the road-removed map and the BEV pyramid level, shown once the localizer has them (on a
first start they are built in the background while the filter plays)."""

from __future__ import annotations

from collections.abc import Callable

from .panel import Controls
from .scene import SceneView


class LayerFolder:
    """``localizer()``: the localizer or None; ``quietly()``: a context in which the viewer's own
    writes to controls run no callbacks; ``on_toggle(name, visible)``: other nodes of that layer
    (a second run's) follow a checkbox too."""

    def __init__(
        self,
        controls: Controls,
        scene: SceneView,
        *,
        guarded: Callable,
        localizer: Callable,
        quietly: Callable,
        on_toggle: Callable[[str, bool], None],
    ):
        self.c, self.scene = controls, scene
        self._localizer, self._quietly, self._on_toggle = localizer, quietly, on_toggle
        for name, h in controls.layers.items():
            h.on_update(guarded(lambda name=name: self.toggle(name), needs_localizer=False))
        controls.bev_level.on_update(guarded(self.show_bev_level))

    def pyramid(self):
        """The localizer's BEV pyramid (None before one is attached)."""
        loc = self._localizer()
        return None if loc is None else loc.pyramid

    def toggle(self, name: str) -> None:
        visible = bool(self.c.layers[name].value)
        if name == "bev_level" and visible:
            self.show_bev_level()
        self.scene.set_layer(name, visible)
        self._on_toggle(name, visible)

    def show_bev_level(self) -> None:
        pyr, level = self.pyramid(), self.c.bev_level
        if pyr is None or not self.c.layers["bev_level"].value:
            return
        top = max(len(pyr.levels) - 1, 0)
        if level.max != top:  # a rebuilt pyramid (new d_m) has other levels
            with self._quietly():
                level.max = top
                level.value = min(level.value, top)
        self.scene.set_pyramid(pyr, int(level.value))

    def show_s2m_tables(self) -> None:
        """The road-removed map layer and the BEV level control, once the localizer has them."""
        loc = self._localizer()
        if loc is None:
            return
        if loc.prior_map.points_bev is not None and not self.scene.has_map_bev:
            self.scene.set_map_bev(loc.prior_map.points_bev)
        pyr = self.pyramid()
        c = self.c
        if pyr is not None and not c.bev_level.visible:
            c.layers["bev_level"].visible = True
            with self._quietly():
                c.bev_level.max = max(len(pyr.levels) - 1, 0)
                c.bev_level.value = min(2, len(pyr.levels) - 1)
            c.bev_level.visible = True

    def on_display(self, ready: bool) -> None:
        """Each display update: the layers that arrived since, the BEV level of a rebuilt pyramid."""
        if ready and not self.c.bev_level.visible:
            self.show_s2m_tables()
        if self._localizer() is not None and self.c.layers["bev_level"].value:
            self.show_bev_level()

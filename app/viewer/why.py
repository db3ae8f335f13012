"""The "why" views: what the filter saw and why it went where it went — the scan's residuals to
the map (at the estimate, a selected particle or the truth), the likelihood surface around the
estimate, one particle's inspection, and the last scan-to-map match in detail.

The :class:`~lidarloc.app.viewer.app.Viewer` builds one :class:`WhyViews` and calls it at four
points only: ``attach`` (a localizer is ready), ``on_draw`` (the display thread just drew a
snapshot), ``clear`` (the run restarted) and ``stop``. Everything else (its panel folder, its scene
nodes, its background computations) lives here and in the modules it uses:
:mod:`.why_residuals`, :mod:`.why_surface`, :mod:`.why_particle`, :mod:`.s2m_detail`, with
:mod:`.why_worker` for the heavy work and :mod:`.why_style` for their colours.

Threads: ``on_draw`` runs on the display thread and only draws the residuals (one table read per
point) and asks for the rest; surfaces and particle ranks are computed on one worker thread
(:class:`~.why_worker.LatestOnly`), where a newer request of a kind supersedes an older one. A
surface asked for by the user comes in two passes (coarse, then full; see :mod:`.why_surface`):
while the scans play, the coarse one is on screen in a quarter of the time.
"""

from __future__ import annotations

import sys
import threading
import traceback
from collections.abc import Callable
from typing import TYPE_CHECKING

from ...core.errors import LidarlocError
from ...core.filter.surface import LikelihoodModel
from .s2m_detail import S2MDetailView, s2m_detail_markdown
from .why_particle import NoParticleNear, ParticleInspector, particle_report, pick_particle
from .why_residuals import AT_CHOICES, AT_ESTIMATE, AT_PARTICLE, ResidualView
from .why_surface import COARSE_CELL, SurfaceView, compute_surface
from .why_worker import LatestOnly

if TYPE_CHECKING:
    import viser

    from ...core.localizer import Localizer
    from ...core.snapshot import Snapshot
    from .scene import SceneView

COARSE = "surface, coarse"  # the worker's kind of a surface's first pass

S2M_HELP = (
    "The last match: its search area, the best candidates the branch and bound scored, the "
    "GICP refinement and why it was accepted or rejected."
)


class WhyViews:
    def __init__(
        self,
        server: viser.ViserServer,
        scene: SceneView,
        *,
        localizer: Callable[[], Localizer | None],
        drawn: Callable[[], Snapshot | None],
        guarded: Callable,
        show_message: Callable,
        folder_order: float,
    ):
        self.server = server
        self.scene = scene
        self._localizer = localizer
        self._drawn = drawn
        self._guarded = guarded
        self._show_message = show_message
        self._folder_order = folder_order
        self._lock = threading.Lock()
        self._s2m_shown = None
        self._surface_scan: int | None = None  # the scan of the surface drawn or being computed
        self.worker = LatestOnly("lidarloc-why")
        gui = server.gui
        with gui.add_folder("Why", order=folder_order, expand_by_default=False):
            with gui.add_folder("Scan residuals"):
                self.residuals = ResidualView(server.scene, gui)
            with gui.add_folder("Likelihood surface"):
                self.surface = SurfaceView(server.scene, gui)
            with gui.add_folder("Inspect a particle"):
                self.particle = ParticleInspector(server.scene, gui)
            with gui.add_folder("S2M match"):
                self.s2m_enabled = gui.add_checkbox(
                    "S2M details", False, hint="The last scan-to-map match's candidates and refinement"
                )
                self.s2m_text = gui.add_markdown("", visible=False)
                gui.add_markdown(f"<small>{S2M_HELP}</small>")
        self.s2m = S2MDetailView(server.scene)
        self._wire()

    # ------------------------------------------------------------------ the four hooks
    def attach(self, localizer: Localizer) -> None:
        """A localizer is ready (called once, before playback starts)."""
        if not localizer.seq.has_poses:
            self.residuals.at.options = AT_CHOICES[:2]  # no truth to place the scan at

    def on_draw(self, snap: Snapshot, recorded: bool = False) -> None:
        """The display thread has just drawn ``snap`` (keep this cheap: heavy work goes to a thread);
        ``recorded``: a step the timeline was moved to, whose surface replaces any other scan's."""
        model = self._model()
        if recorded and self._surface_scan is not None and self._surface_scan != snap.scan_index:
            # another scan's surface (drawn or on its way) must not stay under this one: it goes,
            # and with "Surface on every scan" this scan's follows once its scan is recomputed
            self.worker.cancel(COARSE)
            self.worker.cancel("surface")
            self.surface.clear()
            self._surface_scan = None
        # a snapshot of a run that was restarted meanwhile starts no work whose result would stay
        current = model is not None and self._current(snap)
        if self.particle.selected:
            j = self.particle.resolve(snap)
            if j is not None and current:
                self._submit_report(snap, j, model)
        self.residuals.show(snap if current else None, model, self.particle.pose)
        if self.surface.every_scan.value and current and len(snap.scan_world):
            self._submit_surface(snap, model)
        if snap.s2m is not self._s2m_shown:
            self._show_s2m(snap)

    def clear(self) -> None:
        """The run restarted: nothing of the old run may stay in the scene or the panel."""
        self.worker.cancel()
        self.particle.clear()
        self.residuals.at.value = AT_ESTIMATE  # the inspected particle is gone
        self.residuals.clear()
        self.surface.clear()
        self._surface_scan = None
        with self._lock:
            self._s2m_shown = None
            self.s2m.clear()
            self.s2m_text.content = ""

    def stop(self) -> None:
        """The viewer is stopping: end any background work."""
        self.worker.stop()

    # ------------------------------------------------------------------ controls
    def _wire(self) -> None:
        r, s, p = self.residuals, self.surface, self.particle
        # the views set these two themselves (inspecting a particle, a restart): their callbacks
        # report refusals on their own instead of through the viewer's guard, which would end the
        # guarded action's hold on its tab in the middle of that action
        r.enabled.on_update(self._quietly_guarded(self.redraw_residuals))
        r.at.on_update(self._quietly_guarded(self.redraw_residuals))
        s.button.on_click(self._guarded(self.request_surface))
        s.every_scan.on_update(self._guarded(self._every_scan_toggled))
        s.over_yaw.on_update(self._guarded(lambda: self.request_surface() if s.last is not None else None))
        p.best.on_click(self._guarded(self.inspect_best))
        self.s2m_enabled.on_update(self._guarded(self._toggle_s2m, needs_localizer=False))
        # a plain click (no modifier; shift+click resets the particles)
        self.server.scene.on_click()(self.on_click)

    def _quietly_guarded(self, action: Callable[[], object]) -> Callable:
        def callback(event) -> None:
            try:
                action()
            except LidarlocError as exc:
                self._show_message(f"refused: {exc}", error=True, client=getattr(event, "client", None))
            except Exception as exc:  # keep the server alive and say what went wrong
                traceback.print_exc(file=sys.stderr)
                self._show_message(
                    f"internal error: {type(exc).__name__}: {exc}", error=True, client=getattr(event, "client", None)
                )

        return callback

    def on_click(self, event) -> None:
        """A click in the scene: inspect the particle nearest to it (nothing before the localizer
        is ready: a click then is someone looking around the map)."""
        if self._localizer() is None:
            return
        self._guarded(lambda: self._inspect_click(event))(event)

    def _inspect_click(self, event) -> None:
        """A click on no particle is no refusal: a hint to this tab, which goes by itself."""
        try:
            self.inspect_at(event.ray_origin, event.ray_direction)
        except NoParticleNear as exc:
            self._show_message(f"{exc} to inspect it", client=getattr(event, "client", None))

    def _model(self) -> LikelihoodModel | None:
        loc = self._localizer()
        return None if loc is None else LikelihoodModel.of(loc)

    def _current(self, snap: Snapshot) -> bool:
        """Whether ``snap`` belongs to the localizer's present run: a restart sets its scan
        counter back, so a snapshot of the run before is one of a scan not processed yet."""
        loc = self._localizer()
        return loc is not None and snap.scan_index < loc.k

    def _snapshot(self) -> Snapshot:
        """The drawn snapshot, if it has a scan of the present run."""
        snap = self._drawn()
        if snap is None or snap.scan_index < 0 or len(snap.scan_world) == 0 or not self._current(snap):
            raise LidarlocError("no scan yet: play or step first")
        return snap

    def redraw_residuals(self) -> None:
        snap = self._drawn()
        self.residuals.show(
            snap if snap is not None and self._current(snap) else None, self._model(), self.particle.pose
        )

    # ------------------------------------------------------------------ likelihood surface
    def request_surface(self) -> None:
        """Compute the surface of the drawn scan on the worker thread (superseding one running)."""
        snap, model = self._snapshot(), self._model()
        if model is None:
            raise LidarlocError("the localizer is still starting")
        self._submit_surface(snap, model, coarse_first=True)

    def _every_scan_toggled(self) -> None:
        """Switched on: the drawn scan's surface now, if there is one (else from the next scan)."""
        if self.surface.every_scan.value and self._model() is not None:
            try:
                self.request_surface()
            except LidarlocError:  # no scan yet: the next one will have its surface
                pass

    def _submit_surface(self, snap: Snapshot, model: LikelihoodModel, coarse_first: bool = False) -> None:
        """The surface of ``snap`` on the worker; ``coarse_first``: a coarse pass before it (a
        user's request; the surface on every scan goes straight to the full one)."""
        over_yaw = bool(self.surface.over_yaw.value)
        ground = self.scene.ground
        self._surface_scan = snap.scan_index
        self.surface.busy(snap.scan_index)
        if coarse_first:  # submitted first: the worker takes the kinds in the order they came
            self.worker.submit(
                COARSE,
                lambda: compute_surface(snap, model, over_yaw, COARSE_CELL),
                done=lambda surf: self.surface.draw(surf, snap, ground),
                failed=self._surface_failed,
            )
        else:
            self.worker.cancel(COARSE)  # a first pass of an older request must not land after it
        self.worker.submit(
            "surface",
            lambda: compute_surface(snap, model, over_yaw),
            done=lambda surf: self.surface.draw(surf, snap, ground),
            failed=self._surface_failed,
            superseded_ok=True,
        )

    def _surface_failed(self, message: str) -> None:
        self.surface.failed(message)
        self._show_message(f"likelihood surface: {message}", error=True)

    # ------------------------------------------------------------------ particle inspection
    def inspect_best(self) -> None:
        snap = self._snapshot()
        self._inspect(snap, int(snap.best_index), follow_best=True)

    def inspect_at(self, ray_origin, ray_direction) -> int:
        """Inspect the particle nearest to a click's ray; returns its index."""
        snap = self._snapshot()
        j = pick_particle(snap.particles, ray_origin, ray_direction)
        self._inspect(snap, j, follow_best=False)
        return j

    def _inspect(self, snap: Snapshot, j: int, follow_best: bool) -> None:
        model = self._model()
        self.particle.select(snap, j, follow_best)
        # its scan residual view: the residuals switch to the inspected particle
        r = self.residuals
        if r.at.value != AT_PARTICLE or not r.enabled.value:
            r.at.value = AT_PARTICLE
            r.enabled.value = True
        self.redraw_residuals()
        if model is not None:
            self._submit_report(snap, j, model)

    def _submit_report(self, snap: Snapshot, j: int, model: LikelihoodModel) -> None:
        loc = self._localizer()
        origin = (0.0, 0.0, 0.0) if loc is None else tuple(loc.prior_map.origin)
        self.worker.submit(
            "particle",
            lambda: particle_report(snap, j, model, origin),
            done=self.particle.show,
            failed=self.particle.failed,
        )

    # ------------------------------------------------------------------ S2M details
    def _toggle_s2m(self) -> None:
        on = bool(self.s2m_enabled.value)
        with self._lock:
            self.s2m.set_visible(on)
            self.s2m_text.visible = on
            snap = self._drawn()
            if on and snap is not None:
                self._s2m_shown = snap.s2m
                self.s2m.draw(snap.s2m, True)
                self.s2m_text.content = s2m_detail_markdown(snap.s2m)

    def _show_s2m(self, snap: Snapshot) -> None:
        with self._lock:
            self._s2m_shown = snap.s2m
            on = bool(self.s2m_enabled.value)
            self.s2m.draw(snap.s2m, on)
            if on:
                self.s2m_text.content = s2m_detail_markdown(snap.s2m)

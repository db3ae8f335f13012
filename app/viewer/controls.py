"""The Particles and Parameters folders of the :class:`~lidarloc.app.viewer.app.Viewer`: reset
(button, shift+click, shift+drag), kidnap, and the live parameters with their Apply button. Mixed
into the Viewer, whose state they use (its controls, localizer, player, scene and messages)."""

from __future__ import annotations

import math

import numpy as np

from ...core.errors import LidarlocError
from .ground import clicked_point, dragged_region, pose_on_ground
from .style import SHIFT


class ParticleControls:
    """The Particles folder and the scene's shift picks."""

    def _wire_particles(self) -> None:
        c = self.controls
        c.reset.on_click(self._guarded(self.reset))
        c.kidnap.on_click(self._guarded(self._kidnap))
        self.server.scene.on_click(modifier=SHIFT)(self.on_shift_click)
        self.server.scene.on_rect_select(modifier=SHIFT)(self.on_shift_rect)

    def reset(self, pose: np.ndarray | None = None, region: tuple | None = None) -> None:
        with self.travel.lock:  # between two recorded steps, never inside one
            self.localizer.reset(pose=pose, region=region)
        if pose is not None or region is not None:
            last = self._latest.scan_index if self._latest is not None else -1
            self.scene.show_reset_area(last, center=None if pose is None else pose[:3, 3], region=region)
        self.publish(self.localizer.snapshot())
        where = (
            "globally"
            if pose is None and region is None
            else f"around ({pose[0, 3]:.1f}, {pose[1, 3]:.1f})"
            if pose is not None
            else f"in x {region[0]:.0f}…{region[2]:.0f}, y {region[1]:.0f}…{region[3]:.0f} m"
        )
        self.show_message(f"particles reset {where}")

    def on_shift_click(self, event) -> None:
        """Shift+click on the ground: reset the particles around that point."""

        def act():
            hit = clicked_point(self.scene.ground, event.ray_origin, event.ray_direction)
            self.reset(pose=pose_on_ground(self.scene.ground, hit[0], hit[1], self.localizer.cfg.pf.sensor_height))

        self._guard(event, act)

    def on_shift_rect(self, event) -> None:
        """Shift+drag a rectangle on the ground: reset the particles inside it."""
        self._guard(
            event,
            lambda: self.reset(
                region=dragged_region(self.scene.ground, event.client.camera, event.screen_min, event.screen_max)
            ),
        )

    def _kidnap(self) -> None:
        skip = whole_number(self.controls.kidnap_skip, "kidnap skip", 1)
        before = self.localizer.k
        with self.travel.lock:
            target = self.localizer.kidnap(skip)
        self.player.rebase()
        if target is None:
            target = self.localizer.k
        self._publish_after_control()
        self.show_message(f"kidnapped: the vehicle jumped from scan {before} to {target}; the filter was not told")

    def _publish_after_control(self) -> None:
        """Show what a control just changed at once, also while paused: the localizer brings its
        snapshot up to date after a kidnap or S2M switched off."""
        self.publish(self.localizer.snapshot())


class ParameterControls:
    """The Parameters folder: the numbers, the S2M switch and Apply."""

    def _wire_parameters(self) -> None:
        c = self.controls
        # no localizer needed: on a recorded run the numbers are what "Branch from here" takes
        for h in list(c.params.values()) + c.q:
            h.on_update(self._guarded(self._mark_pending, needs_localizer=False))
        c.s2m_enabled.on_update(self._guarded(self._apply_s2m_enabled))
        c.apply.on_click(self._guarded(self.apply_params))

    def _mark_pending(self) -> None:
        """The Apply button says how many numbers differ from what the localizer has."""
        n = len(self.params.changed()) if self.params.applied else 0  # nothing shown yet: nothing changed
        apply = self.controls.apply
        label = f"Apply {n} change{'s' if n != 1 else ''}" if n else "Apply"
        # one message to the clients: with three, "Apply 1 change" could show while the button
        # was still disabled, and a quick click on it was lost (seen once in the browser test)
        with self.server.atomic():
            if apply.label != label:
                apply.label = label
            apply.disabled = n == 0
            apply.color = "orange" if n else None

    def _apply_s2m_enabled(self) -> None:
        on = bool(self.controls.s2m_enabled.value)
        self.localizer.set_params(s2m_enabled=on)
        self._publish_after_control()
        self.show_message(f"scan-to-map matching {'on' if on else 'off'} from the next scan")

    def apply_params(self) -> dict:
        """Send the changed numbers to the localizer (effective from the next scan). All or nothing:
        an invalid value refuses the whole change with a message. Returns what was sent (SI)."""
        changed = self.params.changed()
        if not changed:
            return {}
        si = self.params.to_si(changed)
        with self.travel.lock:  # set_params validates them all, once, before changing any
            self.localizer.set_params(**si)
        self.params.accept(changed)
        self._mark_pending()
        self.show_message(f"applied from the next scan: {self.params.names(changed)}")
        self._wake.set()
        return si


def whole_number(handle, what: str, minimum: int, maximum: int = 2**32 - 1) -> int:
    """The value of a number field, checked on the server (a page can send anything) to be a whole
    number from ``minimum`` to ``maximum``."""
    v = handle.value
    if not (isinstance(v, (int, float)) and math.isfinite(v) and float(v).is_integer() and minimum <= v <= maximum):
        raise LidarlocError(f"{what} must be a whole number from {minimum} to {maximum}, got {v}")
    return int(v)

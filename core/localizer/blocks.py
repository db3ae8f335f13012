"""The localizer's dealings with its blocks inside a step: waiting for one (giving up on
``interrupt()``), de-skewing a scan for the odometry and S2M, re-initialising the particles, entering
tracking mode, and moving the filter where the whole-map check clearly found it.

De-skew (``localize.deskew``): a spinning LiDAR measures its points over a whole sweep while the
car moves. Each scan is moved into its mid-sweep frame (:mod:`lidarloc.core.odometry.deskew`) before the
PF, the RPE and S2M see it, assuming the motion of the newest known odometry step (constant
velocity over one sweep; the scan's own odometry is not known yet when it arrives). The first two
scans after a (re)start of the odometry have no such step and are used as they come. Recorded
odometry (``localize.recorded_odometry``) is KISS-ICP's over the scans as they come, so with
de-skewing it differs slightly from the live odometry, which registers the de-skewed scans.
"""

from __future__ import annotations

import time
from concurrent.futures import Future
from concurrent.futures import wait as wait_futures

import numpy as np

from ..errors import LidarlocError
from ..failures import BlockError, block_failure
from ..rules.integrity import fits_clearly_better

__all__ = ["BlockError", "BlocksMixin", "Interrupted", "INTERRUPT_POLL_S"]


class Interrupted(LidarlocError):
    """``interrupt()`` stopped a step that was waiting for a block; that scan is not recorded."""


#: How often a step waiting for a block checks for ``interrupt()`` (seconds).
INTERRUPT_POLL_S = 0.05


class BlocksMixin:
    """The step's work with its blocks (see the module docstring). A part of :class:`~lidarloc.core.localizer.Localizer`."""

    def _odometry_scan(self, k: int) -> np.ndarray:
        """Scan k as the odometry and S2M are given it (de-skewed if so configured)."""
        scan = self.seq.scan(k)
        return self._deskew(k, scan) if self.cfg.localize.deskew else scan

    def _deskew(self, k: int, scan: np.ndarray) -> np.ndarray:
        """Scan k moved into its mid-sweep frame with the newest known odometry step's constant
        velocity (see the module docstring); as it comes while no step is known."""
        from ..odometry.deskew import deskew, sweep_offsets, twist_from_relative_pose

        step = self.odometry.last_step(k)
        if step is None:
            return scan
        velocity, angular_velocity = twist_from_relative_pose(*step)
        return deskew(scan, sweep_offsets(scan, self._sweep_period), velocity, angular_velocity)

    def _wait(self, future: Future, block: str, k: int, what: str | None = None, recover: tuple = ()):
        """The result of ``future`` (a block's work for scan k), waiting for it unless
        ``interrupt()`` comes first. A failure is recorded as an ``error`` event, refuses further
        steps, and is raised as one line naming the block (:class:`BlockError`); exceptions of
        the types in ``recover`` are raised as they are, for the caller to handle."""
        if not future.done():
            self._waiting = (
                what or (f"KISS-ICP's registration of scan {k}" if block == "RPE" else block),
                time.monotonic(),
            )
        try:
            while not future.done():
                if self._interrupt.is_set():  # step() refuses further steps until restart()
                    raise Interrupted(f"interrupted at scan {k} while waiting for {block}")
                wait_futures([future], timeout=INTERRUPT_POLL_S)
        finally:
            self._waiting = None
        try:
            return future.result()
        except recover:
            raise
        except Exception as exc:  # a block's failure surfaces once, clearly, in the caller's thread
            error = exc if isinstance(exc, LidarlocError) else block_failure(block, exc, f" at scan {k}")
            self._event(k, "error", str(error))
            # The step that saw it is half done (the PF already weighted scan k): refuse further
            # steps rather than silently repeat or skip work.
            self._failed = str(error)
            raise error from exc

    def _step_failed(self, exc: Exception) -> Exception:
        """What ``step()`` raises for ``exc``: an error the user can fix as it is; a block's failure
        (a BlockError, or any other exception of the step's own work — the PF, the rules — as
        one line naming the PF) recorded as an ``error`` event, refusing further steps like
        :meth:`_wait` (the step is half done)."""
        if isinstance(exc, LidarlocError) and not isinstance(exc, BlockError):
            return exc
        error = exc if isinstance(exc, BlockError) else block_failure("PF", exc, f" at scan {self.k}")
        if self._failed is None:
            self._event(self.k, "error", str(error))
            self._failed = str(error)
        return error

    def _reinitialize(
        self, region=None, pose=None, k: int | None = None, why: str = "re-initialised", speed: float | None = None
    ) -> None:
        """Spread the particles again (globally, in a region or around a pose), leaving tracking
        mode: the full particle count comes back."""
        self.controls += 1
        self.s2m.cancel(self.k - 1 if k is None else k, why)
        if self.pf.n != self.cfg.pf.n_particles:
            self.pf.set_n_particles(self.cfg.pf.n_particles)
        if speed is None:
            self.pf.initialize(region=region, pose=pose)
        else:
            self.pf.initialize(region=region, pose=pose, speed=speed)

    def _fits_better_there(self, pose: np.ndarray, prepared: np.ndarray) -> tuple[bool, str]:
        """Whether the scan fits the map clearly better in 3D at ``pose`` than at the estimate
        (:func:`~lidarloc.core.rules.integrity.fits_clearly_better`), and both fits in words: the
        second test a whole-map check's far pose must pass to move the filter."""
        from ..filter.likelihood import residual_stats
        from ..geometry import pose_to_xyz_ypr

        d_max = self.effective_d_max
        here = residual_stats(self.pf.estimate().state[:6], prepared, self.lookup, d_max)
        there = residual_stats(pose_to_xyz_ypr(pose), prepared, self.lookup, d_max)
        words = (
            f"in 3D mean residual {there[1]:.2f} m against the estimate's {here[1]:.2f} m, inlier share "
            f"{there[0]:.2f} against {here[0]:.2f}"
        )
        return fits_clearly_better(there, here), words

    def _relocalize(self, k: int, verdict) -> None:
        """A whole-map check found a pose far from the estimate that both blocks clearly prefer:
        the particles start again around it, and the rule must fire again (with S2M's word)
        before the filter says localized (see :mod:`lidarloc.core.rules.integrity`)."""
        self._event(k, "relocalized", f"from the estimate to {verdict.describe()}")
        self._reinitialize(
            pose=verdict.pose,
            k=k,
            why="re-localized by the whole-map check",
            speed=self.odometry.rpe.speed(k) if self.odometry.rpe is not None else None,
        )
        self.rules.reset()
        self.integrity.reset()

    def _enter_tracking(self, k: int) -> None:
        """Tracking mode: resample down to fewer particles; S2M searches a smaller region."""
        n = min(self.cfg.localize.tracking_particles, self.cfg.pf.n_particles)
        self.controls += 1
        self.s2m.cancel(k, "tracking mode: particle indices change")
        self.pf.set_n_particles(n)
        self._event(k, "tracking", f"{n} particles, S2M region ±{self.cfg.localize.tracking_region:g} m")

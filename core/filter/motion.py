"""The paper's dynamic model (Dynamic model): constant acceleration, constant turn rate,
approximate first-order hold, plus additive Gaussian process noise.

State: [x, y, z, yaw, pitch, roll, v, yaw_rate, pitch_rate, roll_rate, a] (config.STATE_NAMES),
metres, radians, seconds. With R = R(yaw, pitch, roll) (geometry.rotation_zyx) and the body's
forward axis dir = R·[1, 0, 0]:

    p ← p + v·dir·dt + ½·a·dir·dt²,   v ← v + a·dt,   (yaw, pitch, roll) ← (…) + rates·dt

and the rates and a are carried unchanged. Then w ~ N(0, diag(q_std²)) is added to every entry
(the paper's Q, per step, not scaled by dt) and the three angles are wrapped to [−π, π). The
speed is not clamped at 0: the paper does not, and the noise on v is small (0.1 m/s).
"""

from __future__ import annotations

import numpy as np

from ..errors import LidarlocError
from ..geometry import wrap_angle

N_STATE = 11
ANGLES = slice(3, 6)
RATES = slice(7, 10)


def forward_axis(yaw, pitch) -> np.ndarray:
    """R(yaw, pitch, roll)·[1, 0, 0] (the first column of geometry.rotation_zyx; roll drops out)."""
    cp = np.cos(pitch)
    return np.stack([np.cos(yaw) * cp, np.sin(yaw) * cp, -np.sin(pitch)], axis=-1)


def propagate(states: np.ndarray, dt: float, q_std, rng: np.random.Generator | None) -> np.ndarray:
    """Propagate (N, 11) states by ``dt`` seconds; returns a new array (the input is untouched).

    ``q_std``: 11 process-noise standard deviations (SI units). With ``rng`` None, or all
    q_std zero, no noise is drawn (deterministic motion).
    """
    s = np.asarray(states, dtype=np.float64)
    if s.ndim != 2 or s.shape[1] != N_STATE:
        raise LidarlocError(f"states must be (N, {N_STATE}); got shape {s.shape}")
    q = np.asarray(q_std, dtype=np.float64)
    if q.shape != (N_STATE,):
        raise LidarlocError(f"q_std must have {N_STATE} entries; got {q.shape}")
    dt = float(dt)
    out = s.copy()
    v, a = s[:, 6], s[:, 10]
    along = v * dt + 0.5 * a * dt * dt
    out[:, 0:3] += forward_axis(s[:, 3], s[:, 4]) * along[:, None]
    out[:, 6] = v + a * dt
    out[:, ANGLES] += s[:, RATES] * dt
    if rng is not None and np.any(q > 0):
        out += rng.standard_normal(out.shape) * q
    out[:, ANGLES] = wrap_angle(out[:, ANGLES])
    return out

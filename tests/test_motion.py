"""The 11-state motion model (core/filter/motion.py): closed forms for a straight line and a constant
turn, process-noise statistics and angle wrapping."""

import math

import numpy as np
import pytest
from lidarloc.core.filter.motion import propagate
from lidarloc.core.geometry import rotation_zyx, wrap_angle

ZERO_Q = np.zeros(11)


def test_straight_line_matches_closed_form():
    s = np.zeros((1, 11))
    yaw, pitch, v0, a = 0.7, -0.1, 3.0, 0.5
    s[0, 3], s[0, 4], s[0, 6], s[0, 10] = yaw, pitch, v0, a
    dt, n = 0.1, 50
    for _ in range(n):
        s = propagate(s, dt, ZERO_Q, None)
    T = n * dt
    direction = rotation_zyx(yaw, pitch, 0.3)[:, 0]  # roll does not move the x axis
    np.testing.assert_allclose(s[0, :3], direction * (v0 * T + 0.5 * a * T * T), atol=1e-9)
    assert s[0, 6] == pytest.approx(v0 + a * T)
    np.testing.assert_allclose(s[0, 3:6], [yaw, pitch, 0.0], atol=1e-12)


def test_constant_turn_matches_closed_form():
    v, omega, dt = 5.0, 0.2, 0.1
    n = int(round(2 * math.pi / (omega * dt)))  # one full circle: 314 steps
    omega = 2 * math.pi / (n * dt)
    s = np.zeros((1, 11))
    s[0, 6], s[0, 7] = v, omega
    path = []
    for _ in range(n):
        s = propagate(s, dt, ZERO_Q, None)
        path.append(s[0, :3].copy())
    path = np.array(path)
    # the first-order hold sums v·dt·(cos θ_k, sin θ_k) with θ_k = k·ω·dt: closed form
    k = np.arange(1, n + 1)
    h = omega * dt
    closed_x = v * dt * np.sin(k * h / 2) / np.sin(h / 2) * np.cos((k - 1) * h / 2)
    closed_y = v * dt * np.sin(k * h / 2) / np.sin(h / 2) * np.sin((k - 1) * h / 2)
    np.testing.assert_allclose(path[:, 0], closed_x, atol=1e-8)
    np.testing.assert_allclose(path[:, 1], closed_y, atol=1e-8)
    np.testing.assert_allclose(path[-1], [0, 0, 0], atol=1e-8)  # back at the start after 2π
    # … and it is the continuous circle of radius v/ω to first order in dt
    radius = v / omega
    centre = np.array([0.0, radius])  # start at 0 heading +x, turning left
    assert np.abs(np.linalg.norm(path[:, :2] - centre, axis=1) - radius).max() < v * dt
    assert s[0, 3] == pytest.approx(wrap_angle(n * h))


def test_noise_statistics_and_angle_wrapping():
    rng = np.random.default_rng(0)
    s = np.zeros((50_000, 11))
    s[:, 3] = math.pi - 1e-3
    q = np.linspace(0.01, 0.5, 11)
    out = propagate(s, 0.1, q, rng)
    assert s[:, 3].max() == pytest.approx(math.pi - 1e-3)  # input untouched
    lin = [0, 1, 2, 6, 7, 8, 9, 10]
    np.testing.assert_allclose(out[:, lin].std(axis=0), q[lin], rtol=0.03)
    assert np.all(out[:, 3:6] >= -math.pi) and np.all(out[:, 3:6] < math.pi)
    assert (out[:, 3] < 0).mean() > 0.3  # yaw wrapped past +π

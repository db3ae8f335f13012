"""Configuration (core/config.py): the paper's defaults, YAML / TOML files with --set overrides,
one-line errors, and the example config that lists the defaults."""

import math
from pathlib import Path

import pytest
from lidarloc.core.config import DEG, Config, load_config
from lidarloc.core.errors import LidarlocError


def test_config_defaults_are_the_papers():
    cfg = Config()
    assert cfg.pf.n_particles == 1000 and cfg.pf.scan_voxel == 0.5
    assert cfg.pf.d_max == 5.0 and cfg.pf.sigma == 0.5
    expected_deg = [None, None, None, 5, 2, 0.1, None, 0.05, 0.05, 0.02, None]
    for q, deg in zip(cfg.pf.q_std, expected_deg):
        if deg is not None:
            assert q == pytest.approx(deg * math.pi / 180)
    assert cfg.pf.q_std[:3] == (0.5, 0.5, 0.1) and cfg.pf.q_std[6] == 0.1 and cfg.pf.q_std[10] == 0.001
    assert cfg.pf.init_yaw == pytest.approx(math.pi) and cfg.pf.init_pitch == pytest.approx(30 * DEG)
    assert cfg.s2m.match_resolution == 1.0 and cfg.s2m.angle_step == pytest.approx(2.5 * DEG)
    assert cfg.map.road_normal_z == 0.75
    lc = cfg.localize
    assert (lc.std_threshold, lc.min_consecutive, lc.min_moved, lc.loss_std) == (10.0, 10, 10.0, 50.0)
    assert lc.min_turned == pytest.approx(30 * DEG)


def test_config_yaml_toml_and_overrides(tmp_path):
    y = tmp_path / "c.yaml"
    y.write_text("pf:\n  sigma: 0.7\n  n_particles: 500\ns2m:\n  enabled: false\n")
    cfg = load_config(y, ["pf.d_max=4", "s2m.region_x=30"])
    assert (cfg.pf.sigma, cfg.pf.n_particles, cfg.s2m.enabled, cfg.pf.d_max, cfg.s2m.region_x) == (
        0.7,
        500,
        False,
        4.0,
        30.0,
    )
    t = tmp_path / "c.toml"
    t.write_text("[pf]\nsigma = 0.9\n")
    assert load_config(t).pf.sigma == 0.9


def test_a_tuple_is_set_with_or_without_brackets():
    q = [0.25, 0.25, 0.05] + [0.01] * 8
    plain = load_config(None, ["pf.q_std=" + ",".join(map(str, q))])
    bracketed = load_config(None, ["pf.q_std=[" + ", ".join(map(str, q)) + "]"])
    assert plain.pf.q_std == bracketed.pf.q_std == tuple(q)
    with pytest.raises(LidarlocError, match="not a valid tuple"):
        load_config(None, ["pf.q_std=[0.1, x]"])


@pytest.mark.parametrize(
    "text,needle",
    [
        ("pf: [1, 2", "unreadable config"),
        ("pf:\n  sigmaa: 1\n", "unknown key"),
        ("pf:\n  sigma: -1\n", "sigma must be > 0"),
        ("pf:\n  sigma: abc\n", "not a valid"),
    ],
)
def test_config_errors_are_one_line(tmp_path, text, needle):
    y = tmp_path / "bad.yaml"
    y.write_text(text)
    with pytest.raises(LidarlocError) as info:
        load_config(y)
    assert needle in str(info.value) and "\n" not in str(info.value)


def test_example_config_is_the_defaults():
    """assets/example-config.yaml says it lists the defaults: it loads, and every value matches."""
    asset = Path(__file__).resolve().parents[1] / "assets" / "example-config.yaml"
    loaded, default = load_config(asset, []).to_dict(), Config().to_dict()
    for section, values in loaded.items():
        if not isinstance(values, dict):
            continue
        for key, value in values.items():
            expected = default[section][key]
            if isinstance(expected, float):
                assert math.isclose(value, expected, rel_tol=1e-6), (section, key)
            else:
                assert value == expected, (section, key)

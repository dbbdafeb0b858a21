"""Rig config: the packaged default loads; bad input names the file, the field and what was expected."""
import tomllib

import pytest

from drivers.errors import ConfigError
from rig.config import MATERIALS, default_config_text, load_config, parse_config


def _default() -> dict:
    return tomllib.loads(default_config_text())


def test_default_rig_loads_and_is_simulated():
    cfg = load_config()
    assert cfg.sphere.url == "sim" and cfg.trigger.url == "sim" and cfg.total_station.url == "sim"
    assert cfg.scene.sigma_s_prime_per_mm == MATERIALS["marble"][0]
    assert cfg.camera.white_level_dn > cfg.camera.black_level_dn


@pytest.mark.parametrize("path, value, field, expected", [
    (("sphere", "radius_mm"), -1.0, "sphere.radius_mm", "a number > 0"),
    (("sphere", "driver"), "usb", "sphere.driver", "one of serial"),
    (("camera", "position_mm"), [1, 2], "camera.position_mm", "a list of 3 numbers"),
    (("camera", "width_px"), 10.5, "camera.width_px", "an integer"),
    (("scene", "material"), "unobtainium", "scene.material", "one of custom"),
    (("sphere", "max_mean_duty"), 1.5, "sphere.max_mean_duty", "a number <= 1.0"),
    (("scene", "eta"), 0.5, "scene.eta", "a number >= 1.0"),
    (("scene", "render"), "exact", "scene.render", "one of fast, mc"),
    (("scene", "mc_spp"), 1, "scene.mc_spp", "an integer in [2, 1000000]"),
    (("estimation", "single_image_model"), "diffusion", "estimation.single_image_model", "one of mc-table"),
])
def test_bad_field_is_named(tmp_path, path, value, field, expected):
    data = _default()
    data[path[0]][path[1]] = value
    with pytest.raises(ConfigError) as err:
        parse_config(data, "my_rig.toml")
    msg = str(err.value)
    assert msg.startswith("my_rig.toml: field '" + field + "'")
    assert expected in msg
    assert isinstance(err.value, ValueError)


def test_missing_section_and_field(tmp_path):
    data = _default()
    del data["camera"]
    with pytest.raises(ConfigError, match=r"x.toml: field 'camera': expected a table"):
        parse_config(data, "x.toml")
    data = _default()
    del data["sphere"]["url"]
    with pytest.raises(ConfigError, match=r"field 'sphere.url': expected a value \(field is missing\)"):
        parse_config(data, "x.toml")


def test_white_below_black_is_refused():
    data = _default()
    data["camera"]["white_level_dn"] = 100
    with pytest.raises(ConfigError, match="camera.white_level_dn"):
        parse_config(data, "x.toml")


def test_syntax_error_and_missing_file_name_the_file(tmp_path):
    bad = tmp_path / "broken.toml"
    bad.write_text("[sphere\nradius_mm = 1")
    with pytest.raises(ConfigError, match=r"broken.toml: field '<syntax>': expected valid TOML"):
        load_config(bad)
    with pytest.raises(ConfigError, match=r"nope.toml: field '<file>'"):
        load_config(tmp_path / "nope.toml")


def test_duplicate_target_names_refused():
    data = _default()
    data["targets"] = [{"name": "a", "xyz_mm": [0, 0, 0]}, {"name": "a", "xyz_mm": [1, 0, 0]}]
    with pytest.raises(ConfigError, match="unique target names"):
        parse_config(data, "x.toml")


def test_scene_render_mode_reaches_the_simulated_camera(tmp_path):
    """[scene] render = "mc" makes the simulated camera render with Monte Carlo light transport, and the session's
    truth says which renderer made the frames (the estimators' model comparison names it)."""
    from rig.acquire.factory import start_simulators
    from rig.acquire.geometry import rig_geometry

    data = _default()
    data["scene"].update(render="mc", mc_spp=8)
    cfg = parse_config(data, "mc_rig.toml")
    assert cfg.scene.render == "mc" and cfg.scene.mc_spp == 8
    sim = start_simulators(cfg, rig_geometry(cfg), tmp_path)
    try:
        assert sim.camera.render_mode == "mc" and sim.camera.mc.spp == 8 and sim.camera.mc.seed == cfg.scene.seed
        assert sim.truth["renderer"].startswith("Monte Carlo")
    finally:
        sim.close()
    fast = load_config()
    assert fast.scene.render == "fast"

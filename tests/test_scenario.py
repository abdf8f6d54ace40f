from __future__ import annotations

import pytest

from shared.scenario import SCENARIO_DIR, ScenarioError, load_scenario
from tests.conftest import write_variant


def test_default_scenario_loads_with_paper_values():
    scenario = load_scenario()
    assert scenario.name == "icc2021"
    assert len(scenario.gbs.positions) == 12
    assert scenario.gbs.power_w == 1.0 and scenario.gbs.height_m == 32.0
    assert scenario.gbs.tilt_deg == 10.0 and scenario.gbs.beamwidth_3db_deg == 15.0
    assert scenario.uav.altitude_m == 50.0
    assert scenario.channel.noise_w == 1e-6 and scenario.channel.sinr_threshold_db == -3.0
    assert scenario.policy.observed_uavs == 4
    assert scenario.timing.disconnection_limit_steps == round(
        scenario.timing.disconnection_limit_s / scenario.timing.step_s
    )


def test_load_by_path_equals_load_by_name():
    assert load_scenario(SCENARIO_DIR / "icc2021.toml") == load_scenario("icc2021")


@pytest.mark.parametrize(
    ("old", "new", "field"),
    [
        ("x_min = -50.0", "x_min = 60.0", "area"),
        ("power_w = 1.0              # paper", "power_w = -1.0", "gbs.power_w"),
        ("max_speed_mps = 5.0", 'max_speed_mps = "fast"', "uav.max_speed_mps"),
        ("noise_w = 1e-6", "noise_w = nan", "channel.noise_w"),
        ("uav_count = 4", "uav_count = 4\nsquadrons = 2", "missions.squadrons"),
        ("level_edges_db = [-3.0, -2.21]", "level_edges_db = [-2.0, -3.0]", "level_edges_db"),
        ("x = 0.0\ny = 0.0", "x = 80.0\ny = 0.0", "jammer"),
        ("gbs_sigma_db = 3.0", "gbs_sigma_db = -1.0", "shadowing.gbs_sigma_db"),
        ("jammer_sigma_db = 3.0", "jammer_sigma_db = -0.5", "shadowing.jammer_sigma_db"),
        ("decorrelation_m = 10.0", "decorrelation_m = 0", "shadowing.decorrelation_m"),
        ("field_spacing_m = 1.0", "field_spacing_m = 0.0", "shadowing.field_spacing_m"),
        ("field_spacing_m = 1.0", "field_spacing_m = 0.01", "shadowing"),
        ("seed = 1", "seed = -1", "shadowing.seed"),
        ("measurement_noise_db = 1.0", "measurement_noise_db = -1.0",
         "uav.measurement_noise_db"),
        ("min_trip_m = 40.0", "min_trip_m = 40.0\nmax_trip_m = 30.0", "missions"),
        # The missions' area inside the 5 m margin is 90 m square, with a 127.3 m diagonal; a
        # 50 m margin leaves nothing of the 100 m area.
        ("margin_m = 5.0", "margin_m = 50.0", "missions.margin_m leaves no room"),
        ("min_trip_m = 40.0", "min_trip_m = 128.0", "longer than any trip inside the margin "
         "(127.3 m at most)"),
        ("power_w = 1.0\n# Open: a jammer", "power_w = 1001.0\n# Open: a jammer",
         "jammer.power_w"),
        ("max_attenuation_db = 20.0", "max_attenuation_db = 20.0\nchannels = [0, 1]", "gbs"),
        ("max_attenuation_db = 20.0", "max_attenuation_db = 20.0\nchannels = " + str([-1] * 12),
         "gbs.channels"),
    ],
)
def test_invalid_files_give_one_line_naming_file_and_field(tmp_path, old, new, field):
    # The shadowing cases edit the shadowed world, the only shipped file with those lines.
    idealized = (SCENARIO_DIR / "icc2021.toml").read_text()
    path = write_variant(tmp_path, old, new,
                         "icc2021" if old in idealized else "icc2021-shadowed")
    with pytest.raises(ScenarioError) as caught:
        load_scenario(path)
    message = str(caught.value)
    assert "\n" not in message
    assert str(path) in message
    assert field in message


def test_missing_field_and_broken_toml(tmp_path):
    path = write_variant(tmp_path, "radius_m = 1.0\n", "")
    with pytest.raises(ScenarioError, match=r"uav\.radius_m: Field required"):
        load_scenario(path)
    broken = tmp_path / "broken.toml"
    broken.write_text("[area\nx_min = 1")
    with pytest.raises(ScenarioError, match="not valid TOML"):
        load_scenario(broken)


def test_unknown_name_lists_known_ones():
    with pytest.raises(ScenarioError, match="icc2021"):
        load_scenario("no-such-scenario")


def test_with_jammer_keeps_height_and_validates():
    scenario = load_scenario()
    moved = scenario.with_jammer(25.0, -10.0, 0.5)
    assert (moved.jammer.x, moved.jammer.y, moved.jammer.power_w) == (25.0, -10.0, 0.5)
    assert moved.jammer.height_m == scenario.jammer.height_m
    assert scenario.with_jammer(25.0, -10.0, 0.5, height_m=12.0).jammer.height_m == 12.0
    assert not scenario.without_jammer().jammer.enabled


def test_the_tt6_world_is_icc2021_but_for_the_disconnection_limit():
    """docs/paper_ablation.md reads icc2021-tt6 as one difference from icc2021: the files must
    not drift apart."""
    base, tt6 = load_scenario("icc2021").model_dump(), load_scenario("icc2021-tt6").model_dump()
    assert tt6["timing"].pop("disconnection_limit_s") == 6.0
    assert base["timing"].pop("disconnection_limit_s") == 3.0
    assert {**tt6, "name": "icc2021"} == base

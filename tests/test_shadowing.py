"""Shadowing fields and measurement noise: statistics against the stated model, and the radio
model with and without them."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cloud_service.simulated_measurements import measurements_at
from shared.radio import JammerParams, RadioModel
from shared.scenario import load_scenario
from shared.shadowing import ShadowingField, shadowing_field
from shared.shipped import SINR_MAP_NO_JAMMER, SINR_MAP_NO_JAMMER_SHADOWED
from shared.survey_maps import (
    NoSurveyMapError,
    foreign_survey_map,
    sinr_map_for,
    survey_world_digest,
)
from tests.conftest import variant

SEEDS = range(6)  # 6 seeds x 13 fields: the pooled estimates below spread by ~0.015 (1 sd)
TOLERANCE = 0.06  # about 4 sd of those estimates


@pytest.fixture(scope="module")
def shadowed():
    return load_scenario("icc2021-shadowed")


def field_values(scenario, **changes) -> np.ndarray:
    """Node values (ny, nx, 13) of a freshly drawn field (not the cached one)."""
    config = scenario.shadowing.model_copy(update=changes)
    return ShadowingField(config, scenario.area, len(scenario.gbs.positions)).values_db


@pytest.fixture(scope="module")
def unit_fields(shadowed):
    """Fields of unit sigma for several seeds: (seeds, ny, nx, 13)."""
    return np.stack([field_values(shadowed, seed=seed, gbs_sigma_db=1.0, jammer_sigma_db=1.0)
                     for seed in SEEDS])


def lagged_product(fields: np.ndarray, lag_x: int, lag_y: int) -> float:
    """Mean of f(p) f(p + lag) over the grid, the fields and the seeds: the covariance at that
    lag for a zero-mean field."""
    ny, nx = fields.shape[1:3]
    here = fields[:, : ny - lag_y, : nx - lag_x]
    there = fields[:, lag_y:, lag_x:]
    return float((here * there).mean())


def test_variance_and_correlation_follow_the_exponential_model(shadowed, unit_fields):
    spacing = shadowed.shadowing.field_spacing_m
    decorrelation = shadowed.shadowing.decorrelation_m
    for distance in (0.0, decorrelation / 2, decorrelation, 2 * decorrelation):
        lag = round(distance / spacing)
        expected = math.exp(-lag * spacing / decorrelation)
        along_x = lagged_product(unit_fields, lag, 0)
        along_y = lagged_product(unit_fields, 0, lag)
        assert along_x == pytest.approx(expected, abs=TOLERANCE), distance
        assert along_y == pytest.approx(expected, abs=TOLERANCE), distance
    # Isotropic: the diagonal lag (7, 7) is 9.9 m, not 14 m of city blocks.
    diagonal = lagged_product(unit_fields, 7, 7)
    assert diagonal == pytest.approx(math.exp(-7 * math.sqrt(2) * spacing / decorrelation),
                                     abs=TOLERANCE)
    assert abs(float(unit_fields.mean())) < TOLERANCE


def test_each_link_has_its_stated_sigma(shadowed):
    values = np.stack([field_values(shadowed, seed=seed, gbs_sigma_db=2.0, jammer_sigma_db=5.0)
                       for seed in SEEDS])
    gbs_sigma = math.sqrt(float((values[..., :-1] ** 2).mean()))
    jammer_sigma = math.sqrt(float((values[..., -1] ** 2).mean()))
    # The jammer's field is one per seed (not 12): its estimate spreads more.
    assert gbs_sigma == pytest.approx(2.0, rel=TOLERANCE / 2)
    assert jammer_sigma == pytest.approx(5.0, rel=2 * TOLERANCE)


def test_transmitters_are_independent(unit_fields):
    links = unit_fields.shape[-1]
    cross = [float((unit_fields[..., a] * unit_fields[..., b]).mean())
             for a in range(links) for b in range(a + 1, links)]
    assert abs(np.mean(cross)) < TOLERANCE / 4
    assert max(abs(c) for c in cross) < 2.5 * TOLERANCE  # one pair of one-field-per-seed


def test_the_embedding_needed_no_correction(shadowed):
    assert shadowing_field(shadowed).clipped_share < 1e-6


def test_fields_are_fixed_by_seed_and_transmitter(shadowed):
    first = field_values(shadowed)
    np.testing.assert_array_equal(first, field_values(shadowed))
    other = field_values(shadowed, seed=shadowed.shadowing.seed + 1)
    assert not np.allclose(first, other)
    # A GBS's field depends on its own index only: dropping GBSs leaves the others' fields.
    fewer = ShadowingField(shadowed.shadowing, shadowed.area, 4).values_db
    np.testing.assert_array_equal(fewer[..., :4], first[..., :4])


def test_interpolation_is_exact_at_nodes_bilinear_between_and_clamped_outside(shadowed):
    field = shadowing_field(shadowed)
    xs, ys = field.node_positions()
    values = field.values_db
    np.testing.assert_allclose(field.at(np.array([xs[7], ys[3]])), values[3, 7], atol=1e-12)
    middle = field.at(np.array([(xs[7] + xs[8]) / 2, (ys[3] + ys[4]) / 2]))
    np.testing.assert_allclose(middle, values[3:5, 7:9].mean(axis=(0, 1)), atol=1e-12)
    np.testing.assert_allclose(field.at(np.array([xs[0] - 500.0, ys[-1] + 3.0])),
                               values[-1, 0], atol=1e-12)
    assert field.at(np.zeros((3, 5, 2))).shape == (3, 5, values.shape[-1])


def test_interpolated_sigma_between_nodes(shadowed):
    # Bilinear interpolation averages neighbouring nodes: at spacing d/10 the std between
    # nodes averages 97 % of the stated one (computed from the model).
    field = shadowing_field(shadowed)
    points = np.random.default_rng(3).uniform(-50, 50, size=(20_000, 2))
    sigma = float(np.sqrt((field.at(points) ** 2).mean()))
    assert 0.85 * shadowed.shadowing.gbs_sigma_db < sigma < 1.1 * shadowed.shadowing.gbs_sigma_db


def test_shadowed_radio_is_the_ideal_one_times_the_field_by_hand(shadowed):
    shadowed_radio, ideal = RadioModel(shadowed), RadioModel(shadowed, shadowed=False)
    field = shadowed_radio.shadowing
    xs, ys = field.node_positions()
    point = np.array([xs[40], ys[70]])  # a grid node: the field there is a stored value
    field_db = field.values_db[70, 40]
    ratio = shadowed_radio.gbs_received_power(point) / ideal.gbs_received_power(point)
    np.testing.assert_allclose(ratio, 10.0 ** (field_db[:-1] / 10.0), rtol=1e-12)
    jammer = JammerParams(5.0, -8.0, 1.0, 30.0)
    jammed = (shadowed_radio.jammer_interference(point, jammer)
              / ideal.jammer_interference(point, jammer))
    assert jammed == pytest.approx(10.0 ** (field_db[-1] / 10.0), rel=1e-12)
    # Eq. (1) on the shadowed powers.
    received = shadowed_radio.gbs_received_power(point)
    interference = shadowed_radio.jammer_interference(point, jammer)
    best = int(received.argmax())
    sinr = received[best] / (shadowed.channel.noise_w + interference + received.sum()
                             - received[best])
    reading = shadowed_radio.evaluate(point, jammer)
    assert float(reading.sinr) == pytest.approx(sinr, rel=1e-12)
    assert int(reading.serving_gbs) == best


def test_without_a_section_or_unshadowed_the_radio_is_the_ideal_one(scenario, shadowed):
    assert scenario.shadowing is None
    assert RadioModel(scenario).shadowing is None
    assert RadioModel(shadowed, shadowed=False).shadowing is None
    points = np.random.default_rng(5).uniform(-55, 55, size=(500, 2))
    jammer = JammerParams(25.0, -10.0, 1.0, 30.0)
    for jam in (None, jammer):
        ideal = RadioModel(scenario).evaluate(points, jam)
        unshadowed = RadioModel(shadowed, shadowed=False).evaluate(points, jam)
        truth = RadioModel(shadowed).evaluate(points, jam)
        np.testing.assert_array_equal(unshadowed.sinr_db, ideal.sinr_db)
        assert np.abs(truth.sinr_db - ideal.sinr_db).mean() > 1.0


def test_one_realisation_per_shadowing_section(shadowed):
    assert RadioModel(shadowed).shadowing is RadioModel(shadowed).shadowing


def test_measurement_noise_has_the_stated_statistics(shadowed):
    radio = RadioModel(shadowed)
    truth = np.linspace(-10.0, 10.0, 200_000)
    error = radio.measured_sinr_db(truth, np.random.default_rng(11)) - truth
    sigma = shadowed.uav.measurement_noise_db
    assert sigma > 0
    assert abs(float(error.mean())) < 4 * sigma / math.sqrt(len(error))
    assert float(error.std()) == pytest.approx(sigma, rel=0.01)
    levels = radio.measured_reports(truth, np.random.default_rng(11)).level
    np.testing.assert_array_equal(levels, radio.level_of(truth + error))
    assert levels.dtype == np.int8


def test_exact_receivers_draw_no_noise(scenario):
    radio = RadioModel(scenario)
    rng = np.random.default_rng(2)
    before = rng.bit_generator.state
    truth = np.array([-3.5, -2.5, 0.0])
    np.testing.assert_array_equal(radio.measured_reports(truth, rng).level, radio.level_of(truth))
    assert rng.bit_generator.state == before


def test_measurements_are_labelled_with_the_noisy_truth(shadowed):
    xy = np.random.default_rng(4).uniform(-50, 50, size=(5000, 2))
    radio = RadioModel(shadowed)
    sinr_db = radio.evaluate(xy).sinr_db
    exact = radio.level_of(sinr_db)
    assert float((exact != RadioModel(shadowed, shadowed=False).evaluate(xy).level).mean()) > 0.1
    # Exact receivers: the label is the shadowed truth.
    exact_receivers = variant(shadowed, uav={"measurement_noise_db": 0.0})
    batch = measurements_at(exact_receivers, RadioModel(exact_receivers), None, xy,
                            np.random.default_rng(9))
    np.testing.assert_array_equal(batch.levels, exact)
    # Noisy receivers: labels leave the truth as often as the receiver's noise makes them.
    batch = measurements_at(shadowed, radio, None, xy, np.random.default_rng(9))
    flipped = float((batch.levels != exact).mean())
    reported = radio.measured_reports(sinr_db, np.random.default_rng(10)).level
    expected = float((reported != exact).mean())
    assert 0.05 < expected < 0.5
    assert flipped == pytest.approx(expected, abs=0.03)  # 5,000 labels: sd ~0.6 point


def test_survey_map_per_radio_world():
    """The survey map goes with the radio world, not the scenario's name: a renamed copy
    with other missions or planning values shares its map; a copy in another radio world
    (here with icc2021-shadowed's name) has none, and is told so in one line."""
    shadowed, idealized = load_scenario("icc2021-shadowed"), load_scenario("icc2021")
    assert sinr_map_for(shadowed) == SINR_MAP_NO_JAMMER_SHADOWED
    assert sinr_map_for(idealized) == SINR_MAP_NO_JAMMER
    assert sinr_map_for(load_scenario("icc2021-tt6")) == SINR_MAP_NO_JAMMER  # timing only
    replanned = shadowed.changed({"missions.uav_count": 8, "policy.lookahead_depth": 1,
                                  "jammer.power_w": 0.5}, name="my-copy")
    assert sinr_map_for(replanned) == SINR_MAP_NO_JAMMER_SHADOWED
    # Each refused world, and the closest shipped one named with what sets them apart.
    for change, named in (({"shadowing.gbs_sigma_db": 4.0}, "icc2021-shadowed's in shadowing"),
                          ({"channel.path_loss_exponent": 3.0},
                           "icc2021-shadowed's in channel"),
                          ({"uav.measurement_noise_db": 0.0}, "icc2021's in shadowing")):
        with pytest.raises(NoSurveyMapError) as refused:
            sinr_map_for(shadowed.changed(change, name="icc2021-shadowed"))
        message = str(refused.value)
        assert "\n" not in message and "jamnav fit-sinr" in message and "--sinr-map" in message
        assert f"differs from {named})" in message


def test_a_survey_map_from_another_world_is_flown_with_a_warning(capsys, tmp_path):
    """A survey map's card records the radio world it was learned in (fit-sinr writes it, the
    shipped cards carry it); given explicitly for another world, it is flown, with one line
    of warning."""
    from cloud_service.sinr_training import fit_sinr_map
    from jamnav.cli import main
    from planning.networks import load_network

    shadowed, idealized = load_scenario("icc2021-shadowed"), load_scenario("icc2021")
    _, card = fit_sinr_map(shadowed, None, 200, 2, 0)
    assert card["survey_world"] == survey_world_digest(shadowed) != survey_world_digest(idealized)
    _, shipped = load_network(SINR_MAP_NO_JAMMER)
    assert foreign_survey_map(shipped, idealized) is None
    assert foreign_survey_map({"scenario": "older"}, shadowed) is None  # a card that does not say
    warning = foreign_survey_map(shipped, shadowed)
    assert "'icc2021'" in warning and "'icc2021-shadowed'" in warning

    assert main(["eval", "--scenario", "icc2021-shadowed", "--method", "proposed", "--episodes",
                 "1", "--json", "--sinr-map", str(SINR_MAP_NO_JAMMER)]) == 0
    err = capsys.readouterr().err
    assert [line for line in err.splitlines() if "warning" in line] == [
        f"jamnav: warning: --sinr-map: {warning}"]

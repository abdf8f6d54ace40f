"""The jammer estimate from uploads: positions, fit, decision, corrected map.

The truth is icc2021-shadowed's world (correlated shadowing on every link, receiver noise);
the estimator sees only levels, positions and the no-jammer map's levels. Bounds are set
from measured spreads (see each test) with a margin, and fail on a real regression.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.special import ndtr as norm_cdf

from cloud_service.estimated_jammer import JammerEstimate, estimated_set, posterior_hypotheses
from cloud_service.jammer_estimation import (
    estimate_jammer,
    estimate_jammers,
    jammer_hypotheses,
    locate_jammer,
    one_more_evidence,
    placed_evidence,
)
from cloud_service.map_correction import (
    corrected_levels,
    ideal_level_probabilities,
    ideal_model_spread_db,
)
from cloud_service.no_jammer_belief import MAP_READING_SD_DB, fit_shadowing_sigma, prior_of_map
from cloud_service.report_likelihood import REPORT_SIGMA_DB, report_shares
from cloud_service.upload_positions import positions_from_features
from planning.measuring import SpotFilter, scenario_features
from shared.paper import TABLE_I_JAMMERS
from shared.radio import JammerParams, RadioModel
from shared.scenario import Scenario, load_scenario
from tests import float32_bounds as bounds
from tests.conftest import variant

SETTINGS = 10  # seeded jammer settings (and shadowing realisations) per accuracy check


@pytest.fixture(scope="module")
def shadowed() -> Scenario:
    return load_scenario("icc2021-shadowed")


def world(shadowed: Scenario, seed: int) -> Scenario:
    """icc2021-shadowed with shadowing realisation ``seed``."""
    return variant(shadowed, shadowing={"seed": seed})


def random_jammer(scenario: Scenario, rng: np.random.Generator) -> JammerParams:
    area = scenario.area
    return JammerParams(rng.uniform(area.x_min, area.x_max), rng.uniform(area.y_min, area.y_max),
                        rng.uniform(0.25, 1.0), scenario.jammer.height_m)


def reports(scenario: Scenario, jammer: JammerParams | None, xy: np.ndarray, rng):
    """Levels the world's receivers report at ``xy``, and the world's no-jammer levels there
    (what a perfectly learned no-jammer map says)."""
    truth = RadioModel(scenario)
    levels = truth.measured_reports(truth.evaluate(xy, jammer).sinr_db, rng).level
    return levels, truth.evaluate(xy).level


def uniform_points(scenario: Scenario, rng: np.random.Generator, n: int) -> np.ndarray:
    area = scenario.area
    return rng.uniform((area.x_min, area.y_min), (area.x_max, area.y_max), size=(n, 2))


def flights(scenario: Scenario, jammer, rng, uavs: int = 4, seconds: float = 10.0):
    """What ``uavs`` UAVs flying straight, random paths at full speed for ``seconds`` upload:
    uav.measurements_per_step reports a step, de-duplicated as agents do (``SpotFilter``)."""
    area, uav = scenario.area, scenario.uav
    samples = round(seconds / scenario.timing.step_s * uav.measurements_per_step)
    length = uav.max_speed_mps * seconds
    starts = np.empty((uavs, 2))
    ends = np.empty((uavs, 2))
    for k in range(uavs):
        while True:
            starts[k] = uniform_points(scenario, rng, 1)[0]
            heading = rng.uniform(0.0, 2.0 * np.pi)
            ends[k] = starts[k] + length * np.array([np.cos(heading), np.sin(heading)])
            if area.contains(*ends[k]):
                break
    along = np.arange(1, samples + 1) / samples
    xy = starts[:, None, :] + along[None, :, None] * (ends - starts)[:, None, :]
    levels, no_jammer = reports(scenario, jammer, xy, rng)
    kept = SpotFilter(scenario, uavs).keep(np.arange(uavs), xy, levels)
    return xy[kept], levels[kept], no_jammer[kept]


def position_error(estimate: JammerEstimate, jammer: JammerParams) -> float:
    return float(np.hypot(estimate.x - jammer.x, estimate.y - jammer.y))


def power_error_db(estimate: JammerEstimate, jammer: JammerParams) -> float:
    return float(10.0 * np.log10(estimate.power_w / jammer.power_w))


# -- positions ----------------------------------------------------------------------------------
def offset_rounding(features: np.ndarray) -> float:
    """A position read back is a GBS's less the float32 offset to it: one rounding."""
    return bounds.rounded_once(np.abs(features[:, :2]).max())


def test_positions_round_trip_the_features(scenario):
    rng = np.random.default_rng(0)
    gbs = np.asarray(scenario.gbs.positions)
    # Random points, the GBSs themselves, and points equidistant from two GBSs (ties).
    xy = np.concatenate([uniform_points(scenario, rng, 3000) * 1.2, gbs,
                         [[0.0, 0.0], [0.0, 16.5], [25.0, -16.5], [-25.0, 0.0]]])
    features = scenario_features(scenario, xy)
    recovered = positions_from_features(scenario, features)
    assert recovered.shape == xy.shape
    np.testing.assert_allclose(recovered, xy, atol=offset_rounding(features))


def test_positions_no_place_gives_are_nan(scenario):
    xy = uniform_points(scenario, np.random.default_rng(2), 100)
    features = scenario_features(scenario, xy)
    features[::2, 5] += 0.5  # the second GBS's dx no longer fits the first's
    recovered = positions_from_features(scenario, features)
    assert np.isnan(recovered[::2]).all()
    np.testing.assert_allclose(recovered[1::2], xy[1::2], atol=offset_rounding(features))


def test_positions_a_repeating_layout_cannot_tell_apart_are_nan(scenario):
    few = variant(scenario, policy={"nearby_gbs": 4})
    xy = uniform_points(few, np.random.default_rng(1), 2000)
    features = scenario_features(few, xy)
    recovered = positions_from_features(few, features)
    unknown = np.isnan(recovered).any(axis=1)
    assert 0 < unknown.mean() < 1  # a lattice step apart, the 4 nearest offsets repeat
    np.testing.assert_allclose(recovered[~unknown], xy[~unknown], atol=offset_rounding(features))


# -- the fit ------------------------------------------------------------------------------------
def fit_settings(shadowed: Scenario | None, data: str):
    """(estimate, jammer) for SETTINGS seeded settings: a random jammer (uniform in the area,
    0.25-1 W) in shadowing realisation ``seed`` of icc2021-shadowed (or in icc2021 when
    ``shadowed`` is None), measured ``data``: "uniform" (2,000 points) or "flights"."""
    out = []
    for seed in range(SETTINGS):
        rng = np.random.default_rng(seed)
        scenario = load_scenario() if shadowed is None else world(shadowed, seed)
        jammer = random_jammer(scenario, rng)
        if data == "uniform":
            xy = uniform_points(scenario, rng, 2000)
            levels, no_jammer = reports(scenario, jammer, xy, rng)
        else:
            xy, levels, no_jammer = flights(scenario, jammer, rng)
        out.append((estimate_jammer(scenario, xy, levels, no_jammer_levels=no_jammer), jammer))
    return out


def test_recovers_a_jammer_in_the_shadowed_world(shadowed):
    """Measured over 30 such settings: 23 converge; median error 9 m (7-11 m per ten),
    median power error 2.2 dB. Without the no-jammer levels the median error is 50-75 m."""
    fits = [(e, j) for e, j in fit_settings(shadowed, "uniform") if e is not None]
    located = [(e, j) for e, j in fits if e.present]
    assert len(located) >= 6
    assert np.median([position_error(e, j) for e, j in located]) <= 13.0
    assert np.median([abs(power_error_db(e, j)) for e, j in located]) <= 3.0
    for estimate, jammer in located:  # its standard deviations hold the error
        assert position_error(estimate, jammer) <= 4.0 * np.hypot(estimate.sd_x_m,
                                                                  estimate.sd_y_m)


def test_recovers_a_jammer_in_the_ideal_world():
    """icc2021, exact receivers. Measured over 30: 26 converge; median error 4 m, median
    power error 0.8 dB: the level quantization and a loss of at most ~2.5 dB, not noise,
    limit it."""
    located = [(e, j) for e, j in fit_settings(None, "uniform") if e is not None and e.present]
    assert len(located) >= 7
    assert np.median([position_error(e, j) for e, j in located]) <= 6.0
    assert np.median([abs(power_error_db(e, j)) for e, j in located]) <= 1.5


@pytest.mark.parametrize("x, y, power_w", [(0, 0, 2.0), (25, -10, 2.0), (0, 0, 1.0)])
def test_exact_reports_around_the_jammer_give_its_power(scenario, x, y, power_w):
    """icc2021's receivers are exact; reports from within 35 m of the jammer, as UAVs that
    fly along its zone give. Read at the 1.2 dB report spread alone, (0,0) 2 W came out
    0.83 dB strong and 1.4 m off; refitted at the spread that explains the reports best,
    within 0.1 dB and 0.4 m on every setting here."""
    jammer = JammerParams(x, y, power_w, scenario.jammer.height_m)
    rng = np.random.default_rng(0)
    distance, angle = 35.0 * np.sqrt(rng.random(1500)), rng.uniform(0.0, 2.0 * np.pi, 1500)
    xy = np.stack([x + distance * np.cos(angle), y + distance * np.sin(angle)], axis=-1)
    xy = xy[[scenario.area.contains(*point) for point in xy]]
    truth = RadioModel(scenario)
    estimate = estimate_jammer(scenario, xy, truth.evaluate(xy, jammer).level,
                               no_jammer_levels=truth.evaluate(xy).level)
    assert estimate is not None and estimate.present
    assert abs(power_error_db(estimate, jammer)) <= 0.3
    assert position_error(estimate, jammer) <= 1.0


@pytest.mark.parametrize("jammers", [
    (), ((-20.0, 15.0, 1.0),), ((-25.0, 15.0, 1.0), (25.0, -10.0, 1.0)),
    ((-25.0, 15.0, 1.0), (25.0, -10.0, 1.0), (10.0, 30.0, 0.7))],
    ids=["none", "one", "two", "three"])
def test_the_jammers_are_counted_and_each_placed_on_crafted_reports(scenario, jammers):
    """icc2021's exact receivers, 2,000 reports over the area and the no-jammer levels there:
    BIC's penalty picks the count. Measured: every jammer within 1.6 m and 0.4 dB, but the
    third of three, 5.9 m and 0.9 dB off beside two others of its strength."""
    truth = RadioModel(scenario)
    xy = uniform_points(scenario, np.random.default_rng(0), 2000)
    placed = [JammerParams(x, y, power_w, scenario.jammer.height_m) for x, y, power_w in jammers]
    found = estimate_jammers(scenario, xy, truth.evaluate(xy, placed).level,
                             no_jammer_levels=truth.evaluate(xy).level)
    assert found is not None and len(found) == len(placed)
    for jammer in placed:  # the estimate nearest each jammer
        nearest = min(found, key=lambda estimate: position_error(estimate, jammer))
        assert position_error(nearest, jammer) <= (8.0 if len(placed) == 3 else 3.0)
        assert abs(power_error_db(nearest, jammer)) <= 1.5


def test_the_evidence_for_one_jammer_more_falls_once_the_jammers_are_known(scenario):
    """Two jammers on exact reports over the area: each, the other known, explains them by
    far more than BIC's penalty; a third, both known, by less (it finds nothing left to
    explain: the survey's exact levels leave the reports no misfit)."""
    truth = RadioModel(scenario)
    xy = uniform_points(scenario, np.random.default_rng(0), 2000)
    jammers = [JammerParams(-25.0, 15.0, 1.0, scenario.jammer.height_m),
               JammerParams(25.0, -10.0, 1.0, scenario.jammer.height_m)]
    levels, no_jammer = truth.evaluate(xy, jammers).level, truth.evaluate(xy).level
    placed = [(np.array([jammer.x, jammer.y]), scenario.jammer.efficiency_db)  # 1 W: 0 dBW
              for jammer in jammers]

    def one_more(known):
        return one_more_evidence(scenario, xy, levels, known, no_jammer_levels=no_jammer)

    # Measured: each 61-63 nats against a penalty of 10.3, a third -1.2. The float32 sums of
    # 2,000 reports, each at most 5.8 nats (the outlier floor), round by under n eps sum|x| =
    # 2,000 x 6e-8 x 11,600 = 1.4 nats: far inside both margins.
    for index in range(2):
        llr, penalty = one_more(placed[:index] + placed[index + 1:])
        assert llr > 2 * penalty
    llr, penalty = one_more(placed)
    assert llr < penalty
    assert one_more_evidence(scenario, xy[:10], levels[:10], [],
                             no_jammer_levels=no_jammer[:10]) is None


def test_a_set_is_weighed_placed_finer_than_the_coarse_grid(scenario):
    """Two jammers off the coarse grid's nodes (3.1 and 2.7 m from the nearest), exact reports
    read at 0.3 dB, the set given 3.6 m and 1 dB off: each is placed again, finer, nearer
    than any node (measured: 0.3 and 0.8 m, 0.13 and 0.05 dB), and the set explains the
    reports better than either alone by more than BIC's penalty."""
    truth = RadioModel(scenario)
    xy = uniform_points(scenario, np.random.default_rng(0), 2000)
    jammers = [JammerParams(12.3, -7.9, 0.8, scenario.jammer.height_m),
               JammerParams(-31.6, 22.2, 1.0, scenario.jammer.height_m)]
    levels, no_jammer = truth.evaluate(xy, jammers).level, truth.evaluate(xy).level
    power_dbw = [10.0 * np.log10(jammer.power_w) + scenario.jammer.efficiency_db
                 for jammer in jammers]
    given = [(np.array([jammer.x + 3.0, jammer.y - 2.0]), power + 1.0)
             for jammer, power in zip(jammers, power_dbw, strict=True)]

    def placed(known):
        return placed_evidence(scenario, xy, levels, known, no_jammer_levels=no_jammer,
                               report_sigma_db=0.3)

    both, log_likelihood, penalty = placed(given)
    for (position, power), jammer, true_dbw in zip(both, jammers, power_dbw, strict=True):
        assert math.dist(position, (jammer.x, jammer.y)) <= 1.5  # the nearest node: 2.7 m
        assert abs(power - true_dbw) <= 0.3
    # Measured: 234 nats and more against a penalty of 10.3; the float32 sums of 2,000
    # reports round by under 1.4 nats (the test above).
    for index in range(2):
        assert log_likelihood - placed(given[index:index + 1])[1] > penalty


def test_one_jammer_counted_is_the_one_estimate_jammer_gives(scenario):
    truth = RadioModel(scenario)
    xy = uniform_points(scenario, np.random.default_rng(1), 1500)
    jammer = JammerParams(10.0, -20.0, 1.0, scenario.jammer.height_m)
    levels, no_jammer = truth.evaluate(xy, jammer).level, truth.evaluate(xy).level
    assert estimate_jammers(scenario, xy, levels, no_jammer_levels=no_jammer) == [
        estimate_jammer(scenario, xy, levels, no_jammer_levels=no_jammer)]
    assert estimate_jammers(scenario, xy[:10], levels[:10], no_jammer_levels=no_jammer[:10]) \
        is None  # too few to tell


def test_ten_seconds_of_four_flights_do_not_pin_a_jammer_down(shadowed):
    """4 UAVs, 10 s of straight flight (~100 reports each): the jammer's footprint is a broad
    dip of ~2 dB, which a few paths through shadowing cannot place. Measured: no estimate in
    30 settings (1 in 50 in icc2021's own realisation). The estimator must say so (None),
    not guess."""
    fits = fit_settings(shadowed, "flights")
    assert sum(e is None for e, _ in fits) >= SETTINGS - 2
    for estimate, jammer in fits:
        if estimate is not None and estimate.present:
            assert position_error(estimate, jammer) <= 3.0 * np.hypot(estimate.sd_x_m,
                                                                      estimate.sd_y_m)


def test_no_jammer_wins_when_there_is_none(shadowed):
    """Measured over 20 realisations: 19 no jammer, 1 undecided, none present."""
    outcomes = []
    for seed in range(5):
        rng = np.random.default_rng(100 + seed)
        scenario = world(shadowed, seed)
        xy = uniform_points(scenario, rng, 2000)
        levels, no_jammer = reports(scenario, None, xy, rng)
        outcomes.append(estimate_jammer(scenario, xy, levels, no_jammer_levels=no_jammer))
    assert not any(e is not None and e.present for e in outcomes)
    absent = [e for e in outcomes if e is not None]
    assert len(absent) >= 3
    assert all(e.x is None and e.power_w is None and e.log_likelihood_ratio < 4.0
               for e in absent)


def test_none_on_too_few_measurements(shadowed):
    rng = np.random.default_rng(7)
    jammer = JammerParams(0.0, 0.0, 1.0, shadowed.jammer.height_m)
    xy = uniform_points(shadowed, rng, 20)
    levels, no_jammer = reports(shadowed, jammer, xy, rng)
    assert estimate_jammer(shadowed, xy, levels, no_jammer_levels=no_jammer) is None


def test_none_on_measurements_far_from_the_jammer(shadowed):
    """Reports from one corner say nothing of a jammer in the opposite one: neither a jammer
    nor its absence can be claimed."""
    rng = np.random.default_rng(8)
    jammer = JammerParams(40.0, 40.0, 1.0, shadowed.jammer.height_m)
    xy = rng.uniform(-50.0, -20.0, size=(1500, 2))
    levels, no_jammer = reports(shadowed, jammer, xy, rng)
    assert estimate_jammer(shadowed, xy, levels, no_jammer_levels=no_jammer) is None


def test_rows_without_a_position_are_ignored(shadowed):
    rng = np.random.default_rng(9)
    jammer = JammerParams(-20.0, 10.0, 1.0, shadowed.jammer.height_m)
    xy = uniform_points(shadowed, rng, 1000)
    levels, no_jammer = reports(shadowed, jammer, xy, rng)
    padded = np.concatenate([xy, np.full((50, 2), np.nan)])
    with_gaps = estimate_jammer(shadowed, padded, np.concatenate([levels, np.zeros(50)]),
                                no_jammer_levels=np.concatenate([no_jammer, np.zeros(50)]))
    assert with_gaps == estimate_jammer(shadowed, xy, levels, no_jammer_levels=no_jammer)


# -- the shadowing's spread and the corrected map -----------------------------------------------
def test_the_spread_is_learned_from_the_no_jammer_map(scenario, shadowed):
    xy = uniform_points(scenario, np.random.default_rng(11), 4000)
    ideal = RadioModel(scenario, shadowed=False)
    assert fit_shadowing_sigma(ideal, xy, RadioModel(scenario).evaluate(xy).level) < 0.5
    world_levels = RadioModel(shadowed).evaluate(xy).level
    assert 2.5 <= fit_shadowing_sigma(ideal, xy, world_levels) <= 5.0


def grid_points(scenario: Scenario, spacing: float = 1.0) -> np.ndarray:
    area = scenario.area
    xs = np.arange(area.x_min, area.x_max + spacing / 2, spacing)
    ys = np.arange(area.y_min, area.y_max + spacing / 2, spacing)
    return np.stack(np.meshgrid(xs, ys), axis=-1)


def known(setting, scenario: Scenario, shift_m: float = 0.0, power_factor: float = 1.0):
    """An estimate of a Table I setting, off by ``shift_m`` in x and ``power_factor``."""
    return JammerEstimate(True, setting.x + shift_m, setting.y, setting.power_w * power_factor,
                          None, 1.0, 1.0, 1.0, 1000, 50.0)


def test_corrected_map_beats_the_outdated_one_in_the_shadowed_world(shadowed):
    """Over the whole area, given the world's no-jammer levels. Measured (0.5 m grid):
    outdated 86.0 / 86.8 / 87.7 / 91.9 %, corrected with the true jammer 88.2 / 89.7 / 90.4 /
    92.4 %, with one 6 m and 1.6x off within 0.2 points of that. Not 95 %: the jammer link's
    own shadowing moves the loss by ~0.6 dB, so even the world's exact no-jammer SINR less
    the ideal loss reaches only 92.5 / 93.3 / 95.1 / 95.5 %. Taking the ideal model's level
    where it says the jammer matters (min with the map) gives 80.6 / 82.8 / 85.3 / 88.3 %,
    worse than no correction: the ideal model agrees with this world on 61 % of the area."""
    truth = RadioModel(shadowed)
    points = grid_points(shadowed)
    for setting in TABLE_I_JAMMERS:
        jammed = truth.evaluate(points, JammerParams(*setting, shadowed.jammer.height_m)).level
        outdated = np.mean(truth.evaluate(points).level == jammed)
        for estimate in (known(setting, shadowed), known(setting, shadowed, 6.0, 1.6)):
            corrected = corrected_levels(shadowed, lambda xy: truth.evaluate(xy).level,
                                         estimate, points)
            assert corrected.shape == jammed.shape
            assert np.mean(corrected == jammed) >= max(outdated + 0.003, 0.87), setting


def test_a_map_is_read_near_a_level_edge_and_weighed_against_the_ideal_model(shadowed):
    """Hand-computed: a map that puts a share Phi(-1) of its reports below -3 dB reads the
    SINR at -3 + REPORT_SIGMA_DB dB, give or take MAP_READING_SD_DB; against the ideal
    model's prior the two are averaged by precision; a certain map reads nothing."""
    radio = RadioModel(shadowed, shadowed=False)
    edge = radio.level_edges_db[0]
    share = float(norm_cdf(-1.0))
    unsure = np.array([[share, 0.0, 1.0 - share]])
    mean, sd = prior_of_map(radio, np.array([edge]), 1e6, unsure)
    np.testing.assert_allclose(mean, edge + REPORT_SIGMA_DB, atol=1e-6)
    np.testing.assert_allclose(sd, MAP_READING_SD_DB, rtol=1e-6)
    mean, sd = prior_of_map(radio, np.array([edge]), MAP_READING_SD_DB, unsure)
    np.testing.assert_allclose(mean, edge + REPORT_SIGMA_DB / 2, atol=1e-9)
    np.testing.assert_allclose(sd, MAP_READING_SD_DB / np.sqrt(2.0), rtol=1e-9)
    mean, sd = prior_of_map(radio, np.array([4.0]), 2.5, np.array([[0.0, 0.0, 1.0]]))
    np.testing.assert_allclose([mean[0], sd[0]], [4.0, 2.5])


def test_a_map_of_report_shares_corrects_the_levels_a_jammer_moves(shadowed):
    """Given only the world's no-jammer level, the correction can hardly tell which points
    lie within the jammer's loss (2.3 dB at most) of a level's edge: the world's spread
    about the ideal model is wider. A map learned from noisy reports says more there, as
    its probabilities are the shares of reports on either side of the edge. Given the
    world's own shares (reports at REPORT_SIGMA_DB), the correction with the true jammer
    rights about twice as many of the points the jammer moves. Measured (1 m grid, Table
    I's 1 W settings), right of the points moved: 23 / 28 / 25 % from the levels, 50 / 48 /
    60 % from the shares; of the rest 99.0 / 99.2 / 99.3 % and 94.1 / 92.9 / 92.8 %: the
    shares err on the dark side near the jammer, which costs a detour, not a link."""
    truth = RadioModel(shadowed)
    points = grid_points(shadowed).reshape(-1, 2)
    quiet = truth.evaluate(points).level

    def shares(xy):
        return report_shares(truth, truth.evaluate(xy).sinr_db)

    for setting in TABLE_I_JAMMERS[:3]:
        jammed = truth.evaluate(points, JammerParams(*setting, shadowed.jammer.height_m)).level
        moved = jammed != quiet
        from_levels = corrected_levels(shadowed, lambda xy: truth.evaluate(xy).level,
                                       known(setting, shadowed), points)
        from_shares = corrected_levels(shadowed, shares, known(setting, shadowed), points)
        righted = np.mean(from_shares[moved] == jammed[moved])
        assert righted >= np.mean(from_levels[moved] == jammed[moved]) + 0.15, setting
        assert np.mean(from_shares[~moved] == jammed[~moved]) >= 0.9, setting


def test_corrected_map_is_exact_in_the_ideal_world(scenario):
    ideal = RadioModel(scenario)
    points = grid_points(scenario)
    for setting in TABLE_I_JAMMERS:
        jammed = ideal.evaluate(points, JammerParams(*setting, scenario.jammer.height_m)).level
        corrected = corrected_levels(scenario, lambda xy: ideal.evaluate(xy).level,
                                     known(setting, scenario), points)
        assert np.mean(corrected == jammed) >= 0.995


def test_a_set_of_jammers_corrects_the_map_with_their_sum(scenario):
    """Two Table I jammers as one estimate: the ideal world's map corrected with the set is
    that world with both jammers, where either alone leaves far more of it wrong."""
    ideal = RadioModel(scenario)
    points = grid_points(scenario)
    first, second = TABLE_I_JAMMERS[0], TABLE_I_JAMMERS[2]
    jammed = ideal.evaluate(points, [JammerParams(*s, scenario.jammer.height_m)
                                     for s in (first, second)]).level
    quiet = lambda xy: ideal.evaluate(xy).level  # noqa: E731
    both = estimated_set([known(first, scenario), known(second, scenario)])
    assert np.mean(corrected_levels(scenario, quiet, both, points) == jammed) >= 0.995
    alone = corrected_levels(scenario, quiet, known(first, scenario), points)
    assert np.mean(alone == jammed) <= 0.98


def test_without_a_jammer_the_no_jammer_map_stands(scenario):
    points = grid_points(scenario, 5.0)
    base = RadioModel(scenario).evaluate(points).level
    absent = JammerEstimate(False, None, None, None, None, None, None, None, 500, 0.3)
    corrected = corrected_levels(scenario, lambda xy: RadioModel(scenario).evaluate(xy).level,
                                 absent, points)
    np.testing.assert_array_equal(corrected, base)


def test_hypotheses_of_a_provisional_map_surround_the_jammer_at_expected_powers():
    """Idealized world, 300 uniform reports: a jammer of Table I shows, and the hypotheses
    (weights summing to 1, powers within the training range) hold it within their spread;
    with no jammer there are none."""
    scenario = load_scenario("icc2021")
    rng = np.random.default_rng(3)
    xy = uniform_points(scenario, rng, 300)
    setting = TABLE_I_JAMMERS[0]
    jammer = JammerParams(setting.x, setting.y, setting.power_w, scenario.jammer.height_m)
    levels, no_jammer = reports(scenario, jammer, xy, rng)
    found = jammer_hypotheses(scenario, xy, levels, no_jammer_levels=no_jammer)
    assert found is not None and found.weights.sum() == pytest.approx(1.0)
    low, high = scenario.training.jammer_power_range_w
    places = np.array([(e.x, e.y) for e in found.estimates])
    assert all(low * 0.999 <= e.power_w <= high * 1.001 for e in found.estimates)
    centre = found.weights @ places
    assert np.hypot(*(centre - (setting.x, setting.y))) <= 10.0
    quiet, no_jammer = reports(scenario, None, xy, rng)
    assert jammer_hypotheses(scenario, xy, quiet, no_jammer_levels=no_jammer) is None


def test_locating_once_gives_what_the_estimate_and_the_hypotheses_give_apart():
    """``locate_jammer`` shares one coarse search between the two: the same estimate, and the
    same hypotheses when no estimate converges (few reports) and none when one does."""
    scenario = load_scenario("icc2021")
    rng = np.random.default_rng(4)
    setting = TABLE_I_JAMMERS[1]
    jammer = JammerParams(setting.x, setting.y, setting.power_w, scenario.jammer.height_m)
    xy = uniform_points(scenario, rng, 1500)
    levels, no_jammer = reports(scenario, jammer, xy, rng)
    outcomes = set()
    for n in (60, 1500):
        fit = locate_jammer(scenario, xy[:n], levels[:n], no_jammer_levels=no_jammer[:n])
        apart = estimate_jammer(scenario, xy[:n], levels[:n], no_jammer_levels=no_jammer[:n])
        assert fit.estimate == apart
        hypotheses = jammer_hypotheses(scenario, xy[:n], levels[:n],
                                       no_jammer_levels=no_jammer[:n])
        if apart is None:
            assert fit.hypotheses.estimates == hypotheses.estimates
            np.testing.assert_array_equal(fit.hypotheses.weights, hypotheses.weights)
        else:
            assert fit.hypotheses is None
        outcomes.add(apart is None)
    assert outcomes == {True, False}


# -- the ideal model vouching for reports -------------------------------------------------------
def test_locating_several_jammers_gives_them_as_one_set(scenario):
    """Where the reports show two jammers, ``locate_jammer``'s estimate is the set
    ``estimate_jammers`` counts, the first with the other beside it, and no hypotheses."""
    truth = RadioModel(scenario)
    xy = uniform_points(scenario, np.random.default_rng(0), 2000)
    placed = [JammerParams(-25.0, 15.0, 1.0, scenario.jammer.height_m),
              JammerParams(25.0, -10.0, 1.0, scenario.jammer.height_m)]
    levels, no_jammer = truth.evaluate(xy, placed).level, truth.evaluate(xy).level
    fit = locate_jammer(scenario, xy, levels, no_jammer_levels=no_jammer)
    counted = estimate_jammers(scenario, xy, levels, no_jammer_levels=no_jammer)
    assert fit.hypotheses is None and len(counted) == 2
    assert list(fit.estimate.members) == counted
    assert fit.estimate.others == (counted[1],)


def test_the_jammers_are_counted_before_they_are_placed(scenario):
    """Reports along one straight path, which passes 6.1 m from each of two 1 W jammers, show
    both but place neither: from one path a jammer's side is a mirror image and its distance
    trades against its power, so each posterior spreads across the path, past the 10 m a
    converged estimate allows. The fit counts two, and one where the first is alone. Exact
    reports read at 0.3 dB, as the ideal world's cloud reads them (its spread is narrower
    still)."""
    truth = RadioModel(scenario)
    along = np.linspace(-50.0, 50.0, 300)
    xy = np.stack([along, 2.5 - 0.25 * along], axis=1)  # through (-25, 8.75) and (25, -3.75)
    placed = [JammerParams(-25.0, 15.0, 1.0, scenario.jammer.height_m),
              JammerParams(25.0, -10.0, 1.0, scenario.jammer.height_m)]
    no_jammer = truth.evaluate(xy).level
    for jammers in (placed, placed[:1]):
        fit = locate_jammer(scenario, xy, truth.evaluate(xy, jammers).level,
                            no_jammer_levels=no_jammer, report_sigma_db=0.3)
        assert fit.estimate is None and fit.count == len(jammers)
    # With no jammer the path rules none out where it never passed: no count yet. Reports
    # over the whole area rule one out everywhere: none.
    assert locate_jammer(scenario, xy, no_jammer, no_jammer_levels=no_jammer,
                         report_sigma_db=0.3).count is None
    everywhere = uniform_points(scenario, np.random.default_rng(0), 2000)
    quiet = truth.evaluate(everywhere).level
    assert locate_jammer(scenario, everywhere, quiet, no_jammer_levels=quiet,
                         report_sigma_db=0.3).count == 0


def test_the_ideal_model_vouches_only_where_the_survey_map_keeps_to_it(scenario, shadowed):
    """Its spread: the survey map's departure and the receivers' noise, added in quadrature
    (0.3 and 0.4 dB give 0.5 dB), and none at all once over half icc2021's narrowest band,
    (-2.21) - (-3.0) = 0.79 dB."""
    assert ideal_model_spread_db(scenario, 0.3) == pytest.approx(0.3)
    assert ideal_model_spread_db(scenario, 0.39) == pytest.approx(0.39)
    assert ideal_model_spread_db(scenario, 0.4) is None
    noisy = variant(scenario, uav={"measurement_noise_db": 0.4})
    assert ideal_model_spread_db(noisy, 0.0) is None  # 0.4 dB > 0.395 dB
    assert ideal_model_spread_db(variant(scenario, uav={"measurement_noise_db": 0.3}),
                                 0.0) == pytest.approx(0.3)
    assert ideal_model_spread_db(shadowed, 6.3) is None


def test_the_ideal_models_probabilities_of_the_levels(scenario):
    """Over the three levels they sum to one; with a spread of 0.01 dB the model's own level
    is near certain wherever the SINR is 0.05 dB (5 sds) or more from an edge; a jammer
    estimated right there makes the no-jammer level improbable; a point that cannot be
    placed gets nothing."""
    rng = np.random.default_rng(0)
    xy = uniform_points(scenario, rng, 400)
    radio = RadioModel(scenario, shadowed=False)
    quiet = radio.evaluate(xy)
    each = ideal_level_probabilities(scenario, xy, None, 0.01)
    assert each.shape == (400, scenario.channel.level_count)
    np.testing.assert_allclose(each.sum(axis=1), 1.0, atol=1e-9)
    clear = np.abs(quiet.sinr_db[:, None] - radio.level_edges_db[None]).min(axis=1) >= 0.05
    assert clear.mean() > 0.9
    assert (each[clear, quiet.level[clear]] > 0.999).all()
    at = np.array([[10.0, -20.0]])
    under = JammerEstimate(present=True, x=10.0, y=-20.0, power_w=1.0,
                           effective_power_dbm=10.0, sd_x_m=1.0, sd_y_m=1.0, sd_power_db=0.5,
                           measurements=1000, log_likelihood_ratio=50.0)
    level_here = int(radio.evaluate(at).level[0])
    assert ideal_level_probabilities(scenario, at, None, 0.01)[0, level_here] > 0.999
    assert ideal_level_probabilities(scenario, at, under, 0.01)[0, level_here] < 0.001
    assert (ideal_level_probabilities(scenario, np.array([[np.nan, np.nan]]), None,
                                      0.01) == 0.0).all()


def test_an_estimates_sigma_points_share_its_mean_and_covariance():
    estimate = JammerEstimate(True, 3.0, -7.0, 0.8, 9.0, 4.0, 2.0, 1.5, 500, 30.0, 3.0)
    hypotheses = posterior_hypotheses(estimate)
    xy = np.array([[h.x, h.y] for h in hypotheses.estimates])
    power_db = 10.0 * np.log10([h.power_w for h in hypotheses.estimates])
    weights = hypotheses.weights
    # float64 sums of six points round near 1e-15 relative: pytest.approx's 1e-6 is wide of it,
    # and summation order cannot reach it on any CPU.
    assert weights.sum() == pytest.approx(1.0)
    assert weights @ xy == pytest.approx([3.0, -7.0])
    centred = xy - (3.0, -7.0)
    covariance = (centred * weights[:, None]).T @ centred
    assert covariance == pytest.approx(np.array([[16.0, 3.0], [3.0, 4.0]]))
    assert weights @ power_db == pytest.approx(10.0 * np.log10(0.8))
    assert weights @ (power_db - 10.0 * np.log10(0.8)) ** 2 == pytest.approx(1.5**2)



def test_the_sigma_points_of_a_set_move_one_jammer_at_a_time():
    """Two jammers: six hypotheses each, every one with the other jammer exactly where it
    was estimated, and each jammer's own points sharing its mean."""
    first = JammerEstimate(True, 3.0, -7.0, 0.8, 9.0, 4.0, 2.0, 1.5, 500, 30.0, 3.0)
    second = JammerEstimate(True, -20.0, 12.0, 0.5, 7.0, 1.0, 3.0, 0.5, 500, 20.0, 0.0)
    hypotheses = posterior_hypotheses(estimated_set([first, second]))
    assert len(hypotheses.estimates) == 12
    for moved, still in ((first, second), (second, first)):
        own = [h for h in hypotheses.estimates if still in h.members]
        assert len(own) == 6
        points = [next(m for m in h.members if m != still) for h in own]
        # A float64 mean of six points rounds near 1e-15 relative; approx's 1e-6 is wide of it.
        assert np.mean([(p.x, p.y) for p in points], axis=0) == pytest.approx([moved.x, moved.y])


def test_an_estimate_of_several_jammers_survives_its_record():
    """What a map's card and an event hold (plain JSON fields) reads back as the set."""
    import json

    first = JammerEstimate(True, 3.0, -7.0, 0.8, 9.0, 4.0, 2.0, 1.5, 500, 30.0, 3.0)
    second = JammerEstimate(True, -20.0, 12.0, 0.5, 7.0, 1.0, 3.0, 0.5, 500, 20.0, 0.0)
    both = estimated_set([first, second])
    record = json.loads(json.dumps(both.record()))
    assert record["others"][0]["x"] == -20.0
    assert JammerEstimate.of_record(record) == both
    assert JammerEstimate.of_record(first.record()) == first
    assert both.members == (first, second) and first.members == (first,)
    assert JammerEstimate(False, None, None, None, None, None, None, None, 10, 0.0).members == ()


def test_an_estimate_of_no_jammer_is_its_one_hypothesis():
    """The uploads can say there is no jammer; weighed with its uncertainty that is still
    no jammer, the one hypothesis, and reports weigh nothing for or against it."""
    absent = JammerEstimate(False, None, None, None, None, None, None, None, 10, -3.0)
    hypotheses = posterior_hypotheses(absent)
    assert hypotheses.estimates == [absent] and hypotheses.weights.tolist() == [1.0]

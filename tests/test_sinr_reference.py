"""The cloud's use of dB reports: the no-jammer reference, the detector's test of a loss, the
likelihood of a dB report in the jammer estimate.

Every value here is float64 arithmetic on a few terms, compared with a hand or scipy value at
1e-12 (absolute, on values of order 1) or 1e-9 (relative), a thousand times float64's rounding
of such sums and more; the estimate's tables are compared at their own resolution (below)."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
from scipy.stats import norm

from cloud_service.change_detection import ChangeDetector
from cloud_service.estimated_jammer import NO_JAMMER
from cloud_service.jammer_estimation import estimate_jammer
from cloud_service.map_correction import sinr_report_probabilities
from cloud_service.no_jammer_belief import SinrBelief
from cloud_service.report_likelihood import OUTLIER_SHARE, ReportTables
from cloud_service.sinr_reference import SinrReference, shift_evidence
from shared.radio import JammerParams, RadioModel
from shared.scenario import load_scenario


@pytest.fixture(scope="module")
def reporting():
    """The shadowed world with receivers that report the SINR."""
    return load_scenario("icc2021-shadowed").changed({"uav.report": "db"})


def test_the_reference_averages_each_cells_reports_once_they_are_old_enough(reporting):
    reference = SinrReference(reporting)
    cell = reporting.online_map.reference_cell_m
    here = np.array([[0.25, 0.25], [0.5, 0.75], [0.1, 0.9], [10.2, 3.3], [80.0, 0.0]])
    assert cell == 1.0 and reporting.online_map.reference_delay_s == 10.0
    reference.offer(here, np.array([-2.0, -3.0, -4.0, 6.5, 1.0]), np.array([0, 0, 0, 0, 0.0]))
    reference.offer(here[:1], np.array([np.nan]), np.array([1.0]))  # a level report
    reference.commit(9.0)
    assert reference.reports == 0  # not old enough yet
    assert np.isnan(reference.at(here).mean_db).all()
    reference.commit(10.0)
    assert reference.reports == 4  # the fifth lies outside the area
    belief = reference.at(np.array([[0.9, 0.1], [10.9, 3.9], [1.5, 0.5], [80.0, 0.0]]))
    np.testing.assert_allclose(belief.mean_db[:2], [-3.0, 6.5], rtol=0, atol=1e-12)
    assert np.isnan(belief.mean_db[2:]).all() and np.isnan(belief.sd_db[2:]).all()
    # The pooled spread: one cell of three reports, sd 1 dB about their mean; the roughness
    # is what it holds beyond the receiver's 1 dB of noise: none.
    assert reference.spread_db() == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(belief.sd_db[:2], [math.sqrt(1 / 3), 1.0], rtol=1e-12)


def test_a_change_drops_the_reports_still_waiting_since_it_began(reporting):
    reference = SinrReference(reporting)
    spot = np.array([[5.0, 5.0]])
    for t in range(20):
        reference.offer(spot, np.array([float(t)]), np.array([float(t)]))
    reference.discard_since(12.0)
    reference.commit(100.0)
    assert reference.reports == 12
    assert reference.at(spot).mean_db[0] == pytest.approx(np.mean(np.arange(12.0)), abs=1e-12)


def test_the_reports_judged_jammed_leave_the_reference_and_the_queue_to_enter_it(reporting):
    """Cells are judged by their mean at their centre, waiting reports by their own SINR at
    their cell's centre; the rest stays, the waiting ones in the order they were offered."""
    reference = SinrReference(reporting)
    spots = np.array([[5.5, 5.5], [-20.5, 30.5], [5.5, 5.5], [-20.5, 30.5]])
    reference.offer(spots[:2], np.array([1.0, 2.0]), np.array([0.0, 0.0]))
    reference.commit(10.0)
    reference.offer(spots, np.array([-8.0, 4.0, 5.0, -6.0]), np.array([5.0, 5.0, 5.0, 6.0]))
    judged = []

    def jammed(xy, sinr_db):
        judged.append((xy.copy(), sinr_db.copy()))
        return (xy[:, 0] > 0.0) | (sinr_db < -5.0)  # east of x = 0, or below -5 dB

    reference.discard_jammed(jammed)
    # Every value below is a whole or half number, exact in float64 through these sums and
    # one division by a count: the tolerances only spare an exact comparison.
    (cells_xy, means), (waiting_xy, waiting_db) = judged
    np.testing.assert_allclose(cells_xy, [[5.5, 5.5], [-20.5, 30.5]], atol=1e-12)
    np.testing.assert_allclose(means, [1.0, 2.0], atol=1e-12)
    np.testing.assert_allclose(waiting_xy, spots, atol=1e-12)
    np.testing.assert_allclose(waiting_db, [-8.0, 4.0, 5.0, -6.0], atol=1e-12)
    assert reference.reports == 1
    reference.commit(100.0)
    belief = reference.at(spots[:2])
    assert np.isnan(belief.mean_db[0]) and reference.reports == 2
    assert belief.mean_db[1] == pytest.approx(3.0, abs=1e-12)  # (2 + 4) / 2


def test_shift_evidence_is_the_gaussian_log_likelihood_ratio_capped_for_outliers():
    reference = SinrBelief(np.array([0.0, 0.0, 0.0, np.nan]), np.array([0.5, 0.5, 0.5, 0.5]))
    reported = np.array([-1.0, 1.0, -40.0, 0.0])
    evidence = shift_evidence(reference, reported, 1.0, 1.0)
    sd = math.sqrt(1.25)
    expected = norm.logpdf(-1.0, -1.0, sd) - norm.logpdf(-1.0, 0.0, sd)
    assert evidence[0] == pytest.approx(expected, abs=1e-12)
    assert evidence[1] == pytest.approx(norm.logpdf(1.0, -1.0, sd) - norm.logpdf(1.0, 0.0, sd),
                                        abs=1e-12)
    assert evidence[2] == pytest.approx(-math.log(OUTLIER_SHARE), abs=1e-12)
    assert np.isnan(evidence[3])


def test_the_detector_weighs_a_db_report_by_its_evidence_and_a_level_report_as_before():
    detector = ChangeDetector(levels=3, threshold=5.0, floor=0.05)
    probability = np.full(4, 1.0)  # the map expected every level it was given
    check = detector.update(probability, ["a"] * 4, np.arange(4.0),
                            np.array([np.nan, 2.0, 2.0, np.nan]))
    # log(1/3) from 0 stays at 0 (the excursion starts at the next report), then 2 + 2,
    # then log(1/3) again.
    assert check.statistic == pytest.approx(4.0 + math.log(1 / 3), abs=1e-12)
    assert not check.fired
    check = detector.update(probability[:2], ["a"] * 2, np.array([4.0, 5.0]),
                            np.array([3.0, 3.0]))
    assert check.fired and check.t == 4.0 and detector.change_start == 1.0


def test_a_db_reports_likelihood_is_its_report_steps_interval(reporting):
    """The estimate's table of a dB report against the normal interval probability, and
    the withdrawal's probability of one, by scipy, with the outlier share."""
    radio = RadioModel(reporting, shadowed=False)
    tables = ReportTables(radio.level_edges_db, np.array([1.3, 2.0]), OUTLIER_SHARE, 0.5)
    believed = np.array([-1.0, 3.0, 10.0])
    reported = np.array([-2.5, 3.0, -30.0])
    rows = np.array([0, 1, 1])
    got = tables.log_probability(believed, np.zeros(3, dtype=np.int64), rows, reported)
    sd = np.array([1.3, 2.0, 2.0])
    interval = norm.cdf((reported + 0.25 - believed) / sd) - norm.cdf(
        (reported - 0.25 - believed) / sd)
    expected = np.log((1 - OUTLIER_SHARE) * interval + OUTLIER_SHARE * 0.5 / 40.0)
    # The table reads the offset to its 0.05 dB step, so to 0.025 dB: the log of a 0.5 dB
    # interval's probability changes by at most |offset| / sd^2 + 1 / sd per dB (the normal
    # density's log-slope, plus the interval's width over the sd), 1.5 / 1.3^2 + 1 / 1.3 =
    # 1.66 here, so by 0.042 at most over 0.025 dB; the third report sits on the outlier floor.
    np.testing.assert_allclose(got, expected, atol=0.042)
    # A level report reads the level table.
    # A level report reads the level table, at a believed SINR on its 0.05 dB grid (10 dB):
    # the table's value there is the band probability itself, but for float64 rounding.
    levels = tables.log_probability(believed, np.array([2, 2, 0]), rows, np.full(3, np.nan))
    assert levels[2] == pytest.approx(math.log((1 - OUTLIER_SHARE) * norm.cdf((-3.0 - 10) / 2)
                                               + OUTLIER_SHARE / 3), abs=1e-9)
    xy = np.array([[0.0, 0.0], [20.0, 5.0]])
    belief = SinrBelief(np.array([1.0, 4.0]), np.array([0.5, 0.5]))
    probability = sinr_report_probabilities(reporting, xy, np.array([0.5, 4.0]), NO_JAMMER,
                                            belief, 1.0)
    spread = math.hypot(0.5, 1.0)
    interval = (norm.cdf((np.array([0.75, 4.25]) - [1.0, 4.0]) / spread)
                - norm.cdf((np.array([0.25, 3.75]) - [1.0, 4.0]) / spread))
    np.testing.assert_allclose(probability, (1 - OUTLIER_SHARE) * interval
                               + OUTLIER_SHARE * 0.5 / 40.0, rtol=1e-9)


def test_a_spread_that_rounds_to_nothing_reads_a_report_by_its_band_alone(reporting):
    """A spread under half the tables' step (the exact receivers' 0.02 dB) is read as none: a
    report of the level whose band holds the SINR has probability 1 but for the outlier
    share, any other the outlier floor; a dB report, 1 within its 0.5 dB step. Built
    without a warning."""
    radio = RadioModel(reporting, shadowed=False)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        tables = ReportTables(radio.level_edges_db, np.array([0.02]), OUTLIER_SHARE, 0.5)
    rows = np.zeros(3, dtype=np.int64)
    believed = np.array([-10.0, -2.6, 5.0])  # in the bands of levels 0, 1 and 2
    # The tables and these expectations are the same float64 logs of the same shares: 1e-12
    # relative is a thousand times their rounding (a few ulps of 2.2e-16).
    inside = math.log(1 - OUTLIER_SHARE + OUTLIER_SHARE / 3)
    floor = math.log(OUTLIER_SHARE / 3)
    for level in range(3):
        got = tables.log_probability(believed, np.full(3, level), rows)
        np.testing.assert_allclose(got, np.where(np.arange(3) == level, inside, floor),
                                   rtol=1e-12)
    got = tables.log_probability(believed, rows, rows, believed + np.array([0.1, -0.1, 2.0]))
    np.testing.assert_allclose(got, [math.log(1 - OUTLIER_SHARE + OUTLIER_SHARE * 0.5 / 40.0)] * 2
                               + [math.log(OUTLIER_SHARE * 0.5 / 40.0)], rtol=1e-12)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_db_reports_place_a_jammer_the_levels_of_the_same_reports_cannot(seed):
    """In the idealized world the reports' SINRs see the jammer's loss wherever it is more
    than a few tenths of a dB; their levels only where it moves a level edge. From the same
    150 noisy reports, the dB estimate converges within a few metres (its sd at most 10 m,
    the estimate's rule), the levels' does not."""
    scenario = load_scenario("icc2021").changed({"uav.report": "db",
                                                 "uav.measurement_noise_db": 0.5})
    truth = RadioModel(scenario)
    jammer = JammerParams(12.0, -8.0, 0.5, scenario.jammer.height_m)
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-45, 45, (150, 2))
    reports = truth.measured_reports(truth.evaluate(xy, jammer).sinr_db, rng)
    by_db = estimate_jammer(scenario, xy, reports.level, reported_db=reports.sinr_db,
                            shadowing_sigma_db=0.05)
    by_level = estimate_jammer(scenario, xy, reports.level, shadowing_sigma_db=0.05)
    assert by_db is not None and by_db.present
    assert math.hypot(by_db.x - 12.0, by_db.y + 8.0) < 2 * max(by_db.sd_x_m, by_db.sd_y_m)
    assert by_level is None

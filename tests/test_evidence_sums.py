"""The jammer search in the compiled core (planning/_evidence.pyx) against the numpy gathers it
replaces: the measurements' tables read bit for bit alike, the same log-likelihood ratios
within the reference's float32 rounding, and so the same estimate."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from cloud_service.jammer_estimation import estimate_jammer
from cloud_service.jammer_evidence import JammerEvidence, Reports, independence_weights
from cloud_service.no_jammer_belief import sinr_beliefs
from cloud_service.report_likelihood import ReportTables
from planning import PLANNER_VARIABLE
from planning.compiled import compiled_module
from shared.radio import JammerParams, RadioModel
from shared.scenario import load_scenario
from tests import float32_bounds as bounds


@pytest.fixture(scope="module")
def scenario():
    return load_scenario("icc2021")


def uploads(scenario, count: int, seed: int):
    """Positions over the area and the levels an exact receiver reports there under a 1 W
    jammer at (10, -20)."""
    rng = np.random.default_rng(seed)
    area = scenario.area
    xy = np.column_stack([rng.uniform(area.x_min, area.x_max, count),
                          rng.uniform(area.y_min, area.y_max, count)])
    jammer = JammerParams(10.0, -20.0, 1.0, scenario.jammer.height_m)
    return xy, RadioModel(scenario).evaluate(xy, jammer).level


def evidence_of(scenario, xy, levels) -> JammerEvidence:
    radio = RadioModel(scenario, shadowed=False)
    return JammerEvidence(radio, scenario.jammer.height_m, Reports.of(scenario, xy, levels),
                          independence_weights(xy, 3.0), sinr_beliefs(radio, xy, None, 1.0),
                          1.2, 0.01, 30.0)


@pytest.mark.parametrize("count", [1, 37, 2500])
def test_the_sums_agree_with_the_gather_within_its_float32_rounding(scenario, monkeypatch,
                                                                    count):
    xy, levels = uploads(scenario, count, count)
    evidence = evidence_of(scenario, xy, levels)
    rng = np.random.default_rng(7)
    positions = rng.uniform(-60.0, 60.0, (300, 2))
    powers = np.linspace(-30.0, 0.0, 31)
    monkeypatch.setenv(PLANNER_VARIABLE, "compiled")
    compiled = evidence.log_likelihood_ratios(positions, powers)
    monkeypatch.setenv(PLANNER_VARIABLE, "reference")
    reference = evidence.log_likelihood_ratios(positions, powers)
    # The reference adds float32 entries in float32, in any order within gamma(n) of the sum
    # of their magnitudes (read with |entries| through the same gather); the compiled sums add
    # in float64, and both then subtract the no-jammer term in float64. The two work out each
    # path gain in their own order (log10, or glibc's vector log over ln 10: within a few
    # 1e-13 dB), which picks another entry only where a gain lies that near a tie between two
    # entries: about one chance in 1e6 over these 2,500 x 300 gains.
    magnitudes = copy.copy(evidence)
    magnitudes.table, magnitudes.no_jammer = np.abs(evidence.table), 0.0
    magnitude = magnitudes.log_likelihood_ratios(positions, powers)
    allowed = bounds.gamma(count) * magnitude * (1 + bounds.gamma(count)) \
        + 4 * np.finfo(np.float64).eps * (np.abs(reference) + abs(evidence.no_jammer))
    assert np.all(np.abs(compiled - reference) <= allowed)
    assert np.ptp(reference) > 1.0  # the hypotheses differ: a wrong entry would show


def test_an_estimate_is_the_same_either_way(scenario, monkeypatch):
    xy, levels = uploads(scenario, 3000, 1)
    found = {}
    for planner in ("compiled", "reference"):
        monkeypatch.setenv(PLANNER_VARIABLE, planner)
        found[planner] = estimate_jammer(scenario, xy, levels)
    compiled, reference = found["compiled"], found["reference"]
    assert compiled.present and reference.present
    assert abs(compiled.x - 10.0) < 3 and abs(compiled.y + 20.0) < 3
    # Not a float32 bound: the estimate is the posterior's moments over the search's grids,
    # weighted by exp(LLR), and each LLR moves by no more than the first test bounds. "The same
    # estimate" is then one no reader of it could tell apart: a thousandth of its own spread,
    # in position and in power, where one wrong table entry per upload moves it by far more.
    assert np.hypot(compiled.x - reference.x, compiled.y - reference.y) \
        < 1e-3 * np.hypot(compiled.sd_x_m, compiled.sd_y_m)
    assert abs(10 * np.log10(compiled.power_w / reference.power_w)) < 1e-3 * compiled.sd_power_db


def test_each_measurements_entry_is_its_path_gain_in_steps_and_none_beyond_the_table():
    """Hand-worked: a hypothesis at the origin, measurements at (3, 4) and (0, 0), a gap of
    sqrt(75) m, 10 dB a decade, offsets of 25 dB and steps of 1 dB: squared distances 100 and
    75, gains 25 - 20 = 5 and 25 - 18.75 = 6.25 steps, so entries 5 and 6 of rows 0 and 1;
    offsets far above and below the tables clip to their last and first entries."""
    add = compiled_module("_evidence").add_hypothesis_entries
    table = np.arange(20, dtype=np.float32)  # two rows of ten: entry k of row i is 10 i + k
    origin, xy = np.zeros((1, 2)), np.array([[3.0, 4.0], [0.0, 0.0]])
    offsets = np.array([0, 2], dtype=np.int32)

    def summed(offset_db, last_first=7):
        out = np.zeros((1, 2))
        add(origin, xy, np.asarray(offset_db, dtype=np.float64), 10.0, 75.0, 1.0, 10,
            last_first, offsets, table, out)
        return out.tolist()

    assert summed([25.0, 25.0]) == [[5.0 + 16.0, 7.0 + 18.0]]
    assert summed([1e6, -1e6]) == [[7.0 + 10.0, 9.0 + 12.0]]
    with pytest.raises(ValueError, match="beyond the table"):
        summed([25.0, 25.0], last_first=8)  # row 1's entry 8 + 2 is the table's 21st
    with pytest.raises(ValueError, match="out of shape"):
        add(origin, xy, np.zeros(2), 10.0, 75.0, 1.0, 10, 7, offsets, table, np.zeros((2, 2)))


@pytest.mark.parametrize("step_db", [None, 0.5])
@pytest.mark.parametrize("each_its_own_loss", [False, True])
def test_the_report_tables_are_read_bit_for_bit_as_numpy_reads_them(monkeypatch, step_db,
                                                                    each_its_own_loss):
    """The same arithmetic in the same order: every entry equal, SINRs beyond the tables'
    range (clipped to their ends) and half-step ties among them."""
    rng = np.random.default_rng(11)
    count, columns = 400, 250
    tables = ReportTables(np.array([-3.0, -2.21]), rng.uniform(0.3, 3.0, count), 0.01, step_db)
    believed = rng.normal(0.0, 15.0, count)
    # Beyond the tables, at half-step ties, and beyond what an int64 index holds (numpy's cast
    # gives int64's least there, clipped to the table's first entry).
    believed[:9] = [-200.0, 200.0, -60.025, 39.975, 0.0, -2.21, 1e300, -1e300, np.nan]
    loss = (rng.uniform(0.0, 40.0, (count, columns)) if each_its_own_loss
            else np.linspace(0.0, 40.0, columns))
    levels = rng.integers(0, 3, count)
    reported = np.where(rng.random(count) < 0.5, np.round(rng.normal(0.0, 15.0, count) / 0.5)
                        * 0.5, np.nan)
    weights = rng.uniform(0.05, 1.0, count)
    read = {}
    for planner in ("compiled", "reference"):
        monkeypatch.setenv(PLANNER_VARIABLE, planner)
        with np.errstate(invalid="ignore"):
            read[planner] = tables.weighted_tables(believed, loss, levels, reported, weights)
    assert read["compiled"].dtype == read["reference"].dtype == np.float32
    assert read["compiled"].shape == (count, columns)
    np.testing.assert_array_equal(read["compiled"].view(np.int32),
                                  read["reference"].view(np.int32))
    assert np.ptp(read["reference"]) > 1.0  # entries differ: a wrong index would show


def test_a_table_row_beyond_the_tables_is_refused():
    read = compiled_module("_evidence").weighted_report_tables
    one, none = np.zeros(1), np.full(1, np.nan)
    arguments = dict(believed_db=one, loss_db=np.zeros((1, 3)), level_rows=np.array([1]),
                     level_values=np.arange(4.0), sinr_count=2, sinr_low_db=0.0,
                     sinr_step_db=1.0, reported_db=none, db_rows=np.array([0]),
                     db_values=one, offset_count=1, offset_range_db=0.0, weights=np.ones(1),
                     out=np.zeros((1, 3), dtype=np.float32))
    read(*arguments.values())
    # Row 1 of the level values, SINRs 0, 0 and 0 read at entry 0: value 2.
    assert arguments["out"].tolist() == [[2.0, 2.0, 2.0]]
    with pytest.raises(ValueError, match="beyond its table"):
        read(*{**arguments, "level_rows": np.array([2])}.values())
    with pytest.raises(ValueError, match="for 1 measurements"):
        read(*{**arguments, "weights": np.ones(2)}.values())

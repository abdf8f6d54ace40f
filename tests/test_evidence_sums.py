"""The jammer search's sums in the compiled core (planning/_evidence.pyx) against the numpy
gather they replace: the same log-likelihood ratios within the reference's float32 rounding,
and so the same estimate."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from cloud_service.jammer_estimation import estimate_jammer
from cloud_service.jammer_evidence import JammerEvidence, Reports, independence_weights
from cloud_service.no_jammer_belief import sinr_beliefs
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
    # in float64, and both then subtract the no-jammer term in float64.
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


def test_an_entry_beyond_the_table_is_refused():
    add = compiled_module("_evidence").add_table_entries
    table = np.zeros(10, dtype=np.float32)
    out = np.zeros((1, 2))
    with pytest.raises(ValueError, match="beyond the table"):
        add(np.array([[8]], dtype=np.int32), np.array([0, 2], dtype=np.int32), table, out)
    with pytest.raises(ValueError, match="out of shape"):
        add(np.array([[0]], dtype=np.int32), np.array([0], dtype=np.int32), table, out)
    add(np.array([[3], [4]], dtype=np.int32), np.array([0, 5], dtype=np.int32),
        np.arange(10, dtype=np.float32), out)
    assert out.tolist() == [[3.0 + 4.0, 8.0 + 9.0]]

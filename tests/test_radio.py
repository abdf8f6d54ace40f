"""Eq. (1)-(5) against hand computation and physical properties."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from shared.radio import JammerParams, RadioModel
from shared.scenario import load_scenario
from tests.conftest import variant

coordinate = st.floats(-50, 50, allow_nan=False)


def reference_sinr_db(scenario, x, y, jammer=None, more_jammers=()):
    """Eq. (1)-(5) written out term by term, one GBS and one jammer at a time (paper's
    readings); the jammers' interference powers add up in Eq. (3)'s denominator."""
    gbs, channel = scenario.gbs, scenario.channel
    hv, hb, alpha = scenario.uav.altitude_m, gbs.height_m, channel.path_loss_exponent
    powers = []
    for bx, by in gbs.positions:
        d = math.hypot(x - bx, y - by)
        angle = math.degrees(math.atan2(hb - hv, d))
        g_b = 10 ** (-min(1.2 * ((angle - gbs.tilt_deg) / gbs.beamwidth_3db_deg) ** 2,
                          gbs.max_attenuation_db / 10))
        g_v = (hv - hb) / math.sqrt(d**2 + (hv - hb) ** 2)
        loss = (d**2 + (hb - hv) ** 2) ** (alpha / 2)
        powers.append(gbs.power_w * g_b * g_v / loss)
    interference = 0.0
    for jx, jy, jp, jh in [] if jammer is None else [jammer, *more_jammers]:
        dj = math.hypot(x - jx, y - jy)
        slant = math.sqrt(dj**2 + (jh - hv) ** 2)
        efficiency = 10 ** (scenario.jammer.efficiency_db / 10)
        interference += jp * efficiency * slant ** (-alpha) * (hv - jh) / slant
    k = int(np.argmax(powers))
    channels = gbs.channels or [0] * len(powers)
    co_channel = sum(p for p, c in zip(powers, channels, strict=True) if c == channels[k])
    sinr = powers[k] / (channel.noise_w + interference + co_channel - powers[k])
    return 10 * math.log10(sinr), k


def test_single_gbs_directly_below_by_hand(scenario):
    # One GBS at the origin, the UAV right above it: elevation 90 deg, so the antenna is
    # 100 deg off boresight -> attenuation capped at G_m = 20 dB; G_V = 1; L = 18^2.5.
    one = variant(scenario, gbs={"positions": [[0.0, 0.0]]}, policy={"nearby_gbs": 1})
    received = RadioModel(one).gbs_received_power(np.array([[0.0, 0.0]]))[0, 0]
    assert math.isclose(received, 0.01 / 18**2.5, rel_tol=1e-12)
    reading = RadioModel(one).evaluate(np.array([0.0, 0.0]))
    assert math.isclose(float(reading.sinr), (0.01 / 18**2.5) / 1e-6, rel_tol=1e-12)


def test_jammer_term_by_hand(scenario):
    # Jammer right below the UAV: I_J = P_J * eff * (H_V - H_J)^-alpha (sin = 1).
    radio = RadioModel(scenario)
    jam = JammerParams(10.0, 20.0, 1.0, 30.0)
    got = radio.jammer_interference(np.array([10.0, 20.0]), jam)
    eff = 10 ** (scenario.jammer.efficiency_db / 10)
    assert math.isclose(float(got), eff * 20.0**-2.5, rel_tol=1e-12)


def test_matches_term_by_term_reference(scenario):
    radio = RadioModel(scenario)
    rng = np.random.default_rng(7)
    points = rng.uniform(-50, 50, size=(40, 2))
    for jammer in (None, JammerParams(0.0, 0.0, 1.0, 30.0), JammerParams(25, -10, 0.5, 1.5)):
        reading = radio.evaluate(points, jammer)
        for (x, y), db, serving in zip(points, reading.sinr_db, reading.serving_gbs, strict=True):
            want_db, want_k = reference_sinr_db(scenario, x, y, jammer)
            assert math.isclose(db, want_db, rel_tol=1e-9, abs_tol=1e-9)
            assert serving == want_k


def test_reused_channels_match_the_reference(scenario):
    # Three channels over the 12 GBSs: only the serving GBS's own channel interferes.
    reused = variant(scenario, gbs={"channels": [0, 1, 2, 7] * 3})
    radio, alone = RadioModel(reused), RadioModel(scenario)
    points = np.random.default_rng(8).uniform(-50, 50, size=(40, 2))
    jammer = JammerParams(10.0, 5.0, 1.0, 30.0)
    reading = radio.evaluate(points, jammer)
    for (x, y), db, serving in zip(points, reading.sinr_db, reading.serving_gbs, strict=True):
        want_db, want_k = reference_sinr_db(reused, x, y, jammer)
        assert math.isclose(db, want_db, rel_tol=1e-9, abs_tol=1e-9)
        assert serving == want_k
    # Fewer interferers, the same serving GBS: never a lower SINR.
    one_channel = alone.evaluate(points, jammer)
    assert (reading.sinr_db > one_channel.sinr_db).all()
    np.testing.assert_array_equal(reading.serving_gbs, one_channel.serving_gbs)


def test_levels_follow_edges(scenario):
    radio = RadioModel(scenario)
    edges = scenario.channel.level_edges_db
    values = np.array([edges[0] - 1e-9, edges[0], edges[1] - 1e-9, edges[1], 30.0, -30.0])
    assert radio.level_of(values).tolist() == [0, 1, 1, 2, 2, 0]


def test_jammer_opens_a_local_hole_not_a_blank_area(scenario):
    radio = RadioModel(scenario)
    _, _, clear = radio.grid(scenario, 101, None)
    _, _, jammed = radio.grid(scenario, 101, radio.default_jammers)
    clear_share, jammed_share = (clear.level > 0).mean(), (jammed.level > 0).mean()
    assert 0.7 < clear_share < 0.95
    assert 0.5 < jammed_share < clear_share - 0.03
    # The hole is local: far corners keep their coverage.
    corner = np.array([[-37.5, 33.0], [37.5, -33.0]])
    assert (radio.evaluate(corner, radio.default_jammers).level > 0).all()


@settings(max_examples=60, deadline=None)
@given(x=coordinate, y=coordinate, jx=coordinate, jy=coordinate,
       p1=st.floats(0, 2), p2=st.floats(0, 2))
def test_more_jammer_power_never_raises_sinr(scenario, x, y, jx, jy, p1, p2):
    radio = RadioModel(scenario)
    low, high = sorted((p1, p2))
    point = np.array([x, y])
    weaker = radio.evaluate(point, JammerParams(jx, jy, low, 30.0)).sinr
    stronger = radio.evaluate(point, JammerParams(jx, jy, high, 30.0)).sinr
    assert stronger <= weaker * (1 + 1e-12)


@settings(max_examples=60, deadline=None)
@given(x=coordinate, y=coordinate, angle=st.floats(0, 2 * math.pi),
       near=st.floats(0, 40), extra=st.floats(0, 40))
def test_moving_the_jammer_away_never_lowers_sinr(scenario, x, y, angle, near, extra):
    radio = RadioModel(scenario)
    point = np.array([x, y])
    direction = np.array([math.cos(angle), math.sin(angle)])
    close_xy = point + near * direction
    far_xy = point + (near + extra) * direction
    close = radio.evaluate(point, JammerParams(*close_xy, 1.0, 30.0)).sinr
    far = radio.evaluate(point, JammerParams(*far_xy, 1.0, 30.0)).sinr
    assert far >= close * (1 - 1e-12)


@settings(max_examples=60, deadline=None)
@given(x=coordinate, y=coordinate, jy=coordinate)
def test_symmetric_layout_gives_symmetric_map(scenario, x, y, jy):
    # The 4 x 3 grid is symmetric under x -> -x and y -> -y; a jammer on the axis keeps it.
    radio = RadioModel(scenario)
    points = np.array([[x, y], [-x, y]])
    no_jammer = radio.evaluate(points).sinr_db
    assert math.isclose(no_jammer[0], no_jammer[1], rel_tol=1e-9, abs_tol=1e-9)
    mirrored_y = radio.evaluate(np.array([[x, y], [x, -y]])).sinr_db
    assert math.isclose(mirrored_y[0], mirrored_y[1], rel_tol=1e-9, abs_tol=1e-9)
    jammed = radio.evaluate(points, JammerParams(0.0, jy, 1.0, 30.0)).sinr_db
    assert math.isclose(jammed[0], jammed[1], rel_tol=1e-9, abs_tol=1e-9)


def test_batch_shapes_and_per_point_jammers(scenario):
    radio = RadioModel(scenario)
    points = np.zeros((3, 4, 2))
    points[..., 0] = np.arange(4) * 5.0
    per_env = JammerParams(np.array([[0.0], [20.0], [0.0]]), 0.0,
                           np.array([[1.0], [1.0], [0.0]]), 30.0)
    reading = radio.evaluate(points, per_env)
    assert reading.sinr_db.shape == (3, 4)
    np.testing.assert_allclose(reading.sinr_db[2], radio.evaluate(points[2]).sinr_db)
    np.testing.assert_allclose(
        reading.sinr_db[1], radio.evaluate(points[1], JammerParams(20.0, 0.0, 1.0, 30.0)).sinr_db
    )


def points_over(scenario, rng, size):
    """``size`` points drawn uniformly over the scenario's area."""
    area = scenario.area
    return rng.uniform([area.x_min, area.y_min], [area.x_max, area.y_max], size=(size, 2))


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), size=st.integers(1, 300),
       name=st.sampled_from(["icc2021", "icc2021-shadowed", "city"]))
def test_a_point_reads_the_same_in_any_batch(seed, size, name):
    # The world evaluates a step's reports and its end in one batch, an in-process
    # evaluation many environments at once, the world process one: a point's reading must
    # not depend on which other points share its batch, bit for bit (the city reuses
    # channels; the shadowed world interpolates its fields).
    scenario = load_scenario(name)
    radio = RadioModel(scenario)
    rng = np.random.default_rng(seed)
    points = points_over(scenario, rng, size)
    jammers = (JammerParams(*rng.uniform(-50, 50, 2), 1.0, 30.0),
               JammerParams(rng.uniform(-50, 50, size), 5.0, rng.uniform(0, 2, size), 20.0))
    whole = radio.evaluate(points, jammers)
    for index in {0, size // 2, size - 1}:
        alone = radio.evaluate(points[index:index + 1],
                               (jammers[0], JammerParams(jammers[1].x[index:index + 1], 5.0,
                                                         jammers[1].power_w[index:index + 1],
                                                         20.0)))
        for together, by_itself in zip(whole, alone, strict=True):
            assert together[index] == by_itself[0]


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), size=st.integers(1, 400),
       name=st.sampled_from(["icc2021", "city", "two-jammers"]))
def test_the_compiled_received_powers_agree_with_the_reference(seed, size, name):
    # The core's atan2, log and exp (glibc's vector math) and numpy's each lie within 4 ulp
    # of the truth, and the other operations round alike. A power is scale * exp(e), e the
    # log-power: the log's error scales with |e|, and so with both sides' 4 ulp on each of
    # the three functions and the 6 roundings feeding e, |d e| <= 2 * (3 * 4 + 6) * (|e| + 1)
    # * eps; exp turns that into the relative error of the power (plus its own 4 ulp each).
    scenario = load_scenario(name)
    radio = RadioModel(scenario)
    assert radio._core is not None
    points = points_over(scenario, np.random.default_rng(seed), size)
    compiled = radio._ideal_gbs_received_power(points)
    reference = radio._reference_gbs_received_power(points)
    # Both sides compute in float64 (no float32 anywhere on this path), so the unit is
    # float64's eps on every x86_64 CPU; the vector and scalar paths keep the same 4 ulp.
    eps = np.finfo(np.float64).eps
    log_power = np.abs(np.log(reference / (radio.gbs_power_w * radio._height_gap)))
    bound = (2 * (3 * 4 + 6) * (log_power + 1) + 2 * 4) * eps
    assert (np.abs(compiled / reference - 1) <= bound).all()
    # The SINR is a ratio of sums of these powers (the jammer's alike on both sides): within
    # twice the powers' worst relative error, 10 / ln 10 dB per unit of it, and so the same
    # level away from the edges. The 1 % on top covers the few roundings of the sums, the
    # division and log10 themselves (each eps, against a bound of hundreds of eps).
    jammers = RadioModel.jammers_of(scenario)
    core = radio._core
    by_core = radio.evaluate(points, jammers)
    radio._core = None
    by_reference = radio.evaluate(points, jammers)
    radio._core = core
    worst_db = 10 / math.log(10) * 2 * bound.max() * 1.01
    assert np.allclose(by_core.sinr_db, by_reference.sinr_db, rtol=0, atol=worst_db)
    clear = (np.abs(by_reference.sinr_db[:, None] - radio.level_edges_db) > worst_db).all(axis=1)
    np.testing.assert_array_equal(by_core.level[clear], by_reference.level[clear])
    # The same serving GBS where the two strongest are not within those errors of a tie.
    strongest = np.sort(reference, axis=1)[:, -2:]
    apart = (strongest[:, 1] - strongest[:, 0]) / strongest[:, 1] > 2 * bound.max()
    np.testing.assert_array_equal(by_core.serving_gbs[apart], by_reference.serving_gbs[apart])

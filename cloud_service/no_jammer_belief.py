"""What the cloud believes of the world's no-jammer SINR at a point (Gaussian, dB).

The cloud knows the GBS layout (the scenario) and the ideal radio model, Eq. (1)-(5), but not
the shadowing of the world nor the receivers' noise. Its belief of the no-jammer SINR
(``sinr_beliefs``) is the ideal model's value with the world's shadowing as its spread,
``shadowing_sigma_db``; or, given the no-jammer map's level there (learned from
measurements, so it carries the shadowing), that prior truncated to the level's band and
moment-matched. Near a level's edge a map learned from noisy reports says more than its
level: its probability of the levels below the edge is the share of reports there that fell
below, which reads the SINR to within ``MAP_READING_SD_DB``, sharper than the ideal model's
spread; the two are combined by their precisions (``prior_of_map``).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from scipy.special import ndtri

from cloud_service.report_likelihood import (
    OUTLIER_SHARE,
    REPORT_SIGMA_DB,
    band_edges,
    log_band_probability,
)
from shared.radio import RadioModel

# The world's spread about the ideal model when no no-jammer map is given to fit it
# (``fit_shadowing_sigma``): a little above what icc2021-shadowed's shadowing gives
# (BENCHMARKS.md, "Online SINR mapping", the estimator's model).
SHADOWING_SIGMA_DB = 3.0
# Reading the SINR off a no-jammer map's probabilities near a level's edge (``prior_of_map``):
# the probability of the levels below the edge, s, puts the SINR at edge - REPORT_SIGMA_DB *
# probit(s), the ordinal probit of the reports the map learned from, give or take
# MAP_READING_SD_DB (the network's smoothing and calibration); a share beyond MAP_SHARE_READ
# of 0 or 1 says only which side of the edge. Both chosen by flying icc2021-shadowed's survey
# map corrected with the true jammer at several values (BENCHMARKS.md, "Online SINR mapping",
# ``bench_correction``).
MAP_READING_SD_DB = 0.5
MAP_SHARE_READ = 0.001

_SIGMA_CHOICES_DB = np.geomspace(0.01, 10.0, 61)  # 12 % apart
_SIGMA_FIT_POINTS = 2000  # a stride through more points: the fit needs no more
_LOG_SQRT_2PI = 0.5 * math.log(2.0 * math.pi)


class SinrBelief(NamedTuple):
    """What the cloud believes of the world's no-jammer SINR at some points (Gaussian, dB)."""

    mean_db: np.ndarray
    sd_db: np.ndarray


def sinr_beliefs(
    radio: RadioModel, xy: np.ndarray, no_jammer_levels: np.ndarray | None = None,
    shadowing_sigma_db: float | None = None, reference: SinrBelief | None = None,
) -> SinrBelief:
    """The world's no-jammer SINR at points ``xy`` (n, 2): the ideal model's, give or take
    ``shadowing_sigma_db``; with the no-jammer map there, ``no_jammer_levels`` (its levels
    (n,) or its probabilities of each level (n, levels)), that prior sharpened by what the
    map's probabilities read near a level's edge (``prior_of_map``) and truncated to its
    most probable level's band (the mean and sd). A sigma of None is fitted to the map's
    levels (``fit_shadowing_sigma``), or else ``SHADOWING_SIGMA_DB``. Where ``reference``
    holds what was measured at a point with no jammer (a mean and sd; NaN where nothing
    was), the ideal model's prior combined with that instead."""
    mean_db = radio.evaluate(xy).sinr_db
    if no_jammer_levels is None:
        sigma_db = SHADOWING_SIGMA_DB if shadowing_sigma_db is None else shadowing_sigma_db
        belief = SinrBelief(mean_db, np.full_like(mean_db, sigma_db))
    else:
        probabilities = level_probabilities(no_jammer_levels, len(radio.level_edges_db) + 1)
        lower_db, upper_db = band_edges(radio, probabilities.argmax(axis=-1))
        if shadowing_sigma_db is None:
            shadowing_sigma_db = fitted_sigma(mean_db, lower_db, upper_db)
        belief = _truncated_normal(
            *prior_of_map(radio, mean_db, shadowing_sigma_db, probabilities), lower_db,
            upper_db)
    if reference is None:
        return belief
    # The SINR measured there with no jammer, where it was: the ideal model's prior sharpened
    # by it, not confined to the map's band, which the map gets wrong where it errs.
    sigma_db = SHADOWING_SIGMA_DB if shadowing_sigma_db is None else shadowing_sigma_db
    known = np.isfinite(reference.mean_db)
    precision = sigma_db**-2.0 + np.where(known, reference.sd_db, np.inf) ** -2.0
    referenced = (sigma_db**-2.0 * mean_db + np.where(
        known, reference.mean_db / np.where(known, reference.sd_db, 1.0) ** 2, 0.0)) / precision
    return SinrBelief(np.where(known, referenced, belief.mean_db),
                      np.where(known, precision**-0.5, belief.sd_db))


def level_probabilities(levels_or_probabilities: np.ndarray, level_count: int) -> np.ndarray:
    """A no-jammer map's probabilities of each level (n, levels), given them or its levels
    (n,), which it is then certain of."""
    given = np.asarray(levels_or_probabilities)
    if given.ndim == 2:
        return given.astype(np.float64)
    return np.eye(level_count)[given.astype(np.int64).reshape(-1)]


def map_reading(radio: RadioModel, probabilities: np.ndarray,
                report_sigma_db: float = REPORT_SIGMA_DB) -> tuple[np.ndarray, np.ndarray]:
    """Where a map's ``probabilities`` (n, levels) of the levels reported put the SINR (dB,
    (n,)): at the level edge whose share of reports below is nearest a half, edge -
    report_sigma_db x probit(share), the ordinal probit of reports erring by
    N(0, report_sigma_db^2); and whether that share says more than which side of the edge
    (within ``MAP_SHARE_READ`` of neither 0 nor 1)."""
    below = np.cumsum(probabilities, axis=-1)[:, :-1]  # share below each edge
    edge = np.abs(below - 0.5).argmin(axis=-1)
    share = below[np.arange(len(below)), edge]
    read = (share > MAP_SHARE_READ) & (share < 1.0 - MAP_SHARE_READ)
    reading_db = radio.level_edges_db[edge] - report_sigma_db * ndtri(
        np.clip(share, MAP_SHARE_READ, 1.0 - MAP_SHARE_READ))
    return reading_db, read


def prior_of_map(radio: RadioModel, ideal_db: np.ndarray, shadowing_sigma_db: float,
                 probabilities: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean and sd (n,) of the no-jammer SINR before the map's band is imposed: the ideal
    model's N(ideal_db, shadowing_sigma_db^2) combined, by precision, with what the map's
    ``probabilities`` (n, levels) read near the level edge whose share below is nearest a
    half (see ``MAP_READING_SD_DB``). Where the map is certain (a share beyond
    ``MAP_SHARE_READ``, as with levels given) the ideal model's prior stands alone."""
    reading_db, read = map_reading(radio, probabilities)
    prior_precision = shadowing_sigma_db**-2.0
    map_precision = np.where(read, MAP_READING_SD_DB**-2.0, 0.0)
    precision = prior_precision + map_precision
    mean_db = (prior_precision * ideal_db + map_precision * reading_db) / precision
    return mean_db, precision**-0.5


def fit_shadowing_sigma(radio: RadioModel, xy: np.ndarray, no_jammer_levels: np.ndarray):
    """How far the world departs from the ideal model: the sd (dB) of its no-jammer SINR
    about the ideal one that best explains the no-jammer map's levels at ``xy`` (n, 2)
    (maximum likelihood over ``_SIGMA_CHOICES_DB``). The cloud learns it from its own map,
    never from the world; a learned map's own errors add to the shadowing it reads
    (BENCHMARKS.md, "Online SINR mapping", the estimator's model)."""
    lower_db, upper_db = band_edges(radio, np.asarray(no_jammer_levels, dtype=np.int64))
    return fitted_sigma(radio.evaluate(xy).sinr_db, lower_db, upper_db)


def sigma_fit_sample(rows: np.ndarray) -> np.ndarray:
    """The rows of points (or of values at them) that ``fit_shadowing_sigma`` reads: a stride
    through them. A caller that labels points for it need label no others."""
    return rows[:: max(1, len(rows) // _SIGMA_FIT_POINTS)]


def fitted_sigma(ideal_db: np.ndarray, lower_db: np.ndarray, upper_db: np.ndarray) -> float:
    """``fit_shadowing_sigma`` given the ideal model's SINR at the points and the band of the
    map's level at each."""
    ideal_db, lower_db, upper_db = (sigma_fit_sample(v) for v in (ideal_db, lower_db, upper_db))
    sigmas = _SIGMA_CHOICES_DB[:, None]
    log_model = log_band_probability((lower_db - ideal_db) / sigmas,
                                     (upper_db - ideal_db) / sigmas)
    # The map's own errors are outliers, not shadowing: the floor keeps them from ruling.
    floor = math.log(OUTLIER_SHARE / 3.0)
    score = np.logaddexp(math.log1p(-OUTLIER_SHARE) + log_model, floor).sum(axis=1)
    return float(_SIGMA_CHOICES_DB[score.argmax()])


def _truncated_normal(mean: np.ndarray, sd: float | np.ndarray, lower: np.ndarray,
                      upper: np.ndarray):
    """Mean and sd of N(mean, sd^2) restricted to [lower, upper), stable far in the tails."""
    a, b = (lower - mean) / sd, (upper - mean) / sd
    log_mass = log_band_probability(a, b)
    # phi(z) / mass and z phi(z) / mass, zero at an infinite bound.
    with np.errstate(invalid="ignore"):
        density_a = np.where(np.isfinite(a), np.exp(-0.5 * a * a - _LOG_SQRT_2PI - log_mass), 0.0)
        density_b = np.where(np.isfinite(b), np.exp(-0.5 * b * b - _LOG_SQRT_2PI - log_mass), 0.0)
        moment_a = np.where(np.isfinite(a), a * density_a, 0.0)
        moment_b = np.where(np.isfinite(b), b * density_b, 0.0)
    shift = density_a - density_b
    # Deep in a tail the variance formula cancels to rounding noise: keep a floor of 5 %.
    variance = np.maximum(1.0 + moment_a - moment_b - shift * shift, 0.0025)
    return SinrBelief(mean + sd * shift, sd * np.sqrt(variance))

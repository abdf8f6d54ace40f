"""Estimating the jammers (position, power, uncertainty) from the uploads alone: whether they
show one, where it stands and how strong it is (``estimate_jammer``), how many there are and
each one (``estimate_jammers``), and, while they cannot place one yet, the hypotheses of a
provisional map (``jammer_hypotheses``).

Why the no-jammer map matters. In the scenarios of this project the jammer costs less SINR
than the world's SINR departs from the ideal model: from the ideal model alone a jammer
cannot be told from the shadowing, and the estimates come out far off with confident but
wrong standard deviations. Conditioned on the world's no-jammer map (``no_jammer_belief``) it
can be placed (measured: BENCHMARKS.md, "Online SINR mapping", the estimator's model).

Search. A coarse search over the area (plus a margin: a jammer may stand at the edge) and
log-spaced powers finds the region (``_CoarseSearch``); a finer grid around it gives the
estimate and its uncertainty as the moments of the likelihood-weighted (flat-prior)
posterior (``_refine``). Each hypothesis is weighed by ``jammer_evidence``. Whether a jammer
is there is decided at one report spread, which no world contradicts (``_decide``); a
converged estimate is then refitted at the spread that explains the reports best, since a
spread wider than the world's reads the power wrong (``_refitted``).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import NamedTuple

import numpy as np

from cloud_service.estimated_jammer import JammerEstimate, JammerHypotheses, estimated_set
from cloud_service.jammer_evidence import (
    INDEPENDENT_SPACING_M,
    JammerEvidence,
    Reports,
    independence_weights,
)
from cloud_service.no_jammer_belief import SinrBelief, sinr_beliefs
from cloud_service.report_likelihood import OUTLIER_SHARE, REPORT_SIGMA_DB
from shared.radio import RadioModel
from shared.scenario import MAX_JAMMERS, Scenario

# A converged estimate is refitted with the report spread that explains the uploads best among
# these (maximum likelihood); whether it converged is decided at REPORT_SIGMA_DB, and so are
# the hypotheses of a provisional map (at 0.3 dB a quiet sky's exact reports showed a jammer).
# An exact receiver (icc2021) read at 1.2 dB pulls the power low on the UAVs' paths, which
# hug the jammed zone's edge (BENCHMARKS.md, "Jammers beyond the training range").
REPORT_SIGMA_CHOICES_DB = (0.3, 0.6, REPORT_SIGMA_DB)

# The search (see ``_CoarseSearch`` and ``_refine``).
SEARCH_MARGIN_M = 10.0  # beyond the area: a jammer may stand at its edge or just outside
COARSE_SPACING_M = 5.0
COARSE_POWER_STEP_DB = 1.0
POWER_SEARCH_DB = 10.0  # searched below and above the training range of nominal powers
FINE_NODES = 13  # per side and per power of the refining grid

# The decision (see ``_decide``).
MIN_MEASUREMENTS = 30
# Wider, fits far off with the power far too high got through from short flights; narrower,
# longer flights lose converged estimates (BENCHMARKS.md, "Online SINR mapping", the
# localization rows).
MAX_POSITION_SD_M = 10.0
PRESENCE_LLR = 4.0
EXCLUSION_LLR = 1.0
# While no estimate converges, the hypotheses behind a provisional map: the most probable
# coarse ones holding this share of the posterior, at most this many (each costs the map one
# evaluation of the radio model over its prior points).
HYPOTHESES_MASS = 0.95
MOST_HYPOTHESES = 64
# A change was detected already: hypotheses need only explain the uploads better than no
# jammer does, by this much (nats), not prove one present (PRESENCE_LLR). More evidence makes
# the first provisional map a little more right but much later (BENCHMARKS.md, "Online SINR
# mapping", provisional maps).
HYPOTHESES_LLR = 1.0


def estimate_jammer(
    scenario: Scenario,
    xy: np.ndarray,
    levels: np.ndarray,
    *,
    reported_db: np.ndarray | None = None,
    no_jammer_levels: np.ndarray | None = None,
    no_jammer_db: SinrBelief | None = None,
    shadowing_sigma_db: float | None = None,
    report_sigma_db: float = REPORT_SIGMA_DB,
    outlier_share: float = OUTLIER_SHARE,
    independent_spacing_m: float = INDEPENDENT_SPACING_M,
    min_measurements: int = MIN_MEASUREMENTS,
    max_position_sd_m: float = MAX_POSITION_SD_M,
    presence_llr: float = PRESENCE_LLR,
    exclusion_llr: float = EXCLUSION_LLR,
) -> JammerEstimate | None:
    """The jammer (at the scenario's jammer height) that best explains the reported
    ``levels`` (n,), and SINRs ``reported_db`` (n,) where they are finite, at positions
    ``xy`` (n, 2), or None when the data cannot pin it down. Rows with a NaN position are
    ignored.

    ``no_jammer_levels``: the no-jammer map's level (n,), or better its probability of each
    level (n, levels), at each position, which the estimate should be given whenever the
    world may differ from the ideal model (see the module docstring); ``no_jammer_db``: the
    no-jammer SINR measured there, where it was (``sinr_beliefs``). ``shadowing_sigma_db``:
    sd of the world's no-jammer SINR about the ideal model's; None fits it to
    ``no_jammer_levels`` (``fit_shadowing_sigma``), or without them takes
    ``SHADOWING_SIGMA_DB``. ``report_sigma_db``: what a report adds once that SINR is known
    (receiver noise, the jammer link's own shadowing).

    Steps: the coarse search at ``report_sigma_db`` (``_coarse_search``; None with fewer than
    ``min_measurements`` rows with a position), the decision on it (``_decide``, by
    ``presence_llr``, ``exclusion_llr`` and ``max_position_sd_m``), and a converged
    estimate refitted with the spread among ``REPORT_SIGMA_CHOICES_DB`` that explains the
    reports best (``_refitted``).
    """
    reports = Reports.of(scenario, xy, levels, reported_db)
    reading = _Reading(no_jammer_levels, no_jammer_db, shadowing_sigma_db, outlier_share,
                       independent_spacing_m, min_measurements)
    searched = _coarse_search(scenario, reports, reading, report_sigma_db)
    if searched is None:
        return None
    estimate = _decide(scenario, searched, presence_llr, exclusion_llr, max_position_sd_m)
    return _refitted(scenario, searched, estimate,
                     lambda sigma_db: _coarse_search(scenario, reports, reading, sigma_db))


def _refitted(scenario: Scenario, searched: _Searched, estimate: JammerEstimate | None,
              search_at: Callable[[float], _Searched]) -> JammerEstimate | None:
    """A converged ``estimate`` of ``searched`` refined again on the coarse search of the same
    reports at the report spread of ``REPORT_SIGMA_CHOICES_DB`` (``search_at`` gives it)
    whose best hypothesis explains the reports best, if that is not ``searched``'s own;
    anything else as it is."""
    if estimate is None or not estimate.present:
        return estimate
    best, best_log_likelihood = searched, searched.evidence.no_jammer + float(searched.llr.max())
    for sigma_db in REPORT_SIGMA_CHOICES_DB:
        if sigma_db == searched.evidence.report_sigma_db:
            continue
        other = search_at(sigma_db)
        log_likelihood = other.evidence.no_jammer + float(other.llr.max())
        if log_likelihood > best_log_likelihood:
            best, best_log_likelihood = other, log_likelihood
    if best is searched:
        return estimate
    fine, fine_llr = _refine(best.evidence, best.search, best.llr)
    return _present(scenario, fine, len(best.evidence.xy), fine_llr)


def _decide(scenario: Scenario, searched: _Searched, presence_llr: float, exclusion_llr: float,
            max_position_sd_m: float) -> JammerEstimate | None:
    """``estimate_jammer``'s decision on a coarse search, by the weighted log-likelihood
    ratio (LLR) of a jammer against none:
    - best coarse LLR below ``presence_llr``: no jammer (``present`` false) if the data rules
      out a jammer of the training range's middle power (geometric mean) everywhere in the
      area (its LLR below ``-exclusion_llr`` at every coarse node there); otherwise None, as
      the data has not looked everywhere a jammer may be. A weaker jammer may remain: at
      the range's lowest power it costs under 1 dB of SINR, which the shadowing hides even
      from measurements over the whole area;
    - best coarse hypothesis on the edge of the search (position on the outer ring, power
      the lowest or the highest searched), or a fine posterior (``_refine``) whose position
      standard deviation along the least certain direction is above
      ``max_position_sd_m``: None;
    - otherwise the estimate: the mean of the fine posterior, its standard deviations those
      of the posterior."""
    evidence, search, llr = searched
    if llr.max() < presence_llr:
        return (_absent(len(evidence.xy), float(llr.max()))
                if _ruled_out(searched, exclusion_llr) else None)
    best_position, best_power = np.unravel_index(llr.argmax(), llr.shape)
    if search.on_edge[best_position] or best_power in (0, len(search.powers_dbw) - 1):
        return None
    fine, fine_llr = _refine(evidence, search, llr)
    if fine.worst_sd_m > max_position_sd_m:
        return None
    return _present(scenario, fine, len(evidence.xy), fine_llr)


def _ruled_out(searched: _Searched, exclusion_llr: float) -> bool:
    """Whether the data rules out a jammer of the training range's middle power everywhere in
    the area: its LLR below ``-exclusion_llr`` at every coarse node there."""
    _, search, llr = searched
    return bool((llr[search.in_area, search.middle_of_range] < -exclusion_llr).all())


def jammer_hypotheses(
    scenario: Scenario,
    xy: np.ndarray,
    levels: np.ndarray,
    *,
    reported_db: np.ndarray | None = None,
    no_jammer_levels: np.ndarray | None = None,
    no_jammer_db: SinrBelief | None = None,
    mass: float = HYPOTHESES_MASS,
    most: int = MOST_HYPOTHESES,
    presence_llr: float = HYPOTHESES_LLR,
    report_sigma_db: float = REPORT_SIGMA_DB,
) -> JammerHypotheses | None:
    """The fewest coarse hypotheses (at most ``most``) that hold ``mass`` of the posterior of
    a jammer of the scenario's expected powers, when one explains the uploads better than
    none (best LLR at least ``presence_llr``); None otherwise.
    The same search and model as ``estimate_jammer``, which answers None in that case when
    the posterior is too wide."""
    searched = _coarse_search(scenario, Reports.of(scenario, xy, levels, reported_db),
                              _Reading(no_jammer_levels, no_jammer_db), report_sigma_db)
    if searched is None:
        return None
    return _hypotheses(scenario, searched, mass, most, presence_llr)


# A jammer taken as known while the next is searched for: position (2,), effective power dBW.
Placed = tuple[np.ndarray, float]
# A jammer's parameters, for BIC's penalty on one jammer more: its x, y and power.
JAMMER_PARAMETERS = 3
PLACING_ROUNDS = 4  # of placing each jammer again with the others known (``_placed_again``)
REFINING_GRIDS = 2  # finer grids a jammer placed finer is sought on (``_best_placed``)


def estimate_jammers(
    scenario: Scenario,
    xy: np.ndarray,
    levels: np.ndarray,
    *,
    reported_db: np.ndarray | None = None,
    no_jammer_levels: np.ndarray | None = None,
    no_jammer_db: SinrBelief | None = None,
    most: int = MAX_JAMMERS,
    report_sigma_db: float = REPORT_SIGMA_DB,
) -> list[JammerEstimate] | None:
    """How many jammers, from none to ``most``, the uploads show, and each one; None when
    they cannot tell yet (``_counted``)."""
    reports = Reports.of(scenario, xy, levels, reported_db)
    reading = _Reading(no_jammer_levels, no_jammer_db)
    searched = _coarse_search(scenario, reports, reading, report_sigma_db)
    if searched is None:
        return None
    counted = _counted(scenario, reports, reading, report_sigma_db, searched,
                       _greedy_placed(scenario, reports, reading, report_sigma_db, searched,
                                      most))
    return None if counted is None else list(counted.members)


def _greedy_placed(scenario: Scenario, reports: Reports, reading: _Reading,
                   report_sigma_db: float, searched: _Searched, most: int) -> list[Placed]:
    """The jammers the reports show, each placed at a coarse hypothesis, from their coarse
    search ``searched``: none while no jammer explains them by ``PRESENCE_LLR``. Then,
    greedily, one more is searched for with those found taken as known (their interference
    adds in Eq. (3)), among the powers the scenario expects (its training range), and kept
    while it raises the weighted log-likelihood by more than BIC's penalty,
    ``JAMMER_PARAMETERS`` / 2 ln n over the n reports that count as independent; after each
    is added, every earlier one is placed again with all the others known (the first was
    placed as if alone, and read the others' losses as its own). At most ``most``."""
    if searched.llr.max() < PRESENCE_LLR:
        return []
    penalty = _penalty(searched.evidence)
    placed = [_best_placed(searched)]
    while len(placed) < most:
        # One more must be of the powers the scenario expects: a weaker one found beside a
        # jammer is the misfit of the cloud's model (the survey map's errors) read as a source
        # (BENCHMARKS.md, "Several jammers, and jammers that move", correcting with the sum).
        more = _of_expected_powers(
            scenario, _coarse_search(scenario, reports, reading, report_sigma_db, placed))
        if more.llr.max() <= penalty:
            break
        placed = _placed_again(scenario, reports, reading, report_sigma_db,
                               [*placed, _best_placed(more)])
    return placed


def _counted(scenario: Scenario, reports: Reports, reading: _Reading, report_sigma_db: float,
             searched: _Searched, placed: list[Placed]) -> JammerEstimate | None:
    """The jammers the reports show, as one estimate of the set (``estimated_set``; with
    ``present`` false, none), from their coarse search ``searched`` and the jammers
    ``_greedy_placed`` placed on it; None when they cannot tell yet.

    None or one placed: ``estimate_jammer``'s decision. Several: each is estimated with the
    others known, and must converge as ``estimate_jammer`` asks (else None), its
    log-likelihood ratio against the others alone past BIC's penalty; and each but the first
    must stay of the powers the scenario expects once estimated, else the count is one
    jammer less."""
    if len(placed) <= 1:
        return _refitted(scenario, searched, _decide(
            scenario, searched, PRESENCE_LLR, EXCLUSION_LLR, MAX_POSITION_SD_M),
            lambda sigma_db: _coarse_search(scenario, reports, reading, sigma_db))
    estimates = []
    for index in range(len(placed)):
        given = _coarse_search(scenario, reports, reading, report_sigma_db,
                               placed[:index] + placed[index + 1:])
        estimate = _decide(scenario, given, _penalty(searched.evidence), EXCLUSION_LLR,
                           MAX_POSITION_SD_M)
        if estimate is None or not estimate.present:
            return None
        estimates.append(estimate)
    if not all(_expected(scenario, estimate.effective_power_dbm - 30.0)
               for estimate in estimates[1:]):
        return _counted(scenario, reports, reading, report_sigma_db, searched, _greedy_placed(
            scenario, reports, reading, report_sigma_db, searched, len(placed) - 1))
    return estimated_set(estimates)


def _shown(searched: _Searched, placed: list[Placed]) -> int | None:
    """How many jammers the reports show, placed or not: those ``_greedy_placed`` placed, or
    none where the reports rule out a jammer everywhere (``_ruled_out``); None while they can
    tell neither."""
    if placed:
        return len(placed)
    return 0 if _ruled_out(searched, EXCLUSION_LLR) else None


def one_more_evidence(scenario: Scenario, xy: np.ndarray, levels: np.ndarray,
                      known: Sequence[Placed], *, reported_db: np.ndarray | None = None,
                      no_jammer_levels: np.ndarray | None = None,
                      no_jammer_db: SinrBelief | None = None,
                      report_sigma_db: float = REPORT_SIGMA_DB) -> tuple[float, float] | None:
    """How much one jammer more than ``known`` (each its position and effective power, dBW)
    explains the uploads, as ``estimate_jammers`` weighs it: the best weighted LLR of the
    coarse search over the powers the scenario expects, and BIC's penalty it must beat to be
    counted beside others. None with too few located reports."""
    searched = _coarse_search(scenario, Reports.of(scenario, xy, levels, reported_db),
                              _Reading(no_jammer_levels, no_jammer_db), report_sigma_db, known)
    if searched is None:
        return None
    return (float(_of_expected_powers(scenario, searched).llr.max()),
            _penalty(searched.evidence))


def _penalty(evidence: JammerEvidence) -> float:
    """BIC's penalty for one jammer more: ``JAMMER_PARAMETERS`` / 2 ln n, n the reports that
    count as independent."""
    return 0.5 * JAMMER_PARAMETERS * math.log(max(evidence.effective_count, 2.0))


def _of_expected_powers(scenario: Scenario, searched: _Searched) -> _Searched:
    """``searched`` with the hypotheses of powers the scenario does not expect ruled out."""
    return searched._replace(llr=np.where(_expected(scenario, searched.search.powers_dbw),
                                          searched.llr, -np.inf))


def _best_placed(searched: _Searched, finer: bool = False) -> Placed:
    """The coarse search's best hypothesis; ``finer``, placed again on ``REFINING_GRIDS``
    grids of ``FINE_NODES`` per side and per power around it, the first one coarse step each
    way, each next a sixth of the last, over the powers the search weighed. The greedy
    search places on the coarse grid. On its nodes a jammer may explain the uploads worse
    than at its own place by more than BIC's penalty, so a set is weighed at its best placed
    finer (``placed_evidence``; BENCHMARKS.md, "The count's ceiling, each jammer placed
    finer")."""
    position_index, power_index = np.unravel_index(searched.llr.argmax(), searched.llr.shape)
    position = searched.search.positions[position_index]
    power = float(searched.search.powers_dbw[power_index])
    if not finer:
        return position, power
    weighed = searched.search.powers_dbw[np.isfinite(searched.llr).any(axis=0)]
    best_llr = float(searched.llr.max())
    half_width, half_power_db = COARSE_SPACING_M, COARSE_POWER_STEP_DB
    for _ in range(REFINING_GRIDS):
        positions = _square_grid(position, half_width)
        powers_dbw = np.clip(power + np.linspace(-half_power_db, half_power_db, FINE_NODES),
                             weighed.min(), weighed.max())
        llr = searched.evidence.log_likelihood_ratios(positions, powers_dbw)
        at = np.unravel_index(llr.argmax(), llr.shape)
        if llr[at] > best_llr:
            position, power, best_llr = positions[at[0]], float(powers_dbw[at[1]]), llr[at]
        half_width, half_power_db = half_width / 6.0, half_power_db / 6.0
    return position, power


def _placed_again(scenario: Scenario, reports: Reports, reading: _Reading,
                  report_sigma_db: float, placed: list[Placed],
                  finer: bool = False) -> list[Placed]:
    """Each of ``placed`` placed again (``_best_placed``), in turn, with all the others
    known, round after round until a round moves none by more than a node of the finest
    grid (at most ``PLACING_ROUNDS``): placed finer, a jammer shifts a little with each move
    of the others."""
    for _ in range(PLACING_ROUNDS):
        before = list(placed)
        for index in range(len(placed)):
            placed[index] = _best_placed(_coarse_search(
                scenario, reports, reading, report_sigma_db, placed[:index] + placed[index + 1:]),
                finer)
        if all(_settled(old, new) for old, new in zip(before, placed, strict=True)):
            break
    return placed


def _settled(before: Placed, after: Placed) -> bool:
    """Whether a jammer placed again moved by at most a node of ``_best_placed``'s finest
    grid, in place and in power."""
    finest = 2.0 / (FINE_NODES - 1) / 6.0 ** (REFINING_GRIDS - 1)  # of the first grid's span
    return (math.dist(before[0], after[0]) <= finest * COARSE_SPACING_M * (1 + 1e-9)
            and abs(before[1] - after[1]) <= finest * COARSE_POWER_STEP_DB * (1 + 1e-9))


def placed_evidence(scenario: Scenario, xy: np.ndarray, levels: np.ndarray,
                    jammers: Sequence[Placed], *, reported_db: np.ndarray | None = None,
                    no_jammer_levels: np.ndarray | None = None,
                    no_jammer_db: SinrBelief | None = None,
                    report_sigma_db: float = REPORT_SIGMA_DB,
                    ) -> tuple[list[Placed], float, float] | None:
    """What the uploads say of a set of ``jammers`` (each its position and effective power,
    dBW) at its best: each placed again, finer, with the others known (``_placed_again``);
    the uploads' weighted log-likelihood with them, as ``estimate_jammers`` weighs a set; and
    BIC's penalty for one jammer more. None with too few located reports."""
    reports = Reports.of(scenario, xy, levels, reported_db)
    reading = _Reading(no_jammer_levels, no_jammer_db)
    evidence = _evidence(scenario, reports, reading, report_sigma_db)
    if evidence is None:
        return None
    placed = _placed_again(scenario, reports, reading, report_sigma_db, list(jammers),
                           finer=True)
    return (placed, _evidence(scenario, reports, reading, report_sigma_db, placed).no_jammer,
            _penalty(evidence))


class JammerFit(NamedTuple):
    estimate: JammerEstimate | None  # as ``estimate_jammers``, the set as one estimate
    hypotheses: JammerHypotheses | None  # as ``jammer_hypotheses``, when no estimate converged
    # How many jammers the uploads show, by the count's rule, before each is placed within
    # ``MAX_POSITION_SD_M`` (``_shown``): what the estimate counts where it converged; None
    # while the uploads cannot tell.
    count: int | None = None


def locate_jammer(scenario: Scenario, xy: np.ndarray, levels: np.ndarray, *,
                  reported_db: np.ndarray | None = None,
                  no_jammer_levels: np.ndarray | None = None,
                  no_jammer_db: SinrBelief | None = None,
                  report_sigma_db: float = REPORT_SIGMA_DB) -> JammerFit:
    """``estimate_jammers`` as one estimate of the set (``estimated_set``) and, if it gives
    none, ``jammer_hypotheses``, each with its defaults but ``report_sigma_db``, from one
    coarse search (most of the cost of each); and how many jammers the uploads show, which
    the count's rule tells before every one converges."""
    reports = Reports.of(scenario, xy, levels, reported_db)
    reading = _Reading(no_jammer_levels, no_jammer_db)
    searched = _coarse_search(scenario, reports, reading, report_sigma_db)
    if searched is None:
        return JammerFit(None, None)
    placed = _greedy_placed(scenario, reports, reading, report_sigma_db, searched, MAX_JAMMERS)
    estimate = _counted(scenario, reports, reading, report_sigma_db, searched, placed)
    if estimate is not None:
        return JammerFit(estimate, None, len(estimate.members))
    return JammerFit(None, _hypotheses(scenario, searched, HYPOTHESES_MASS, MOST_HYPOTHESES,
                                       HYPOTHESES_LLR), _shown(searched, placed))


class FrameFit(NamedTuple):
    frame: int  # which of the frames fitted
    estimate: JammerEstimate | None  # as ``estimate_jammer`` reads that frame, if present
    # The reports' weighted log-likelihood with the frame's best coarse hypothesis, at the
    # report spread of ``REPORT_SIGMA_CHOICES_DB`` that explains them best: comparable
    # between the frames, converged or not.
    log_likelihood: float


def fit_frames(scenario: Scenario, xy: np.ndarray, levels: np.ndarray, frames_xy: np.ndarray,
               *, fitted: int, reported_db: np.ndarray | None = None,
               no_jammer_levels: np.ndarray | None = None,
               no_jammer_db: SinrBelief | None = None,
               report_sigma_db: float = REPORT_SIGMA_DB) -> list[FrameFit] | None:
    """One jammer in each of the frames ``frames_xy`` (F, n, 2) where its path loss may read
    the reports (``JammerEvidence.in_frame``), the first of them the reports' own places: each
    frame's coarse search at ``report_sigma_db`` over the powers the scenario expects, and
    ``estimate_jammer``'s whole estimate in the first frame and in the ``fitted`` others
    whose coarse search (its best LLR at ``report_sigma_db`` among those powers) explains the
    reports best: their fits, the first frame's first. None with too few located reports. The
    reports' tables are built once for each spread and read in every frame: most of the
    cost is each frame's coarse search."""
    reports = Reports.of(scenario, xy, levels, reported_db)
    reading = _Reading(no_jammer_levels, no_jammer_db)
    located = np.isfinite(reports.xy).all(axis=1)  # the rows the evidence keeps
    evidence = {report_sigma_db: _evidence(scenario, reports, reading, report_sigma_db)}
    if evidence[report_sigma_db] is None:
        return None
    search = _CoarseSearch.of(scenario)
    searches: dict[tuple[int, float], _Searched] = {}

    def search_at(frame: int, sigma_db: float) -> _Searched:
        if sigma_db not in evidence:
            evidence[sigma_db] = _evidence(scenario, reports, reading, sigma_db)
        if (frame, sigma_db) not in searches:
            searches[frame, sigma_db] = _searched(
                search, evidence[sigma_db].in_frame(frames_xy[frame][located]))
        return searches[frame, sigma_db]

    expected_dbw = search.powers_dbw[_expected(scenario, search.powers_dbw)]
    coarse_llr = np.array([
        float(evidence[report_sigma_db].in_frame(frame_xy[located])
              .log_likelihood_ratios(search.positions, expected_dbw).max())
        for frame_xy in frames_xy])
    fits = []
    for frame in [0, *[int(f) for f in np.argsort(-coarse_llr) if f != 0][:fitted]]:
        searched = search_at(frame, report_sigma_db)
        estimate = _refitted(scenario, searched, _decide(
            scenario, searched, PRESENCE_LLR, EXCLUSION_LLR, MAX_POSITION_SD_M),
            lambda sigma_db, frame=frame: search_at(frame, sigma_db))
        log_likelihood = max(
            other.evidence.no_jammer + float(other.llr.max())
            for other in (search_at(frame, sigma_db) for sigma_db in REPORT_SIGMA_CHOICES_DB))
        fits.append(FrameFit(frame, estimate if estimate is not None and estimate.present
                             else None, log_likelihood))
    return fits


def _hypotheses(scenario: Scenario, searched: _Searched, mass: float, most: int,
                presence_llr: float) -> JammerHypotheses | None:
    """``jammer_hypotheses`` on a coarse search."""
    # Early on, a far stronger jammer farther off explains the few contradicting reports as
    # well as the right one, and it would darken the whole map: a provisional map weighs only
    # the powers the scenario expects (its training range).
    evidence, search, llr = _of_expected_powers(scenario, searched)
    if llr.max() < presence_llr:
        return None
    weight = np.exp(llr - llr.max()).ravel()
    weight /= weight.sum()
    order = np.argsort(weight)[::-1]
    kept = order[: min(most, int(np.searchsorted(np.cumsum(weight[order]), mass)) + 1)]
    positions, powers = np.unravel_index(kept, llr.shape)
    estimates = [
        _present(scenario, _Posterior(*search.positions[p], search.powers_dbw[k],
                                      np.zeros((2, 2)), 0.0),
                 len(evidence.xy), float(llr[p, k]))
        for p, k in zip(positions.tolist(), powers.tolist(), strict=True)]
    return JammerHypotheses(estimates, weight[kept] / weight[kept].sum())


def _expected(scenario: Scenario, powers_dbw: np.ndarray | float) -> np.ndarray | bool:
    """Whether effective powers (dBW) are of the nominal powers the scenario expects (its
    training range)."""
    low_w, high_w = scenario.training.jammer_power_range_w
    nominal_w = 10.0 ** ((np.asarray(powers_dbw) - scenario.jammer.efficiency_db) / 10.0)
    return (nominal_w >= low_w * (1 - 1e-9)) & (nominal_w <= high_w * (1 + 1e-9))


class _Searched(NamedTuple):
    evidence: JammerEvidence
    search: _CoarseSearch
    llr: np.ndarray  # (positions, powers): weighted LLR of each hypothesis against none


class _Reading(NamedTuple):
    """How the search reads the reports: against the no-jammer map's levels (or
    probabilities) and the no-jammer reference, with the world's spread about the ideal model
    (None: fitted), an outlier share, the side of a square that counts about once, and from
    how many located reports on. Defaults: ``estimate_jammer``'s."""

    no_jammer_levels: np.ndarray | None
    no_jammer_db: SinrBelief | None
    shadowing_sigma_db: float | None = None
    outlier_share: float = OUTLIER_SHARE
    independent_spacing_m: float = INDEPENDENT_SPACING_M
    min_measurements: int = MIN_MEASUREMENTS


def _coarse_search(scenario: Scenario, reports: Reports, reading: _Reading,
                   report_sigma_db: float, placed: Sequence[Placed] = ()) -> _Searched | None:
    """The evidence of the located rows, the coarse search and its LLRs (positions x
    powers) of one jammer more than ``placed``; None with fewer than
    ``reading.min_measurements`` located rows."""
    evidence = _evidence(scenario, reports, reading, report_sigma_db, placed)
    return None if evidence is None else _searched(_CoarseSearch.of(scenario), evidence)


def _searched(search: _CoarseSearch, evidence: JammerEvidence) -> _Searched:
    """``search`` of ``evidence``, with its LLRs (positions x powers)."""
    return _Searched(evidence, search,
                     evidence.log_likelihood_ratios(search.positions, search.powers_dbw))


def _evidence(scenario: Scenario, reports: Reports, reading: _Reading, report_sigma_db: float,
              placed: Sequence[Placed] = ()) -> JammerEvidence | None:
    """``_coarse_search``'s evidence."""
    located = np.isfinite(reports.xy).all(axis=1)
    reports = reports.take(located)
    no_jammer_levels, no_jammer_db = reading.no_jammer_levels, reading.no_jammer_db
    if no_jammer_levels is not None:
        no_jammer_levels = np.asarray(no_jammer_levels)[located]  # levels or probabilities
    if no_jammer_db is not None:
        no_jammer_db = SinrBelief(no_jammer_db.mean_db[located], no_jammer_db.sd_db[located])
    if len(reports.xy) < reading.min_measurements:
        return None
    radio = RadioModel(scenario, shadowed=False)
    return JammerEvidence(
        radio, scenario.jammer.height_m, reports,
        independence_weights(reports.xy, reading.independent_spacing_m),
        sinr_beliefs(radio, reports.xy, no_jammer_levels, reading.shadowing_sigma_db,
                     no_jammer_db),
        report_sigma_db, reading.outlier_share, np.ptp(_CoarseSearch.of(scenario).powers_dbw),
        placed)


def _refine(evidence: JammerEvidence, search: _CoarseSearch, llr: np.ndarray):
    """The posterior on a finer grid around the best coarse hypothesis, and its best LLR:
    ``FINE_NODES`` per side and per power, three coarse posterior standard deviations (at
    least one coarse step) each way."""
    best_position, best_power = np.unravel_index(llr.argmax(), llr.shape)
    coarse = _Posterior.of(search.positions, search.powers_dbw, llr)
    positions = _square_grid(
        search.positions[best_position], max(COARSE_SPACING_M, 3.0 * coarse.worst_sd_m))
    powers_dbw = search.powers_dbw[best_power] + np.linspace(-1.0, 1.0, FINE_NODES) * max(
        COARSE_POWER_STEP_DB, 3.0 * coarse.sd_power_db)
    fine_llr = evidence.log_likelihood_ratios(positions, powers_dbw)
    return _Posterior.of(positions, powers_dbw, fine_llr), float(fine_llr.max())


def _absent(measurements: int, llr: float) -> JammerEstimate:
    return JammerEstimate(False, None, None, None, None, None, None, None, measurements, llr)


def _present(scenario: Scenario, fit: _Posterior, measurements: int, llr: float):
    return JammerEstimate(
        present=True, x=fit.x, y=fit.y,
        power_w=10.0 ** ((fit.power_dbw - scenario.jammer.efficiency_db) / 10.0),
        effective_power_dbm=fit.power_dbw + 30.0,
        sd_x_m=math.sqrt(fit.cov_xy[0, 0]), sd_y_m=math.sqrt(fit.cov_xy[1, 1]),
        sd_power_db=fit.sd_power_db, measurements=measurements, log_likelihood_ratio=llr,
        cov_xy_m2=float(fit.cov_xy[0, 1]))


class _Posterior(NamedTuple):
    """Likelihood-weighted moments over a grid of hypotheses (flat prior in x, y and dB)."""

    x: float
    y: float
    power_dbw: float
    cov_xy: np.ndarray  # (2, 2), m^2
    sd_power_db: float

    @property
    def worst_sd_m(self) -> float:
        """Standard deviation along the position's least certain direction."""
        return math.sqrt(max(float(np.linalg.eigvalsh(self.cov_xy)[-1]), 0.0))

    @classmethod
    def of(cls, positions: np.ndarray, powers_dbw: np.ndarray, llr: np.ndarray) -> _Posterior:
        weight = np.exp(llr - llr.max())
        weight /= weight.sum()
        position_weight, power_weight = weight.sum(axis=1), weight.sum(axis=0)
        mean_xy = position_weight @ positions
        centred = positions - mean_xy
        cov_xy = (centred * position_weight[:, None]).T @ centred
        mean_power = float(power_weight @ powers_dbw)
        sd_power = math.sqrt(max(float(power_weight @ (powers_dbw - mean_power) ** 2), 0.0))
        return cls(float(mean_xy[0]), float(mean_xy[1]), mean_power, cov_xy, sd_power)


class _CoarseSearch(NamedTuple):
    """Every ``COARSE_SPACING_M`` over the area plus ``SEARCH_MARGIN_M``, nominal powers every
    ``COARSE_POWER_STEP_DB`` from ``POWER_SEARCH_DB`` below the scenario's training range to
    as far above it."""

    positions: np.ndarray  # (H, 2)
    on_edge: np.ndarray  # (H,) bool: the outer ring of the search
    in_area: np.ndarray  # (H,) bool: inside the scenario's area
    powers_dbw: np.ndarray  # (P,) effective powers
    middle_of_range: int  # index of the training range's middle power (in dB)

    @classmethod
    def of(cls, scenario: Scenario) -> _CoarseSearch:
        area = scenario.area
        xs = _spaced(area.x_min - SEARCH_MARGIN_M, area.x_max + SEARCH_MARGIN_M, COARSE_SPACING_M)
        ys = _spaced(area.y_min - SEARCH_MARGIN_M, area.y_max + SEARCH_MARGIN_M, COARSE_SPACING_M)
        positions = np.stack(np.meshgrid(xs, ys), -1).reshape(-1, 2)
        on_edge = np.isin(positions[:, 0], xs[[0, -1]]) | np.isin(positions[:, 1], ys[[0, -1]])
        in_area = ((positions >= (area.x_min, area.y_min))
                   & (positions <= (area.x_max, area.y_max))).all(axis=1)
        low_w, high_w = scenario.training.jammer_power_range_w
        low_db, high_db = 10.0 * math.log10(low_w), 10.0 * math.log10(high_w)
        nominal_db = _spaced(low_db - POWER_SEARCH_DB, high_db + POWER_SEARCH_DB,
                             COARSE_POWER_STEP_DB)
        middle = int(np.abs(nominal_db - (low_db + high_db) / 2.0).argmin())
        return cls(positions, on_edge, in_area, nominal_db + scenario.jammer.efficiency_db,
                   middle)


def _spaced(low: float, high: float, step: float) -> np.ndarray:
    """From ``low`` to at least ``high`` every ``step``, centred on the span."""
    count = math.ceil((high - low) / step - 1e-9) + 1
    return (low + high) / 2.0 + step * (np.arange(count) - (count - 1) / 2.0)


def _square_grid(center: np.ndarray, half_width: float) -> np.ndarray:
    offsets = np.linspace(-half_width, half_width, FINE_NODES)
    return np.stack(np.meshgrid(center[0] + offsets, center[1] + offsets), -1).reshape(-1, 2)



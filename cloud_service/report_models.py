"""How probable the cloud's models make what the receivers report, for the change detector and
the withdrawal test: the no-jammer map (the survey map, or the ideal model where the survey
map keeps to it closely), corrected by a jammer where one is believed (``ReportModels``)."""

from __future__ import annotations

import numpy as np

from cloud_service.estimated_jammer import NO_JAMMER, JammerEstimate, JammerHypotheses
from cloud_service.map_correction import (
    corrected_level_probabilities,
    ideal_level_probabilities,
    ideal_model_spread_db,
)
from cloud_service.no_jammer_belief import fit_shadowing_sigma, sigma_fit_sample
from cloud_service.report_likelihood import REPORT_SIGMA_DB
from cloud_service.sinr_reference import SinrReference
from cloud_service.upload_positions import positions_from_features
from planning.measuring import scenario_features
from planning.networks import SinrMapNetwork, predict_probabilities
from shared.measurements import MeasurementBatch
from shared.radio import RadioModel
from shared.scenario import Scenario


class ReportModels:
    """The cloud's models of reports, built on the ``survey`` map (the no-jammer map learned
    from a survey) and the no-jammer ``reference`` of dB reports. ``survey_xy``: the points
    over the area at which the survey map's departure from the ideal model is fitted."""

    def __init__(self, scenario: Scenario, survey: SinrMapNetwork, reference: SinrReference,
                 survey_xy: np.ndarray):
        self.scenario = scenario
        self.survey = survey
        self.reference = reference
        self.survey_sigma_db = self.shadowing_sigma(survey_xy)
        # How far reports may lie from the ideal model where the survey map keeps to it so
        # closely that the model is the better no-jammer map (None elsewhere): a property of
        # the survey map, fitted once (``no_jammer_probabilities``).
        self.model_spread_db = ideal_model_spread_db(scenario, self.survey_sigma_db)

    def shadowing_sigma(self, xy: np.ndarray) -> float:
        """How far the survey map says the world departs from the ideal model, at ``xy``."""
        xy = sigma_fit_sample(xy)
        return fit_shadowing_sigma(RadioModel(self.scenario, shadowed=False), xy,
                                   self.survey_probabilities(xy).argmax(axis=-1))

    def survey_probabilities(self, xy: np.ndarray) -> np.ndarray:
        return predict_probabilities(self.survey, scenario_features(self.scenario, xy))

    def no_jammer_probabilities(self, xy: np.ndarray) -> np.ndarray:
        """What the cloud believes of each level at points ``xy`` (n, 2) with no jammer, for
        the estimate, the corrected maps and the detector: the ideal model's, give or take
        its spread, where the survey map keeps to it that closely (in icc2021 it errs only
        along its levels' edges); the survey map's elsewhere. The estimate then reads each
        report at that spread, not at the REPORT_SIGMA_DB a world unlike the model needs: at
        1.2 dB a weak jammer's first few contradicting reports explained no jammer near them,
        and the provisional map that followed was less right than the survey map
        (BENCHMARKS.md, "Online SINR mapping", the model as the no-jammer map)."""
        if self.model_spread_db is None:
            return self.survey_probabilities(xy)
        return ideal_level_probabilities(self.scenario, xy, None, self.model_spread_db)

    def report_probability(self, stored: MeasurementBatch, probabilities: np.ndarray,
                           xy: np.ndarray | None, estimate: JammerEstimate | None,
                           estimate_sigma_db: float) -> np.ndarray:
        """How probable each stored report was: by the map in service, or by a model that
        expected it more: the ideal model (with the jammer ``estimate``, if any) where the
        survey map says the world keeps to it closely (``ideal_model_spread_db``), and the
        survey map corrected by the ``estimate`` (at ``estimate_sigma_db``), where one stands
        behind the map.
        A DNN errs along its levels' edges: the survey map of icc2021 is confidently wrong
        there often enough to raise false changes, none when the ideal model vouches for
        such reports; and a DNN fitted to a jammed zone errs along the zone's edge, where the
        lookahead flies its UAVs, so one UAV's reports there contradict it again and again
        (BENCHMARKS.md, "Online SINR mapping": the model vouches; a still jammer after
        adapting). A moved or retuned jammer contradicts the models too, so a change still
        shows.
        ``probabilities``: the map's of every level for each report; ``xy``: where the
        reports were taken (``positions_from_features`` of their features, if None)."""
        if xy is None:
            xy = positions_from_features(self.scenario, stored.features)
        reported = _of_reported(probabilities, stored.levels)
        if estimate is not None and estimate.present:
            model = self.model_probability(stored.levels, xy, estimate, estimate_sigma_db)
        elif self.model_spread_db is not None:
            model = _of_reported(ideal_level_probabilities(
                self.scenario, xy, None, self.model_spread_db), stored.levels)
        else:
            return reported
        # fmax: a report whose position cannot be recovered has the map's probability only.
        return np.fmax(reported, model)

    def model_probability(self, levels: np.ndarray, xy: np.ndarray,
                          jammer: JammerEstimate | JammerHypotheses | None,
                          shadowing_sigma_db: float) -> np.ndarray:
        """How probable the cloud's models make each reported level (n,), taken at ``xy``
        (n, 2), with ``jammer`` (an estimate, a provisional map's hypotheses, or None: no
        jammer): the no-jammer map corrected by it as a receiver reports
        (``corrected_level_probabilities``, at ``shadowing_sigma_db``), or the ideal model
        with it where the survey map keeps to that model, whichever expected the report
        more. NaN where ``xy`` is."""
        model = _of_reported(corrected_level_probabilities(
            self.scenario, self.no_jammer_probabilities, jammer or NO_JAMMER, xy,
            shadowing_sigma_db=shadowing_sigma_db, report_sigma_db=REPORT_SIGMA_DB), levels)
        if self.model_spread_db is None:
            return model
        return np.fmax(model, _of_reported(ideal_level_probabilities(
            self.scenario, xy, jammer, self.model_spread_db), levels))


def _of_reported(probabilities: np.ndarray, levels: np.ndarray) -> np.ndarray:
    """Each row's probability (n, levels) of its reported level (n,)."""
    return np.take_along_axis(probabilities, levels[:, None], -1)[:, 0]

"""What the cloud's jammer estimates read of stored uploads: where each was taken, its level
and SINR, and the cloud's no-jammer beliefs there (``EstimateInputs``)."""

from __future__ import annotations

import numpy as np

from cloud_service.estimated_jammer import JammerEstimate
from cloud_service.jammer_estimation import estimate_jammer
from cloud_service.report_likelihood import REPORT_SIGMA_DB
from cloud_service.report_models import ReportModels
from cloud_service.sinr_memory import SinrMemory
from cloud_service.sinr_reference import SinrReference
from cloud_service.upload_positions import positions_from_features
from shared.measurements import MeasurementBatch


class EstimateInputs:
    """The survey map carries the world's shadowing, which the ideal model lacks: without it
    a jammer cannot be told from a shadow; its probabilities, not only its levels, say how
    near a level's edge each report lies (see ``jammer_estimation``). The dB reference says
    what the SINR was there with no jammer."""

    def __init__(self, models: ReportModels, reference: SinrReference, memory: SinrMemory):
        self.models, self.reference, self.memory = models, reference, memory

    def of(self, data: MeasurementBatch) -> tuple[np.ndarray, np.ndarray, dict]:
        """Where the reports of ``data`` were taken, their levels, and the keywords an
        estimate takes besides: their SINRs and the no-jammer beliefs there."""
        xy = positions_from_features(self.models.scenario, data.features)
        spread_db = self.models.model_spread_db
        return xy, data.levels, {
            "reported_db": data.sinr_db,
            "no_jammer_levels": self.models.no_jammer_probabilities(xy),
            "no_jammer_db": self.reference.at(xy),
            "report_sigma_db": REPORT_SIGMA_DB if spread_db is None else spread_db}

    def window_estimate(self, start: float, end: float) -> JammerEstimate | None:
        """One jammer from the stored uploads taken in [``start``, ``end``) alone."""
        data = self.memory.since(start)
        xy, levels, inputs = self.of(data.take(np.flatnonzero(data.times < end)))
        return estimate_jammer(self.models.scenario, xy, levels, **inputs)

"""Refitting the SINR-mapping network on a change: the uploads since the change plus a prior
over the whole area, points that the no-jammer map (corrected by the jammer, where one is
believed) labels. Fitted to the uploads alone, which lie along a few paths, the network
forgets the survey elsewhere (BENCHMARKS.md, "Online SINR mapping", flying missions with no
jammer)."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from cloud_service.change_handling import RetrainConfig
from cloud_service.simulated_measurements import uniform_positions
from planning.measuring import scenario_features
from planning.networks import SinrMapNetwork
from shared.measurements import MeasurementBatch
from shared.scenario import Scenario

if TYPE_CHECKING:
    from cloud_service.sinr_training import TrainResult


def prior_positions(scenario: Scenario, seed: int) -> np.ndarray:
    """Where the prior labels the area for the network (the mapper draws afresh for each map
    version)."""
    return uniform_positions(scenario, scenario.online_map.prior_points,
                             np.random.default_rng(seed))


def refit_network(scenario: Scenario, network: SinrMapNetwork, data: MeasurementBatch,
                  prior_xy: np.ndarray, prior_levels: np.ndarray, config: RetrainConfig, *,
                  provisional: bool, seed: int, stop: Callable[[], bool]) -> TrainResult:
    """``network`` fitted further to the uploads ``data`` and the prior's levels at
    ``prior_xy``, for ``config.steps`` (``config.provisional_steps`` for a provisional map)."""
    features = np.concatenate([data.features, scenario_features(scenario, prior_xy)])
    levels = np.concatenate([data.levels, prior_levels])
    # Imported here, on the first refit: torch takes seconds to load, and the cloud serves
    # weights from its start (the cloud process loads it meanwhile).
    from cloud_service.sinr_training import train_sinr_map

    return train_sinr_map(
        features, levels, scenario.channel.level_count, network=network,
        steps=config.provisional_steps if provisional else config.steps,
        max_seconds=config.max_seconds, target_accuracy=config.target_accuracy,
        holdout=config.holdout, seed=seed, stop=stop)

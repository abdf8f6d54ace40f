"""How right can any map of a radio world be? Level accuracy is scored point by point against
the true levels (bench_adaptation's 2 m truth grid, no jammer), so it depends on how close
the world's SINR lies to a level's edge, and in a shadowed world it lies close everywhere
the field wanders across an edge within a metre or two. Two ceilings, for both radio worlds:

- a map that knows every point's SINR to within a given error (Gaussian, sd in dB) is right
  with the probability that the error keeps the SINR in its band, averaged over the area;
- a map that knows nothing of the radio model but the reports themselves: around each point,
  the share of uniform reports (with the world's receiver noise) at each level in a square
  (the best side of ``LOCAL_SQUARES_M``), read as the level most reported and, where the
  receiver is noisy, through the probit of its noise as the level its SINR reads in. Ten
  and a hundred reports per square metre: 3 and 30 times the survey map's 30,000.

What the survey network and the online maps reach (bench_adaptation, the survey map's card)
is to be read against these. Beside them, the network that learns the map, fitted two ways
to the survey's reports with their SINR in 0.5 dB steps: the paper's classifier of the level
reported, and a regression of the SINR reported whose level is read off the band edges. One
CPU thread; about a minute.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.ndimage import uniform_filter
from scipy.special import ndtr

from benchmarks.bench_adaptation import TRUTH_SPACING_M, TruthGrid
from benchmarks.common import Figure
from cloud_service.no_jammer_belief import map_reading
from cloud_service.simulated_measurements import simulated_measurements
from cloud_service.sinr_training import (
    L2,
    LEARNING_RATE,
    cosine_rates,
    mini_batches,
    train_sinr_map,
)
from cloud_service.torch_networks import TorchSinrMapNetwork
from planning.networks import predict_probabilities
from shared.radio import RadioModel
from shared.scenario import Scenario, load_scenario

SINR_ERRORS_DB = (0.1, 0.25, 0.5, 1.0)
REPORTS_PER_SQUARE_METRE = (10, 100)
LOCAL_SQUARES_M = (0.5, 1.0, 1.5, 2.5)
_CELL_M = 0.5  # reports are counted per cell of this side, then summed over a square of cells
SEED = 0
SURVEY_REPORTS = 30_000  # jamnav fit-sinr's default survey
FIT_STEPS = 10_000  # jamnav fit-sinr's default: both networks get the same mini-batches


def run() -> list[Figure]:
    figures = []
    for name in ("icc2021", "icc2021-shadowed"):
        scenario = load_scenario(name)
        grid = TruthGrid(scenario)
        radio = grid.radio
        sinr_db = radio.evaluate(grid.xy).sinr_db
        figures.append(Figure(f"{name}: median change of SINR between truth points "
                              f"{TRUTH_SPACING_M:g} m apart", _median_step_db(grid, sinr_db), "dB"))
        for error_db in SINR_ERRORS_DB:
            figures.append(Figure(
                f"{name}: a map knowing the SINR to {error_db:g} dB, right on",
                100.0 * _expected_accuracy(radio, sinr_db, error_db), "%"))
        truth = grid.levels(None)
        for density in REPORTS_PER_SQUARE_METRE:
            best: dict[str, tuple[float, float]] = {}
            for square_m in LOCAL_SQUARES_M:
                local = LocalReportMap(scenario, radio, density, square_m)
                readings = _readings(radio, local.shares(grid.xy))
                for how, levels in readings.items():
                    right = 100.0 * float(np.mean(levels == truth))
                    best[how] = max(best.get(how, (right, square_m)), (right, square_m))
            for how, (right, square_m) in best.items():
                figures.append(Figure(f"{name}: {density} reports per m2, {how} "
                                      f"in {square_m:g} m squares, right on", right, "%"))
        figures += _network_maps(scenario, grid, sinr_db)
    return figures


def _network_maps(scenario: Scenario, grid: TruthGrid, true_db: np.ndarray) -> list[Figure]:
    """The survey's network fitted to its reports as the paper fits it (the level reported)
    and as a regression of the SINR reported: how often each map's level is right, and how
    far its SINR lies from the truth (the classifier's read through the receiver's noise, as
    the cloud reads it; without noise, its probabilities carry no SINR to read)."""
    reporting = scenario.changed({"uav.report": "db"})
    survey = simulated_measurements(reporting, None, SURVEY_REPORTS, np.random.default_rng(SEED))
    radio, truth = grid.radio, grid.levels(None)
    classifier = train_sinr_map(survey.features, survey.levels, scenario.channel.level_count,
                                steps=FIT_STEPS, seed=SEED).network
    probabilities = predict_probabilities(classifier, grid.features)
    regressed_db = _regressed_sinr_db(survey.features, survey.sinr_db, grid.features)
    name = scenario.name
    figures = [
        Figure(f"{name}: the survey's level classifier, right on",
               100.0 * float(np.mean(probabilities.argmax(axis=-1) == truth)), "%"),
        Figure(f"{name}: a regression of the survey's SINR, its level right on",
               100.0 * float(np.mean(radio.level_of(regressed_db) == truth)), "%"),
        Figure(f"{name}: a regression of the survey's SINR, off by (rms)",
               _rms(regressed_db - true_db), "dB"),
    ]
    if radio.measurement_noise_db > 0:
        read_db, _ = map_reading(radio, probabilities, radio.measurement_noise_db)
        figures.append(Figure(f"{name}: the survey's level classifier read as a SINR, off by "
                              "(rms)", _rms(read_db - true_db), "dB"))
    return figures


def _regressed_sinr_db(features: np.ndarray, sinr_db: np.ndarray,
                       at_features: np.ndarray) -> np.ndarray:
    """The SINR (dB) at ``at_features`` of the map network with one output fitted to the
    reports' SINR ``sinr_db`` (standardized) by squared error, with the classifier's
    optimizer, schedule, batches and step budget."""
    torch.manual_seed(SEED)
    x = torch.as_tensor(features, dtype=torch.float32)
    target = torch.as_tensor(sinr_db, dtype=torch.float32)
    mean, spread = target.mean(), target.std()
    module = TorchSinrMapNetwork(x.shape[1], 1)
    module.standardize.fit(x)
    optimizer = torch.optim.Adam(module.parameters(), lr=LEARNING_RATE, weight_decay=L2)
    batches = mini_batches(len(target), torch.Generator().manual_seed(SEED))
    for rate in cosine_rates(FIT_STEPS):
        rows = next(batches)
        optimizer.param_groups[0]["lr"] = rate
        loss = ((module(x[rows])[:, 0] - (target[rows] - mean) / spread) ** 2).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    with torch.no_grad():
        predicted = module(torch.as_tensor(at_features, dtype=torch.float32))[:, 0]
    return (predicted * spread + mean).numpy().astype(np.float64)


def _rms(error: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(error))))


def _median_step_db(grid: TruthGrid, sinr_db: np.ndarray) -> float:
    """How fast the field wanders: the median |difference| of neighbours along a grid row."""
    rows = sinr_db.reshape(-1, len(np.unique(grid.xy[:, 0])))
    return float(np.median(np.abs(np.diff(rows, axis=1))))


def _expected_accuracy(radio: RadioModel, sinr_db: np.ndarray, error_db: float) -> float:
    """The area's mean probability that N(sinr_db, error_db^2) falls in sinr_db's own band."""
    bounds = np.concatenate([[-np.inf], radio.level_edges_db, [np.inf]])
    level = np.searchsorted(radio.level_edges_db, sinr_db)
    inside = ndtr((bounds[level + 1] - sinr_db) / error_db) - ndtr(
        (bounds[level] - sinr_db) / error_db)
    return float(inside.mean())


class LocalReportMap:
    """A map that knows nothing of the radio model: at each point, the shares of
    ``density`` uniform reports per square metre (the world's receiver noise included, no
    jammer) at each level, counted in a square of side ``square_m`` around it. What a survey
    that dense gives without a model; bench_correction flies it."""

    def __init__(self, scenario: Scenario, radio: RadioModel, density: int, square_m: float):
        area = scenario.area
        rng = np.random.default_rng(SEED)
        count = int(density * (area.x_max - area.x_min) * (area.y_max - area.y_min))
        reported_xy = rng.uniform((area.x_min, area.y_min), (area.x_max, area.y_max), (count, 2))
        reported = radio.measured_reports(radio.evaluate(reported_xy).sinr_db, rng).level
        self.origin = np.array([area.x_min, area.y_min])
        self.shape = (int(np.ceil((area.y_max - area.y_min) / _CELL_M)),
                      int(np.ceil((area.x_max - area.x_min) / _CELL_M)))
        levels = len(radio.level_edges_db) + 1
        counts = np.zeros((levels, *self.shape))
        np.add.at(counts, (reported, *self._cells(reported_xy)), 1.0)
        square = int(round(square_m / _CELL_M))
        local = np.stack([uniform_filter(counts[level], square, mode="nearest")
                          for level in range(levels)], axis=-1)
        self._shares = local / np.maximum(local.sum(axis=-1, keepdims=True), 1e-12)

    def _cells(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        index = ((xy - self.origin) / _CELL_M).astype(np.int64)
        return (np.clip(index[..., 1], 0, self.shape[0] - 1),
                np.clip(index[..., 0], 0, self.shape[1] - 1))

    def shares(self, xy: np.ndarray) -> np.ndarray:
        """The shares of reports at each level (..., levels) around the points ``xy``."""
        return self._shares[self._cells(np.asarray(xy))]


def _readings(radio: RadioModel, shares: np.ndarray) -> dict[str, np.ndarray]:
    """Levels from report ``shares`` (n, levels): the most reported one, and with a noisy
    receiver the band of the SINR that the cloud's reading of a map puts it in
    (``map_reading``, at the receiver's own noise)."""
    readings = {"the level most reported": shares.argmax(axis=-1)}
    if radio.measurement_noise_db > 0:
        read_db, _ = map_reading(radio, shares, radio.measurement_noise_db)
        readings["the level read through the noise"] = np.searchsorted(radio.level_edges_db,
                                                                        read_db)
    return readings

"""The coverage maps the console draws, on one display grid over the area: the map the cloud
serves now (its network evaluated as an agent evaluates it, or its raster read), and the true
map, the world's radio model with the jammer in force (shadowing included)."""

from __future__ import annotations

import base64
from typing import Any

import numpy as np

from planning.maps import LevelRaster
from planning.measuring import scenario_features
from planning.networks import from_bytes, predict_levels
from shared.cloud_messages import SinrMap
from shared.measurements import MeasurementSpec
from shared.radio import JammerParams, RadioModel
from shared.scenario import Scenario

DISPLAY_CELLS = 100  # along the area's longer side: 1 m cells in the shipped 100 m area


class CoverageMaps:
    def __init__(self, scenario: Scenario, cells: int = DISPLAY_CELLS):
        self.scenario = scenario
        area = scenario.area
        self.spacing = max(area.x_max - area.x_min, area.y_max - area.y_min) / cells
        # Cell centres, row 0 at the area's lowest y.
        xs = np.arange(area.x_min + self.spacing / 2, area.x_max, self.spacing)
        ys = np.arange(area.y_min + self.spacing / 2, area.y_max, self.spacing)
        self.points = np.stack(np.meshgrid(xs, ys, indexing="xy"), axis=-1)
        self.x0, self.y0 = float(xs[0]), float(ys[0])
        self.features = scenario_features(scenario, self.points)
        self.radio = RadioModel(scenario)
        self.expected = {"kind": "sinr_map", "levels": scenario.channel.level_count,
                         "input_size": MeasurementSpec.of(scenario).feature_size}

    def served(self, update: SinrMap) -> np.ndarray:
        """The levels of a published map at the display grid; WeightsError for a network an
        agent would refuse too."""
        if update.grid is None:
            return predict_levels(from_bytes(update.data, expected=self.expected),
                                  self.features)
        grid = update.grid
        return LevelRaster(update.levels(), grid.x0, grid.y0, grid.spacing).level_at(self.points)

    def true(self, jammers: tuple[JammerParams, ...]) -> np.ndarray:
        """The world's levels (shadowing included) under ``jammers``, where they are now."""
        return self.radio.evaluate(self.points, jammers).level

    def payload(self, levels: np.ndarray, **about: Any) -> dict[str, Any]:
        """What the page draws: the grid and its levels as base64 int8, row-major from the
        lowest y, with ``about`` (version, jammer...)."""
        rows, cols = levels.shape
        data = np.clip(levels, 0, self.scenario.channel.level_count - 1).astype(np.int8)
        return {**about, "x0": self.x0, "y0": self.y0, "spacing": self.spacing, "rows": rows,
                "cols": cols, "levels": base64.b64encode(data.tobytes()).decode("ascii")}

"""The radio model of the paper, Eq. (1)-(5), vectorized over points.

Readings of the paper's typos (see the scenario file): Eq. (2) attenuates by 12 x^2 dB capped at
G_m dB; Eq. (5) is a path loss (negative exponent), scaled by the jammer's efficiency, the share
of its nominal power that reaches the UAV receiver as in-band interference.

This is the only implementation of the radio model: the world, training, evaluation, the cloud
and the command line all call it.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from shared.scenario import Scenario

_LN10 = math.log(10.0)
_CHUNK = 8192  # points per block: keeps the (points x GBS) temporaries inside the CPU cache


class JammerParams(NamedTuple):
    """A jammer at run time; each field is a float or an array broadcastable to the points."""

    x: float | np.ndarray
    y: float | np.ndarray
    power_w: float | np.ndarray
    height_m: float | np.ndarray


class RadioReading(NamedTuple):
    sinr: np.ndarray  # linear
    sinr_db: np.ndarray
    level: np.ndarray  # int8, 0 = below the threshold T_s
    serving_gbs: np.ndarray  # int64 index into the scenario's GBS positions


class RadioModel:
    """SINR at UAV altitude for the GBS layout of one scenario, with any jammer or none."""

    def __init__(self, scenario: Scenario):
        gbs, channel = scenario.gbs, scenario.channel
        self.altitude_m = scenario.uav.altitude_m
        self.gbs_xy = np.asarray(gbs.positions, dtype=np.float64)
        self.gbs_height_m = gbs.height_m
        self.gbs_power_w = gbs.power_w
        self.alpha = channel.path_loss_exponent
        self.noise_w = channel.noise_w
        self.threshold_db = channel.sinr_threshold_db
        self.level_edges_db = np.asarray(channel.level_edges_db, dtype=np.float64)
        self.jammer_efficiency = 10.0 ** (scenario.jammer.efficiency_db / 10.0)
        self.default_jammer = self.jammer_of(scenario)
        self._height_gap = self.altitude_m - self.gbs_height_m
        self._tilt_rad = math.radians(gbs.tilt_deg)
        self._beamwidth_rad = math.radians(gbs.beamwidth_3db_deg)
        self._max_attenuation_db = gbs.max_attenuation_db

    @staticmethod
    def jammer_of(scenario: Scenario) -> JammerParams | None:
        jam = scenario.jammer
        if not jam.enabled or jam.power_w == 0:
            return None
        return JammerParams(jam.x, jam.y, jam.power_w, jam.height_m)

    def gbs_received_power(self, xy: np.ndarray) -> np.ndarray:
        """Received power from every GBS, numerator of Eq. (1): shape (..., K)."""
        xy = np.asarray(xy, dtype=np.float64)
        dx = xy[..., 0, None] - self.gbs_xy[:, 0]
        dy = xy[..., 1, None] - self.gbs_xy[:, 1]
        horizontal_sq = dx * dx + dy * dy
        slant_sq = horizontal_sq + self._height_gap**2
        # Eq. (2) as 3GPP intends: 12 x^2 dB of attenuation off boresight, capped at G_m dB.
        off_boresight = (
            np.arctan2(-self._height_gap, np.sqrt(horizontal_sq)) - self._tilt_rad
        ) / self._beamwidth_rad
        attenuation_db = np.minimum(12.0 * off_boresight * off_boresight, self._max_attenuation_db)
        # G_V / L = sin(elevation) * slant^-alpha = gap * slant_sq^-((alpha+1)/2), Eq. (3)-(4).
        exponent = -0.5 * (self.alpha + 1.0) * np.log(slant_sq) - (_LN10 / 10.0) * attenuation_db
        return (self.gbs_power_w * self._height_gap) * np.exp(exponent)

    def jammer_interference(self, xy: np.ndarray, jammer: JammerParams | None) -> np.ndarray:
        """I_J of Eq. (5) with a negative path-loss exponent, times the jamming efficiency."""
        xy = np.asarray(xy, dtype=np.float64)
        if jammer is None:
            return np.zeros(xy.shape[:-1])
        gap = self.altitude_m - np.asarray(jammer.height_m, dtype=np.float64)
        dx = xy[..., 0] - jammer.x
        dy = xy[..., 1] - jammer.y
        slant_sq = dx * dx + dy * dy + gap * gap
        power = np.asarray(jammer.power_w, dtype=np.float64) * self.jammer_efficiency
        return power * gap * slant_sq ** (-0.5 * (self.alpha + 1.0))

    def level_of(self, sinr_db: np.ndarray) -> np.ndarray:
        """Quantized level: 0 below T_s, then one level per band between the edges."""
        return np.searchsorted(self.level_edges_db, sinr_db, side="right").astype(np.int8)

    def evaluate(self, xy: np.ndarray, jammer: JammerParams | None = None) -> RadioReading:
        """SINR (Eq. 1) at every point of ``xy`` (shape (..., 2)); serving GBS = strongest."""
        xy = np.asarray(xy, dtype=np.float64)
        batch_shape = xy.shape[:-1]
        flat = xy.reshape(-1, 2)
        flat_jammer = _flatten_jammer(jammer, batch_shape)
        n = flat.shape[0]
        sinr = np.empty(n)
        serving = np.empty(n, dtype=np.int64)
        for start in range(0, n, _CHUNK):
            block = slice(start, start + _CHUNK)
            received = self.gbs_received_power(flat[block])
            best = received.argmax(axis=1)
            signal = np.take_along_axis(received, best[:, None], axis=1)[:, 0]
            block_jammer = None
            if flat_jammer is not None:
                block_jammer = JammerParams(
                    *(f if np.ndim(f) == 0 else f[block] for f in flat_jammer)
                )
            denominator = (
                self.noise_w
                + self.jammer_interference(flat[block], block_jammer)
                + received.sum(axis=1)
                - signal
            )
            sinr[block] = signal / denominator
            serving[block] = best
        sinr_db = 10.0 * np.log10(sinr)
        return RadioReading(
            sinr.reshape(batch_shape),
            sinr_db.reshape(batch_shape),
            self.level_of(sinr_db).reshape(batch_shape),
            serving.reshape(batch_shape),
        )

    def grid(
        self, scenario: Scenario, resolution: int, jammer: JammerParams | None
    ) -> tuple[np.ndarray, np.ndarray, RadioReading]:
        """The map over the scenario's area on a ``resolution`` x ``resolution`` grid."""
        area = scenario.area
        xs = np.linspace(area.x_min, area.x_max, resolution)
        ys = np.linspace(area.y_min, area.y_max, resolution)
        points = np.stack(np.meshgrid(xs, ys, indexing="xy"), axis=-1)
        return xs, ys, self.evaluate(points, jammer)


def _flatten_jammer(jammer: JammerParams | None, batch_shape: tuple[int, ...]):
    if jammer is None:
        return None
    fields = []
    for value in jammer:
        if np.ndim(value) == 0:
            fields.append(float(value))
        else:
            fields.append(np.broadcast_to(np.asarray(value, dtype=np.float64), batch_shape).ravel())
    return JammerParams(*fields)

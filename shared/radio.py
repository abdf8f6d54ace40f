"""The radio model of the paper, Eq. (1)-(5), vectorized over points.

Readings of the paper's typos (see the scenario file): Eq. (2) attenuates by 12 x^2 dB capped at
G_m dB; Eq. (5) is a path loss (negative exponent), scaled by the jammer's efficiency, the share
of its nominal power that reaches the UAV receiver as in-band interference.

This is the only implementation of the radio model: the world, training, evaluation, the cloud
and the command line all call it. The received powers, most of its time, run compiled
(``shared/_radio.pyx``) unless ``JAMNAV_PLANNER=reference`` chooses their numpy reference. A
scenario with a ``[shadowing]`` section adds log-normal shadowing to every link
(``shared/shadowing.py``): that is the world's truth. The same model built with
``shadowed=False`` is the idealized Eq. (1)-(5) for the same layout, all that the operator's
cloud can know.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from types import ModuleType
from typing import NamedTuple

import numpy as np

from shared.compiled_core import chosen_core, compiled_module
from shared.scenario import Scenario
from shared.shadowing import shadowing_field

_LN10 = math.log(10.0)
_CHUNK = 8192  # points per block: keeps the (points x GBS) temporaries inside the CPU cache


class JammerParams(NamedTuple):
    """A jammer at run time; each field is a float or an array broadcastable to the points."""

    x: float | np.ndarray
    y: float | np.ndarray
    power_w: float | np.ndarray
    height_m: float | np.ndarray


# The jammers the radio sums in Eq. (3)'s interference: one, several, or none (None or ()).
Jammers = JammerParams | Sequence[JammerParams] | None


def as_jammers(jammers: Jammers) -> tuple[JammerParams, ...]:
    if jammers is None:
        return ()
    if isinstance(jammers, JammerParams):
        return (jammers,)
    return tuple(jammers)


class RadioReading(NamedTuple):
    """The radio model's answer at some points: the SINR (linear and dB), its quantized
    level and the ground station that serves each point."""

    sinr: np.ndarray  # linear
    sinr_db: np.ndarray
    level: np.ndarray  # int8, 0 = below the threshold T_s
    serving_gbs: np.ndarray  # int64 index into the scenario's GBS positions


class Reports(NamedTuple):
    """What UAV receivers report at some points."""

    level: np.ndarray  # int8, of the measured SINR
    sinr_db: np.ndarray  # the measured SINR in report steps; NaN where only levels are reported


def radio_core() -> ModuleType | None:
    """The radio's compiled core (``shared/_radio.pyx``), or None where ``JAMNAV_PLANNER``
    chooses the numpy reference; a missing or stale core is a CompiledCoreError, which a
    process meets as it starts."""
    return None if chosen_core() == "reference" else _compiled_radio()


@functools.cache
def _compiled_radio() -> ModuleType:
    return compiled_module("shared._radio")


class RadioModel:
    """SINR at UAV altitude for the GBS layout of one scenario, with any jammers or none.

    ``shadowed``: apply the scenario's shadowing, if it has any (the world's truth); without,
    the idealized Eq. (1)-(5).
    """

    def __init__(self, scenario: Scenario, *, shadowed: bool = True):
        self._core = radio_core()
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
        self.default_jammers = self.jammers_of(scenario)
        self._height_gap = self.altitude_m - self.gbs_height_m
        self._tilt_rad = math.radians(gbs.tilt_deg)
        self._beamwidth_rad = math.radians(gbs.beamwidth_3db_deg)
        self._max_attenuation_db = gbs.max_attenuation_db
        self.measurement_noise_db = scenario.uav.measurement_noise_db
        self.report_step_db = (scenario.uav.report_step_db if scenario.uav.report == "db"
                               else None)
        self.shadowing = shadowing_field(scenario) if shadowed else None
        # (K, K): whether two GBSs share a channel; None when all do (the paper's case, kept to
        # the plain sum, bit for bit).
        self._same_channel = (
            None if gbs.channels is None
            else np.asarray(gbs.channels)[:, None] == np.asarray(gbs.channels)[None, :])

    @staticmethod
    def jammer_of(scenario: Scenario) -> JammerParams | None:
        """The scenario's first jammer where it starts, if it is on."""
        jam = scenario.jammer
        if not jam.enabled or jam.power_w == 0:
            return None
        return JammerParams(jam.x, jam.y, jam.power_w, jam.height_m)

    @staticmethod
    def jammers_of(scenario: Scenario) -> tuple[JammerParams, ...]:
        """The scenario's jammers where they start, each on whatever its schedule."""
        return tuple(JammerParams(jam.x, jam.y, jam.power_w, jam.height_m)
                     for jam in scenario.flown_jammers)

    def gbs_received_power(self, xy: np.ndarray) -> np.ndarray:
        """Received power from every GBS, numerator of Eq. (1), with the world's shadowing if
        it has any: shape (..., K)."""
        received = self._ideal_gbs_received_power(xy)
        if self.shadowing is None:
            return received
        return received * _gain_of(self.shadowing.at(xy)[..., :-1])

    def jammer_interference(self, xy: np.ndarray, jammers: Jammers) -> np.ndarray:
        """I_J of Eq. (5) with a negative path-loss exponent, times the jamming efficiency,
        summed over the jammers, with the world's shadowing if it has any: one field for every
        jammer link, as it is the receiver's surroundings that shadow them."""
        interference = self._ideal_jammer_interference(xy, jammers)
        if self.shadowing is None or not as_jammers(jammers):
            return interference
        return interference * _gain_of(self.shadowing.at(xy)[..., -1])

    def _ideal_gbs_received_power(self, xy: np.ndarray) -> np.ndarray:
        xy = np.asarray(xy, dtype=np.float64)
        if self._core is None:
            return self._reference_gbs_received_power(xy)
        points = np.ascontiguousarray(xy.reshape(-1, 2))
        received = np.empty((len(points), len(self.gbs_xy)))
        self._core.gbs_received_power(
            points, self.gbs_xy, self._height_gap, self._tilt_rad, self._beamwidth_rad,
            self._max_attenuation_db, self.alpha, self.gbs_power_w, _LN10, received)
        return received.reshape(xy.shape[:-1] + (len(self.gbs_xy),))

    def _reference_gbs_received_power(self, xy: np.ndarray) -> np.ndarray:
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

    def _ideal_jammer_interference(self, xy: np.ndarray, jammers: Jammers) -> np.ndarray:
        xy = np.asarray(xy, dtype=np.float64)
        each = [self._one_jammer_interference(xy, jammer) for jammer in as_jammers(jammers)]
        return sum(each[1:], each[0]) if each else np.zeros(xy.shape[:-1])

    def _one_jammer_interference(self, xy: np.ndarray, jammer: JammerParams) -> np.ndarray:
        gap = self.altitude_m - np.asarray(jammer.height_m, dtype=np.float64)
        dx = xy[..., 0] - jammer.x
        dy = xy[..., 1] - jammer.y
        slant_sq = dx * dx + dy * dy + gap * gap
        power = np.asarray(jammer.power_w, dtype=np.float64) * self.jammer_efficiency
        return power * gap * slant_sq ** (-0.5 * (self.alpha + 1.0))

    def _powers(self, xy: np.ndarray, jammers: tuple[JammerParams, ...]):
        """Received GBS powers (n, K) and jammer interference (n,) at points (n, 2), with the
        shadowing fields interpolated once for both."""
        received = self._ideal_gbs_received_power(xy)
        interference = self._ideal_jammer_interference(xy, jammers)
        if self.shadowing is not None:
            gain = _gain_of(self.shadowing.at(xy))
            received = received * gain[:, :-1]
            interference = interference * gain[:, -1]
        return received, interference

    def serving(self, received: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """From received GBS powers (n, K): the serving GBS (the strongest), its power, and the
        interference of the other GBSs on its channel."""
        best = received.argmax(axis=1)
        signal = np.take_along_axis(received, best[:, None], axis=1)[:, 0]
        if self._same_channel is None:
            return best, signal, received.sum(axis=1) - signal
        # Each point's row summed on its own (not a matrix product, whose blocking depends on
        # how many points there are), so a point reads the same in any batch.
        on_channel = np.where(self._same_channel[best], received, 0.0)
        return best, signal, on_channel.sum(axis=1) - signal

    def sinr_of(self, signal: np.ndarray, co_channel: np.ndarray,
                interference: np.ndarray | float) -> np.ndarray:
        """Eq. (1) from its parts (``serving``'s signal and co-channel interference, and the
        jammer's): linear SINR."""
        return signal / (self.noise_w + interference + co_channel)

    def level_of(self, sinr_db: np.ndarray) -> np.ndarray:
        """Quantized level: 0 below T_s, then one level per band between the edges."""
        return np.searchsorted(self.level_edges_db, sinr_db, side="right").astype(np.int8)

    def measured_sinr_db(self, sinr_db: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """The SINR a UAV's receiver measures where the true one is ``sinr_db``. Exact
        receivers draw nothing from ``rng``, so the idealized world's random streams are
        those it always had."""
        sinr_db = np.asarray(sinr_db, dtype=np.float64)
        if self.measurement_noise_db == 0:
            return sinr_db
        return sinr_db + rng.normal(0.0, self.measurement_noise_db, size=sinr_db.shape)

    def measured_reports(self, sinr_db: np.ndarray, rng: np.random.Generator) -> Reports:
        """What a UAV's receiver reports where the true SINR is ``sinr_db``. The level is that
        of the measured SINR, not of its rounded report, so that a world reports the same
        levels, draw for draw, whichever it reports: dB reports only add to level ones."""
        measured_db = self.measured_sinr_db(sinr_db, rng)
        if self.report_step_db is None:
            reported_db = np.full(measured_db.shape, np.nan)
        else:
            reported_db = np.round(measured_db / self.report_step_db) * self.report_step_db
        return Reports(self.level_of(measured_db), reported_db)

    def evaluate(self, xy: np.ndarray, jammers: Jammers = None) -> RadioReading:
        """SINR (Eq. 1) at every point of ``xy`` (shape (..., 2)); serving GBS = strongest.
        Each jammer's fields are floats or arrays broadcastable to the points."""
        xy = np.asarray(xy, dtype=np.float64)
        batch_shape = xy.shape[:-1]
        flat = xy.reshape(-1, 2)
        flat_jammers = [_flatten_jammer(jammer, batch_shape) for jammer in as_jammers(jammers)]
        n = flat.shape[0]
        sinr = np.empty(n)
        serving = np.empty(n, dtype=np.int64)
        for start in range(0, n, _CHUNK):
            block = slice(start, start + _CHUNK)
            block_jammers = tuple(
                JammerParams(*(f if np.ndim(f) == 0 else f[block] for f in jammer))
                for jammer in flat_jammers)
            received, interference = self._powers(flat[block], block_jammers)
            best, signal, co_channel = self.serving(received)
            sinr[block] = self.sinr_of(signal, co_channel, interference)
            serving[block] = best
        sinr_db = 10.0 * np.log10(sinr)
        return RadioReading(
            sinr.reshape(batch_shape),
            sinr_db.reshape(batch_shape),
            self.level_of(sinr_db).reshape(batch_shape),
            serving.reshape(batch_shape),
        )

    def grid(
        self, scenario: Scenario, resolution: int, jammers: Jammers
    ) -> tuple[np.ndarray, np.ndarray, RadioReading]:
        """The map over the scenario's area on a ``resolution`` x ``resolution`` grid."""
        area = scenario.area
        xs = np.linspace(area.x_min, area.x_max, resolution)
        ys = np.linspace(area.y_min, area.y_max, resolution)
        points = np.stack(np.meshgrid(xs, ys, indexing="xy"), axis=-1)
        return xs, ys, self.evaluate(points, jammers)


def _gain_of(shadowing_db: np.ndarray) -> np.ndarray:
    return np.exp((_LN10 / 10.0) * shadowing_db)


def _flatten_jammer(jammer: JammerParams, batch_shape: tuple[int, ...]) -> JammerParams:
    fields = []
    for value in jammer:
        if np.ndim(value) == 0:
            fields.append(float(value))
        else:
            fields.append(np.broadcast_to(np.asarray(value, dtype=np.float64), batch_shape).ravel())
    return JammerParams(*fields)

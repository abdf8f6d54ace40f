"""Log-normal shadowing: spatially correlated Gaussian fields (in dB) over the scenario's area.

One field per transmitter: field k (k < K) shadows the link from GBS k, field K the jammer's
link. Each is indexed by the receiver's (the UAV's) position only, for any jammer position:
at 50 m up, what a link passes through changes with where the UAV is, and a field over the
jammer's position as well would be four-dimensional for little gain in realism.

Correlation over distance d follows Gudmundson's exponential model, R(d) = exp(-d / d_c). A
field is sampled exactly on a grid by circulant embedding: the covariance, laid on a periodic
grid large enough that it has decayed before it wraps round, is diagonalized by the 2-D FFT;
scaling white noise by the square root of its eigenvalues and transforming back gives the
field. Between grid nodes the field is interpolated bilinearly; beyond the grid it is held at
its edge value.
"""

from __future__ import annotations

import math
from functools import lru_cache
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

if TYPE_CHECKING:
    from shared.scenario import Area, Scenario, Shadowing

# The periodic grid spans at least this many decorrelation distances per side, so that the
# covariance has fallen to exp(-5) where it wraps round: its embedding is then nonnegative
# definite but for eigenvalues at the level of rounding, which are set to zero.
_PERIOD_IN_DECORRELATIONS = 10
# A periodic grid beyond this many points per side (a 1,000 m area at 1 m spacing) is a
# mistake in the scenario, a spacing far too fine for the area or a decorrelation distance far
# too long for the spacing, and drawing it would take gigabytes.
MAX_GRID_SIDE = 2048


class FieldGrid(NamedTuple):
    """Where a scenario's fields are sampled, and the periodic grid they are drawn on."""

    x0: float  # position of node (0, 0)
    y0: float
    spacing: float
    nx: int  # nodes along x
    ny: int
    period_x: int  # nodes of the periodic grid along x
    period_y: int


def field_grid(shadowing: Shadowing, area: Area) -> FieldGrid:
    """The area plus a margin of one decorrelation distance on every side: a UAV straying a
    little out of the area still sees a field that varies."""
    spacing, margin = shadowing.field_spacing_m, shadowing.decorrelation_m
    nx = math.ceil((area.x_max - area.x_min + 2 * margin) / spacing) + 1
    ny = math.ceil((area.y_max - area.y_min + 2 * margin) / spacing) + 1
    decay = math.ceil(_PERIOD_IN_DECORRELATIONS * shadowing.decorrelation_m / spacing)
    return FieldGrid(area.x_min - margin, area.y_min - margin, spacing, nx, ny,
                     _fast_length(max(2 * (nx - 1), decay)),
                     _fast_length(max(2 * (ny - 1), decay)))


def _fast_length(n: int) -> int:
    """The smallest length >= n with no prime factor above 5: the FFT is fastest there."""
    best = 1 << max(0, n - 1).bit_length()
    power5 = 1
    while power5 < best:
        power3 = power5
        while power3 < best:
            candidate = power3 << max(0, math.ceil(n / power3) - 1).bit_length()
            best = min(best, candidate)
            power3 *= 3
        power5 *= 5
    return best


class ShadowingField:
    """Shadowing in dB of every transmitter's link at any receiver position.

    ``values_db`` (ny, nx, K + 1): the fields at the grid nodes, GBS links first, the jammer
    link last. ``clipped_share``: the share of the embedding's spectrum that was negative and
    set to zero (a measure of how far the sampled covariance departs from the stated one).
    """

    def __init__(self, shadowing: Shadowing, area: Area, gbs_count: int):
        self.grid = grid = field_grid(shadowing, area)
        spectrum = _embedding_spectrum(grid, shadowing.decorrelation_m)
        self.clipped_share = float(np.maximum(-spectrum, 0.0).sum() / np.abs(spectrum).sum())
        # Zeroing the negative eigenvalues adds variance; rescaling keeps R(0) = 1 exactly.
        spectrum = np.maximum(spectrum, 0.0)
        amplitude = np.sqrt(spectrum / spectrum.sum())
        sigmas = [shadowing.gbs_sigma_db] * gbs_count + [shadowing.jammer_sigma_db]
        fields = [
            sigma * _unit_field(amplitude, grid, np.random.SeedSequence([shadowing.seed, k]))
            for k, sigma in enumerate(sigmas)
        ]
        self.values_db = np.stack(fields, axis=-1)
        self.values_db.flags.writeable = False  # shared through the cache
        self._flat = self.values_db.reshape(-1, len(sigmas))
        self._corner_offsets = np.array([0, 1, grid.nx, grid.nx + 1])  # in self._flat's rows

    def node_positions(self) -> tuple[np.ndarray, np.ndarray]:
        """x (nx,) and y (ny,) of the grid nodes."""
        grid = self.grid
        return (grid.x0 + grid.spacing * np.arange(grid.nx),
                grid.y0 + grid.spacing * np.arange(grid.ny))

    def at(self, xy: np.ndarray) -> np.ndarray:
        """Shadowing in dB at receiver positions ``xy`` (..., 2): shape (..., K + 1)."""
        grid = self.grid
        xy = np.asarray(xy, dtype=np.float64)
        gx = np.clip((xy[..., 0] - grid.x0) / grid.spacing, 0.0, grid.nx - 1)
        gy = np.clip((xy[..., 1] - grid.y0) / grid.spacing, 0.0, grid.ny - 1)
        ix = np.minimum(gx.astype(np.intp), grid.nx - 2)
        iy = np.minimum(gy.astype(np.intp), grid.ny - 2)
        tx, ty = gx - ix, gy - iy
        sx, sy = 1.0 - tx, 1.0 - ty
        weights = np.stack([sx * sy, tx * sy, sx * ty, tx * ty], axis=-1)
        corners = np.take(self._flat, (iy * grid.nx + ix)[..., None] + self._corner_offsets,
                          axis=0)
        return np.einsum("...c,...ct->...t", weights, corners)


def _embedding_spectrum(grid: FieldGrid, decorrelation_m: float) -> np.ndarray:
    """Eigenvalues of the exponential covariance laid on the periodic grid (unit variance)."""
    lag_x = np.arange(grid.period_x)
    lag_y = np.arange(grid.period_y)
    lag_x = np.minimum(lag_x, grid.period_x - lag_x) * grid.spacing
    lag_y = np.minimum(lag_y, grid.period_y - lag_y) * grid.spacing
    covariance = np.exp(-np.hypot(lag_y[:, None], lag_x[None, :]) / decorrelation_m)
    return np.fft.fft2(covariance).real  # real: the covariance is even on the periodic grid


def _unit_field(
    amplitude: np.ndarray, grid: FieldGrid, seed: np.random.SeedSequence
) -> np.ndarray:
    """One zero-mean, unit-variance field on the grid's nodes, shape (ny, nx)."""
    rng = np.random.default_rng(seed)
    white = rng.standard_normal((2, *amplitude.shape))
    # With complex white noise of variance 2, the transform's real part has the covariance
    # whose spectrum is amplitude**2 times the grid size (its imaginary part is a second,
    # independent field, left unused so that every transmitter has a seed of its own).
    periodic = np.fft.fft2(amplitude * (white[0] + 1j * white[1]))
    return np.ascontiguousarray(periodic.real[: grid.ny, : grid.nx])


@lru_cache(maxsize=8)
def _cached_field(shadowing: Shadowing, area: Area, gbs_count: int) -> ShadowingField:
    return ShadowingField(shadowing, area, gbs_count)


def shadowing_field(scenario: Scenario) -> ShadowingField | None:
    """The scenario's shadowing fields, drawn once per shadowing section and area."""
    if scenario.shadowing is None:
        return None
    return _cached_field(scenario.shadowing, scenario.area, len(scenario.gbs.positions))

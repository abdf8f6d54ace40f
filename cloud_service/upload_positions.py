"""Where each upload was taken, recovered from its features: an upload says where the UAV was
only through the offsets of its nearest GBSs (``positions_from_features``)."""

from __future__ import annotations

import numpy as np

from planning.measuring import scenario_features
from shared.measurements import feature_size, features_per_gbs
from shared.scenario import Scenario

# Offsets that agree to this (mean, metres) are the same place: float32 features of points
# within ~100 m carry ~1e-5 m of rounding.
_SAME_PLACE_M = 1e-3


def positions_from_features(scenario: Scenario, features: np.ndarray) -> np.ndarray:
    """UAV positions (n, 2) that produced the uploaded ``features`` (n, ``feature_size``).

    Each GBS in turn (or only the one the features name, with ``policy.nearest_gbs_position``)
    is taken as the nearest one: the UAV then sits at that GBS minus the
    first (dx, dy). The candidate kept is the one whose own K_n nearest GBSs lie at the
    uploaded offsets, exact to the features' float32 precision. Offsets are compared as
    sorted lists of dx and of dy, so GBSs at equal distance (whose order rounding may swap)
    do not matter. A row is NaN where no place gives its offsets (features of another
    layout, or tampered with), and where two places do: with K_n below the GBS count a
    regular layout repeats itself, and places a lattice step apart see the same nearest
    offsets (with every GBS in view, as in icc2021, none do; naming the nearest GBS, as the
    city does, settles it).
    """
    nearby, per_gbs = scenario.policy.nearby_gbs, features_per_gbs(scenario)
    flat = np.asarray(features, dtype=np.float64).reshape(-1, feature_size(scenario))
    features = flat[:, :nearby * per_gbs].reshape(-1, nearby, per_gbs)
    if scenario.policy.nearest_gbs_position:  # the measurement names its nearest GBS
        nearest = flat[:, None, -2:]
    else:
        gbs_xy = np.asarray(scenario.gbs.positions, dtype=np.float64)
        nearest = np.broadcast_to(gbs_xy, (len(flat), *gbs_xy.shape))
    candidates = nearest - features[:, None, 0, :2]  # (n, candidates, 2)
    seen = scenario_features(scenario, candidates)[..., :nearby * per_gbs].reshape(
        *candidates.shape[:2], nearby, per_gbs)
    uploaded = np.sort(features[:, None, :, :2], axis=2)
    miss = np.abs(np.sort(seen[..., :2], axis=2) - uploaded).mean(axis=(2, 3))
    rows = np.arange(len(features))
    xy = candidates[rows, miss.argmin(axis=1)]
    elsewhere = np.abs(candidates - xy[:, None, :]).max(-1) > _SAME_PLACE_M
    ambiguous = ((miss < _SAME_PLACE_M) & elsewhere).any(axis=1)
    xy[ambiguous | (miss.min(axis=1) > _SAME_PLACE_M)] = np.nan
    return xy

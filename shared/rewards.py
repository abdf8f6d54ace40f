"""The paper's reward R = R_c + R_s + R_d + R_t, written once for the world and the lookahead."""

from __future__ import annotations

import numpy as np

from shared.kinematics import clamp
from shared.scenario import Scenario


class RewardModel:
    """The paper's reward R = R_c + R_s + R_d + R_t for a step, the one the world books and
    the lookahead predicts."""

    def __init__(self, scenario: Scenario):
        rewards = scenario.rewards
        self.collision = rewards.collision
        self.discomfort = rewards.discomfort_distance_m
        self.arrival = rewards.arrival
        self.step = rewards.step
        self.check_every = scenario.connectivity_check_steps
        # R_s by quantized level: level 0 is below T_s, level 1 the marginal band (if the
        # scenario has one), higher levels are connected.
        by_level = np.zeros(scenario.channel.level_count)
        by_level[0] = rewards.disconnected
        if by_level.shape[0] > 2:
            by_level[1] = rewards.marginal
        self.connectivity_by_level = by_level

    def is_check_step(self, step: np.ndarray) -> np.ndarray:
        """(P1.a): connectivity is checked when the step index is divisible by n_t."""
        return np.asarray(step) % self.check_every == 0

    def connectivity(self, level: np.ndarray, check_now: np.ndarray) -> np.ndarray:
        """R_s from the quantized level at the next position."""
        return np.where(check_now, self.connectivity_by_level[level], 0.0)

    def proximity(self, gap: np.ndarray) -> np.ndarray:
        """R_c from the smallest gap (distance minus both radii) to any other UAV in the step:
        the collision reward at contact, rising linearly to 0 at the discomfort distance."""
        if self.discomfort > 0:
            share = clamp(1.0 - gap / self.discomfort, 0.0, 1.0)
        else:
            share = (gap <= 0).astype(np.float64)
        return np.where(gap <= 0, self.collision, self.collision * share)

    def total(
        self, level: np.ndarray, check_now: np.ndarray, gap: np.ndarray, arrived: np.ndarray
    ) -> np.ndarray:
        return (
            self.proximity(gap)
            + self.connectivity(level, check_now)
            + np.where(arrived, self.arrival, 0.0)
            + self.step
        )

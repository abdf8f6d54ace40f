"""One-step lookahead (Algorithm 1, lines 11-20): the policy every UAV runs.

For every permissible action the UAV predicts its next state (other UAVs propagated at their
last observed velocity, the CADRL "filtered velocity"), the SINR level there from a radio map,
and the reward; it picks argmax R + gamma * V(next joint state). All UAVs and all actions go
through the value network in one forward pass. Training, evaluation and the agent processes
call this same code.
"""

from __future__ import annotations

from typing import NamedTuple, Protocol

import numpy as np
import torch

from shared.features import Observation, joint_state
from shared.kinematics import ActionSet, closest_approach, velocity_of
from shared.networks import ValueNetwork
from shared.radio import JammerParams, RadioModel
from shared.rewards import RewardModel, smallest_gaps
from shared.scenario import Scenario


class RadioMap(Protocol):
    """Where the lookahead gets the SINR level of a position it has not been to yet."""

    def level_at(self, xy: np.ndarray) -> np.ndarray:
        """Levels at positions ``xy`` of shape (N, A, 2), one row per UAV: (N, A)."""


class TrueMap:
    """The simulator's map with the current jammer ("perfectly updated map")."""

    def __init__(self, radio: RadioModel, jammer: JammerParams | None):
        self.radio = radio
        self.jammer = jammer

    def level_at(self, xy: np.ndarray) -> np.ndarray:
        return self.radio.evaluate(xy, self.jammer).level


def outdated_map(radio: RadioModel) -> TrueMap:
    """The map of the world without a jammer: what a UAV knows before any jamming."""
    return TrueMap(radio, None)


class Decision(NamedTuple):
    speed: np.ndarray  # (N,)
    heading: np.ndarray  # (N,)
    action: np.ndarray  # (N,) index into the action set
    value: np.ndarray  # (N,) R + gamma V of the chosen action (NaN when explored)


class LookaheadPolicy:
    def __init__(self, scenario: Scenario, value_net: ValueNetwork, device: str = "cpu"):
        self.scenario = scenario
        self.actions = ActionSet(scenario)
        self.rewards = RewardModel(scenario)
        self.dt = scenario.timing.step_s
        self.gamma = scenario.policy.gamma
        self.observed_uavs = scenario.policy.observed_uavs
        self.tolerance = scenario.uav.arrival_tolerance_m
        self.device = torch.device(device)
        self.value_net = value_net.to(self.device).eval()

    def values(self, states: np.ndarray) -> np.ndarray:
        with torch.inference_mode():
            tensor = torch.from_numpy(states).to(self.device)
            return self.value_net(tensor).cpu().numpy().astype(np.float64)

    def decide(
        self,
        observation: Observation,
        radio_map: RadioMap,
        epsilon: float = 0.0,
        rng: np.random.Generator | None = None,
    ) -> Decision:
        n = len(observation)
        observation = observation.nearest_neighbours(self.observed_uavs)
        speeds, headings = self.actions.candidates(observation.heading)  # (N, A)
        velocity = velocity_of(speeds, headings)  # (N, A, 2)
        position = observation.position[:, None, :]
        destination = observation.destination[:, None, :]
        arrived = closest_approach(position - destination, velocity, self.dt) <= self.tolerance
        next_position = np.where(arrived[..., None], destination, position + velocity * self.dt)

        others_next = observation.others_position + observation.others_velocity * self.dt
        gap = smallest_gaps(
            position,
            velocity,
            observation.radius[:, None],
            observation.others_position[:, None],
            observation.others_velocity[:, None],
            observation.others_radius[:, None],
            observation.others_present[:, None],
            self.dt,
        )
        level = radio_map.level_at(next_position)
        check_now = self.rewards.is_check_step(observation.step)[:, None]
        reward = self.rewards.total(level, check_now, gap, arrived)

        states = joint_state(
            next_position,
            velocity,
            headings,
            destination,
            observation.radius[:, None],
            observation.max_speed[:, None],
            level,
            others_next[:, None],
            observation.others_velocity[:, None],
            observation.others_present[:, None],
            self.observed_uavs,
        )
        next_value = self.values(states.reshape(-1, states.shape[-1])).reshape(n, -1)
        # Arrival and collision end the mission: nothing follows them.
        terminal = arrived | (gap <= 0)
        score = reward + self.gamma * np.where(terminal, 0.0, next_value)
        chosen = score.argmax(axis=1)
        value = score[np.arange(n), chosen]
        if epsilon > 0:
            rng = rng or np.random.default_rng()
            explore = rng.random(n) < epsilon
            chosen = np.where(explore, rng.integers(0, len(self.actions), n), chosen)
            value = np.where(explore, np.nan, value)
        rows = np.arange(n)
        return Decision(speeds[rows, chosen], headings[rows, chosen], chosen, value)

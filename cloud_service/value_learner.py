"""What Algorithm 1 learns with: the replay memory D of state-value pairs, the value network
with its target and best copies and the Adam optimizer, and the regressions that change them
(the ORCA initialization, the TD targets of a finished mission, the mini-batch steps after
each episode)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from cloud_service.adam_step import AdamStep, adam_step
from cloud_service.torch_networks import TorchValueNetwork
from cloud_service.training_config import TrainConfig
from planning.features import METHODS, joint_state_size
from shared.scenario import Scenario


class ReplayMemory:
    """Bounded state-value pairs D; the oldest pairs are overwritten first."""

    def __init__(self, capacity: int, state_size: int):
        self.states = np.zeros((capacity, state_size), dtype=np.float32)
        self.values = np.zeros(capacity, dtype=np.float32)
        self.size = 0
        self.cursor = 0

    def push(self, states: np.ndarray, values: np.ndarray) -> None:
        capacity = self.values.shape[0]
        for start in range(0, len(values), capacity):
            chunk_states = states[start : start + capacity]
            chunk_values = values[start : start + capacity]
            index = (self.cursor + np.arange(len(chunk_values))) % capacity
            self.states[index] = chunk_states
            self.values[index] = chunk_values
            self.cursor = int((self.cursor + len(chunk_values)) % capacity)
            self.size = min(capacity, self.size + len(chunk_values))

    def sample(self, rng: np.random.Generator, batch: int) -> tuple[np.ndarray, np.ndarray]:
        index = rng.integers(0, self.size, batch)
        return self.states[index], self.values[index]

    def arrays(self) -> dict[str, np.ndarray]:
        return {"states": self.states[: self.size], "values": self.values[: self.size]}


def discounted_returns(rewards: np.ndarray, gamma: float) -> np.ndarray:
    values = np.zeros_like(rewards)
    running = 0.0
    for t in range(len(rewards) - 1, -1, -1):
        running = rewards[t] + gamma * running
        values[t] = running
    return values


def adam(net: TorchValueNetwork, config: TrainConfig) -> torch.optim.Adam:
    """The paper's optimizer, fused: a step of this small net is mostly per-operation overhead,
    which the fused kernel saves (BENCHMARKS.md, training)."""
    return torch.optim.Adam(net.parameters(), lr=config.learning_rate,
                            weight_decay=config.weight_decay, fused=True)


@dataclass
class Learner:
    """What TD learning changes, and so what a checkpoint holds besides its progress."""

    net: TorchValueNetwork
    target: TorchValueNetwork  # gives the TD targets; follows net every target_sync_episodes
    best: TorchValueNetwork  # the best-validated net so far
    optimizer: torch.optim.Adam
    memory: ReplayMemory
    step: AdamStep | None = None  # the mini-batch step, kept from episode to episode

    @classmethod
    def fresh(cls, scenario: Scenario, config: TrainConfig) -> Learner:
        options = METHODS[config.method]
        size = joint_state_size(scenario, options)
        net, target, best = (
            TorchValueNetwork(size, scenario.policy.value_scale, options._asdict())
            .to(torch.device(config.device)) for _ in range(3))
        return cls(net, target, best, adam(net, config),
                   ReplayMemory(config.capacity(config.uav_count(scenario)), size))

    def networks(self) -> dict[str, TorchValueNetwork]:
        """By the name of their checkpoint file."""
        return {"value": self.net, "target": self.target, "best": self.best}

    def initialize(self, states: np.ndarray, values: np.ndarray, config: TrainConfig,
                   rng: np.random.Generator) -> float:
        """Start from state-value pairs: the network is fitted to them, they are the first
        content of D, and the target network starts as a copy. Returns the fit's last MSE."""
        mse = fit_value_net(self.net, states, values, config.orca_epochs, config, rng)
        self.memory.push(states, values)
        self.sync_target()
        return mse

    def remember(self, missions: list[tuple[np.ndarray, np.ndarray]], gamma: float,
                 device: torch.device) -> None:
        """updateValue of Algorithm 1: the finished missions' TD targets go into D."""
        missions = [m for m in missions if len(m[0])]
        if missions:
            self.memory.push(*td_targets(self.target, missions, gamma, device))

    def learn(self, rng: np.random.Generator, config: TrainConfig, episode: int) -> None:
        """The mini-batch steps after ``episode`` episodes, once D holds a batch, at that
        episode's learning rate."""
        if self.memory.size < config.batch_size:
            return
        self.optimizer.param_groups[0]["lr"] = config.learning_rate_at(episode)
        self.step = adam_step(self.net, self.optimizer, self.step)
        for _ in range(config.updates_per_episode):
            self.step(*self.memory.sample(rng, config.batch_size))

    def sync_target(self) -> None:
        self.target.load_state_dict(self.net.state_dict())

    def keep_as_best(self) -> None:
        self.best.load_state_dict(self.net.state_dict())


def fit_value_net(
    net: TorchValueNetwork,
    states: np.ndarray,
    values: np.ndarray,
    epochs: int,
    config: TrainConfig,
    rng: np.random.Generator,
) -> float:
    """Line 1 of Algorithm 1: regress the network on state-value pairs; returns the last MSE."""
    net.standardize.fit(torch.from_numpy(states).to(torch.device(config.device)))
    step = adam_step(net, adam(net, config))
    loss_value = math.nan
    for _ in range(epochs):
        order = rng.permutation(len(values))
        for start in range(0, len(values), config.batch_size):
            batch = order[start : start + config.batch_size]
            loss_value = step(states[batch], values[batch])
    return loss_value


def td_targets(
    target_net: TorchValueNetwork,
    missions: list[tuple[np.ndarray, np.ndarray]],
    gamma: float,
    device: torch.device,
) -> tuple[np.ndarray, np.ndarray]:
    """updateValue of Algorithm 1: V_t = R_t + gamma V'(s_{t+1}); the last step is terminal."""
    states = np.concatenate([s for s, _ in missions])
    rewards = np.concatenate([r for _, r in missions]).astype(np.float64)
    with torch.inference_mode():
        values = target_net(torch.from_numpy(states).to(device)).cpu().numpy().astype(np.float64)
    next_values = np.zeros_like(rewards)
    offset = 0
    for mission_states, _ in missions:
        length = len(mission_states)
        next_values[offset : offset + length - 1] = values[offset + 1 : offset + length]
        offset += length
    return states, (rewards + gamma * next_values).astype(np.float32)

"""The settings of one value-network training run (``jamnav train``, Algorithm 1): the
paper's hyperparameters, how long and how wide the run flies, and how it checkpoints."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from shared.scenario import Scenario

# Environments flown at once, at most: each keeps its UAVs' whole trajectories in memory (4096
# environments of the city's 64 UAVs: 2.3 GiB), so a mistyped count is refused before it
# allocates far more.
MAX_ENVS = 4096

# The rate each method's updates fall to by the run's end when `jamnav train` is not told. The
# paper's method keeps the one rate the paper gives, 0.001 (None: constant); the extended
# method's checkpoints swing by points of validation at that rate, and falling to 1e-5 lifted
# each seed tried by 0.8-1.6 points (BENCHMARKS.md, "The compiled training step").
DEFAULT_FINAL_LEARNING_RATE = {"paper": None, "extended": 1e-5}


@dataclass
class TrainConfig:
    episodes: int = 20000
    envs: int = 64
    uavs: int | None = None
    seed: int = 0
    device: str = "cpu"
    method: str = "paper"  # a key of planning.features.METHODS
    threads: int = 1  # torch threads: on 2 cores one thread beats two fighting the world
    batch_size: int = 200  # paper
    learning_rate: float = 1e-3  # paper
    # None: the paper's constant rate. A rate: the rate falls to it along half a cosine over
    # the run, so that the last checkpoints' weights settle instead of swinging by points of
    # validation from one to the next (BENCHMARKS.md, "The compiled training step").
    final_learning_rate: float | None = None
    weight_decay: float = 1e-4  # paper: L2 regularization
    epsilon_start: float = 0.5  # paper
    epsilon_end: float = 0.1  # paper
    epsilon_decay_share: float = 0.5  # epsilon reaches its end value halfway through
    memory_capacity: int | None = None  # None: paper's 30,000 for 2 UAVs, 100,000 for more
    updates_per_episode: int = 8
    target_sync_episodes: int = 50
    orca_episodes: int = 1000
    orca_epochs: int = 30
    checkpoint_every_episodes: int = 2000
    validation_episodes: int = 200  # per Table I jammer setting: 3,200 UAV-episodes, SE ~0.3 pt
    extra: dict = field(default_factory=dict)

    def uav_count(self, scenario: Scenario) -> int:
        return self.uavs or scenario.missions.uav_count

    def capacity(self, uavs: int) -> int:
        if self.memory_capacity is not None:
            return self.memory_capacity
        return 30_000 if uavs <= 2 else 100_000

    def learning_rate_at(self, episode: int) -> float:
        """The rate of the updates after ``episode`` episodes (see ``final_learning_rate``)."""
        if self.final_learning_rate is None:
            return self.learning_rate
        share = min(1.0, episode / max(1, self.episodes))
        return self.final_learning_rate + 0.5 * (self.learning_rate - self.final_learning_rate) * (
            1.0 + math.cos(math.pi * share))

    def epsilon_at(self, episode: int) -> float:
        """Exploration after ``episode`` episodes: linear from start to end over the first
        ``epsilon_decay_share`` of the run, then held."""
        decay_episodes = max(1, int(self.episodes * self.epsilon_decay_share))
        share = min(1.0, episode / decay_episodes)
        return self.epsilon_start + share * (self.epsilon_end - self.epsilon_start)

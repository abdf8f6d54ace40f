"""Offline value-network training, Algorithm 1 of the paper, top to bottom.

1. ORCA initialization: fly ORCA episodes, turn each UAV's trajectory into state-value pairs
   (discounted returns), fit the standardization layer and regress the network on them.
2. TD learning: many environments fly the one-step lookahead policy with epsilon-greedy
   exploration (epsilon 0.5 -> 0.1 linearly) on the true map of their current jammer; when a
   UAV's mission ends its trajectory becomes TD targets V_t = R_t + gamma V'(s_{t+1}) from a
   target network, pushed into the replay memory; after every finished episode the network
   takes gradient steps on mini-batches of 200 (Adam, lr 1e-3, L2 1e-4).
3. The jammer moves or changes power every few episodes (random position and power inside
   the area; sometimes absent), as in the paper's training.
4. Every checkpoint is scored on a fixed, seeded validation set (greedy, true map, the Table I
   jammer settings) and the best-scoring one is the result: with epsilon held at 0.1 the
   network keeps moving, and successive checkpoints differ by a few points of success.
Checkpoints make a run resumable; Ctrl-C while learning writes one before it stops.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
import platform
import shutil
import signal
import subprocess
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from safetensors import SafetensorError
from safetensors.numpy import load as bytes_to_arrays
from safetensors.numpy import save as arrays_to_bytes

from cloud_service.rollout import (
    EpisodeHooks,
    LookaheadController,
    OrcaController,
    RasterMaps,
    fly_episodes,
    outcome_rates,
    perfect_maps,
    run_episodes,
)
from cloud_service.torch_networks import TorchValueNetwork
from planning.chosen import lookahead_policy
from planning.features import METHODS, MethodOptions, joint_state_size, observation_state
from planning.networks import (
    ValueNetwork,
    WeightsError,
    card_path,
    from_bytes,
    save_network,
    sha256,
    to_bytes,
)
from planning.reference import PUBLISHED_LOOKAHEAD
from shared.outcomes import Outcome
from shared.paper import TABLE_I_JAMMERS
from shared.radio import JammerParams
from shared.resources import resident_mib
from shared.scenario import Scenario
from world_sim.core import StepResult, VectorWorld, episode_seed, fleet_observation

VALIDATION_SEED = 20210614  # fixed: every model is scored on the same episodes
TRAINING_JAMMER_STREAM = 7  # separates the jammer schedule's random stream from missions'
# Environments flown at once, at most: each keeps its UAVs' whole trajectories in memory (4096
# environments of the city's 64 UAVs: 2.3 GiB), so a mistyped count is refused before it
# allocates far more.
MAX_ENVS = 4096


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


def training_jammer(scenario: Scenario, seed: int, period: int) -> JammerParams | None:
    """The jammer of training period ``period``: random position and power, or absent."""
    rng = np.random.default_rng([seed, TRAINING_JAMMER_STREAM, period])
    spec = scenario.training
    if rng.random() < spec.jammer_absent_probability:
        return None
    area = scenario.area
    return JammerParams(
        float(rng.uniform(area.x_min, area.x_max)),
        float(rng.uniform(area.y_min, area.y_max)),
        float(rng.uniform(*spec.jammer_power_range_w)),
        scenario.jammer.height_m,
    )


def discounted_returns(rewards: np.ndarray, gamma: float) -> np.ndarray:
    values = np.zeros_like(rewards)
    running = 0.0
    for t in range(len(rewards) - 1, -1, -1):
        running = rewards[t] + gamma * running
        values[t] = running
    return values


class TrajectoryRecorder:
    """Per-UAV states and rewards of the running episodes, flushed when a mission ends."""

    def __init__(self, envs: int, uavs: int, horizon: int, state_size: int):
        self.states = np.zeros((envs, uavs, horizon + 1, state_size), dtype=np.float32)
        self.rewards = np.zeros((envs, uavs, horizon), dtype=np.float32)
        self.length = np.zeros((envs, uavs), dtype=np.int64)

    def record(self, rows_state: np.ndarray, rows: np.ndarray, reward: np.ndarray) -> None:
        """Store the state each active UAV acted from, and the reward it then received."""
        uavs = self.length.shape[1]
        env, uav = rows // uavs, rows % uavs
        t = self.length[env, uav]
        self.states[env, uav, t] = rows_state
        self.rewards[env, uav, t] = reward[env, uav]
        self.length[env, uav] = t + 1

    def take(self, env: int, uav: int) -> tuple[np.ndarray, np.ndarray]:
        length = self.length[env, uav]
        self.length[env, uav] = 0
        return self.states[env, uav, :length], self.rewards[env, uav, :length]


def adam(net: TorchValueNetwork, config: TrainConfig) -> torch.optim.Adam:
    """The paper's optimizer; the fused kernel halves the cost of a step of this small net."""
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


def fit_value_net(
    net: TorchValueNetwork,
    states: np.ndarray,
    values: np.ndarray,
    epochs: int,
    config: TrainConfig,
    rng: np.random.Generator,
) -> float:
    """Line 1 of Algorithm 1: regress the network on state-value pairs; returns the last MSE."""
    device = torch.device(config.device)
    net.standardize.fit(torch.from_numpy(states).to(device))
    optimizer = adam(net, config)
    x_all, y_all = torch.from_numpy(states).to(device), torch.from_numpy(values).to(device)
    loss_value = math.nan
    for _ in range(epochs):
        order = torch.from_numpy(rng.permutation(len(values))).to(device)
        for start in range(0, len(values), config.batch_size):
            batch = order[start : start + config.batch_size]
            loss = torch.nn.functional.mse_loss(net(x_all[batch]), y_all[batch])
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            loss_value = float(loss.detach())
    return loss_value


@dataclass
class EpisodeStats:
    episode: int
    outcomes: np.ndarray  # (J,)
    mean_return: float
    straight_bound: float


def straight_line_bound(scenario: Scenario, start: np.ndarray, goal: np.ndarray) -> np.ndarray:
    """Reward of flying straight at full speed, ignoring R_s and R_c (the paper's bound)."""
    reach = scenario.uav.max_speed_mps * scenario.timing.step_s
    distance = np.linalg.norm(goal - start, axis=-1) - scenario.uav.arrival_tolerance_m
    steps = np.maximum(1, np.ceil(distance / reach))
    return scenario.rewards.arrival + scenario.rewards.step * steps


class TrainingFlight(EpisodeHooks):
    """Training's side of a flight: the training jammer schedule, the state each UAV acted
    from and the reward it received (with the disconnection penalty), and each episode's
    statistics."""

    def __init__(
        self,
        world: VectorWorld,
        maps: RasterMaps,
        options: MethodOptions,
        seed: int,
        on_missions: Callable[[list[tuple[np.ndarray, np.ndarray]]], None],
        on_episode: Callable[[EpisodeStats], None],
    ):
        self.world, self.maps, self.options, self.seed = world, maps, options, seed
        self.on_missions, self.on_episode = on_missions, on_episode
        size = joint_state_size(world.scenario, options)
        self.recorder = TrajectoryRecorder(world.num_envs, world.num_uavs, world.step_limit, size)
        self.returns = np.zeros((world.num_envs, world.num_uavs))
        self.decisions = 0
        self.next_episode = 0  # the first episode not yet started
        # From before_step to after_step: the rows of the UAVs about to act, and their states.
        self.rows = np.zeros(0, dtype=np.int64)
        self.states = np.zeros((0, size), dtype=np.float32)

    def start(self, env: int, episode: int) -> None:
        scenario = self.world.scenario
        period = episode // scenario.training.jammer_change_every_episodes
        self.next_episode = episode + 1
        self.world.set_jammer([env], training_jammer(scenario, self.seed, period))
        self.world.reset([env], [episode_seed(self.seed, episode)])
        self.returns[env] = 0.0

    def before_step(self, running: np.ndarray) -> None:
        world, options = self.world, self.options
        self.rows = np.flatnonzero((world.active & running[:, None]).ravel())
        self.states = observation_state(
            fleet_observation(world).select(self.rows), world.scenario, options,
            self.maps(world, self.rows) if options.route_distance else None)

    def after_step(self, result: StepResult, slot_episode: np.ndarray,
                   running: np.ndarray) -> None:
        self.decisions += self.rows.size
        lost = result.finished & (self.world.status == Outcome.DISCONNECTION)
        reward = result.reward + self.options.disconnection_reward * lost
        self.recorder.record(self.states, self.rows, reward)
        self.returns += reward
        self.on_missions([self.recorder.take(e, u)
                          for e, u in zip(*np.nonzero(result.finished), strict=True)])

    def end(self, env: int, episode: int) -> None:
        world = self.world
        bound = straight_line_bound(world.scenario, world.start[env], world.destination[env])
        self.on_episode(EpisodeStats(int(episode), world.status[env].copy(),
                                     float(self.returns[env].mean()), float(bound.mean())))


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


def validate(scenario: Scenario, net: ValueNetwork, episodes: int, uavs: int) -> dict[str, float]:
    """Greedy lookahead on the true map, over the fixed validation episodes of each Table I
    jammer setting: the share of UAV-episodes ending in each outcome."""
    # The lookahead the network is trained with: selecting checkpoints by the deployed
    # planner would score the planner as much as the network.
    policy = lookahead_policy(scenario, net, **PUBLISHED_LOOKAHEAD)
    outcomes = [
        run_episodes(scenario, LookaheadController(policy, perfect_maps(scenario)), episodes,
                     VALIDATION_SEED, setting, uavs).outcomes
        for setting in TABLE_I_JAMMERS
    ]
    rates = outcome_rates(np.concatenate(outcomes))
    return {**rates, "episodes_per_setting": episodes,
            "settings": [setting.label for setting in TABLE_I_JAMMERS]}


def best_score(scores: list[dict]) -> dict:
    """The checkpoint score with the highest success rate; the later one on a tie."""
    return max(reversed(scores), key=lambda score: score["success_rate"])


def git_commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True,
                              timeout=10, check=True).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"


# The vector instructions that decide how float32 sums are grouped, and so the last bits of
# every gradient step: two CPUs that differ in them train to different weights.
ARITHMETIC_FLAGS = ("sse4_2", "avx", "avx2", "fma", "avx512f", "avx512_vnni", "amx_tile")


def cpu_description() -> dict[str, Any]:
    """The training machine as far as the weights depend on it: CPU model, the vector
    instructions it offers (``ARITHMETIC_FLAGS``), the kernel, and torch's own choice."""
    model, flags = platform.processor() or platform.machine(), set()
    try:
        for line in Path("/proc/cpuinfo").read_text(encoding="utf-8").splitlines():
            key, _, value = line.partition(":")
            if key.strip() == "model name":
                model = value.strip()
            elif key.strip() == "flags":
                flags = set(value.split())
                break
    except OSError:  # not Linux: the model name alone
        pass
    return {"model": model, "flags": [flag for flag in ARITHMETIC_FLAGS if flag in flags],
            "kernel": platform.release(), "torch_cpu_capability":
                torch.backends.cpu.get_cpu_capability()}


LOG_FIELDS = ["episode", "wall_seconds", "epsilon", "mean_return", "straight_bound",
              "success", "disconnection", "collision", "timeout"]


def write_synced(path: Path, data: bytes) -> None:
    """Write ``data`` and push it to the disk, so that no later rename can outlive it."""
    with path.open("wb") as handle:
        handle.write(data)
        handle.flush()
        os.fsync(handle.fileno())


def sync_directory(path: Path) -> None:
    """Push the entries created or renamed in ``path`` to the disk."""
    descriptor = os.open(path, os.O_RDONLY)
    try:
        os.fsync(descriptor)
    finally:
        os.close(descriptor)


VALUE_NET_FILE = "value_net.safetensors"  # the result, beside its card (value_net.json)


class CheckpointError(ValueError):
    """A checkpoint a run cannot continue from: missing, damaged, or made with other settings.
    One line, naming the file or the settings."""


def run_settings(scenario: Scenario, config: TrainConfig) -> dict[str, Any]:
    """What a run's network depends on besides how long it trains, by the ``jamnav train``
    options that set them: a resumed run must keep them all, or the card would describe a
    network that no run made. The scenario counts by its content (a value network learns its
    missions, rewards and planning values as much as its radio), whatever it is called."""
    content = json.dumps(scenario.model_dump(mode="json"), sort_keys=True)
    return {"--scenario": f"{scenario.name} [sha256 {sha256(content.encode())[:12]}]",
            "--method": config.method, "--seed": config.seed,
            "--uavs": config.uav_count(scenario)}


# What progress.json must hold for a run to continue from it.
PROGRESS_FIELDS = {"episodes_done": int, "next_episode": int, "wall_seconds": (int, float),
                   "decisions": int, "td_seconds": (int, float), "orca": dict,
                   "checkpoint_scores": list, "config": dict}


class Checkpoint:
    """Everything a resumed run needs, under ``<out>/checkpoint/``. Each save writes a
    complete set of files into a fresh directory and only then repoints the pointer file at
    it (an atomic rename): a kill at any moment leaves the old or the new set whole. The next
    save removes every directory the pointer does not name (older sets, a killed save's).
    progress.json records the digest of every other file of its set, so that a damaged one is
    found before a resumed run reads it."""

    def __init__(self, out: Path):
        self.out = out
        self.root = out / "checkpoint"
        self.pointer = self.root / "current"

    @property
    def dir(self) -> Path:
        """The current set's directory; without a pointer, the root itself, where jamnav
        wrote its checkpoints in place before it had pointers."""
        if self.pointer.is_file():
            return self.root / self.pointer.read_text(encoding="utf-8").strip()
        return self.root

    def exists(self) -> bool:
        return (self.dir / "progress.json").is_file()

    def progress(self) -> dict:
        path = self.dir / "progress.json"
        try:
            progress = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError):  # ValueError: not JSON, or not UTF-8
            raise CheckpointError(f"{path} is unreadable") from None
        if not isinstance(progress, dict):
            raise CheckpointError(f"{path} is not a checkpoint's progress")
        return progress

    def save(self, learner: Learner, progress: dict) -> None:
        self.root.mkdir(parents=True, exist_ok=True)
        fresh = Path(tempfile.mkdtemp(prefix=f"episode-{progress['episodes_done']}-",
                                      dir=self.root))
        optimizer_state = io.BytesIO()
        torch.save(learner.optimizer.state_dict(), optimizer_state)
        files = {
            **{f"{name}.safetensors": to_bytes(module.inference())
               for name, module in learner.networks().items()},
            "optimizer.pt": optimizer_state.getvalue(),
            "memory.safetensors": arrays_to_bytes(learner.memory.arrays()),
        }
        files["progress.json"] = json.dumps(
            {**progress, "sha256": {name: sha256(data) for name, data in files.items()}},
            indent=2).encode()
        for name, data in files.items():
            write_synced(fresh / name, data)
        sync_directory(fresh)
        staged = self.root / f"{self.pointer.name}.tmp"
        write_synced(staged, fresh.name.encode())
        os.replace(staged, self.pointer)
        sync_directory(self.root)
        for entry in self.root.iterdir():
            if entry.name in (fresh.name, self.pointer.name):
                continue
            if entry.is_dir():
                shutil.rmtree(entry)
            else:  # a killed save's staged pointer, or a file of an in-place checkpoint
                entry.unlink()

    def load(self, learner: Learner, scenario: Scenario, config: TrainConfig) -> dict:
        """Read the current set into ``learner`` and return its progress, once it is known to
        continue the run that ``scenario`` and ``config`` describe. A missing or damaged file
        raises CheckpointError as it is read: ``jamnav train --resume`` loads into a learner
        of its own before it starts, to refuse in one line what would fail later."""
        if not self.exists():
            raise CheckpointError(f"no checkpoint in {self.dir} "
                                  "(leave out --resume to start afresh)")
        progress = self.progress()
        self._check_continues(progress, scenario, config)
        current = self.dir
        digests = progress.get("sha256")
        if not isinstance(digests, dict):  # a checkpoint from before they were recorded
            digests = {}

        def read(name: str) -> bytes:
            try:
                data = (current / name).read_bytes()
            except OSError as exc:
                raise CheckpointError(f"{current / name}: {exc.strerror}") from None
            if name in digests and sha256(data) != digests[name]:
                raise CheckpointError(f"{current / name}: damaged (it is not the file the "
                                      "checkpoint wrote)")
            return data

        for name, module in learner.networks().items():
            try:
                module.assign(from_bytes(read(f"{name}.safetensors"), expected=module.card))
            except WeightsError as exc:
                raise CheckpointError(f"{current / name}.safetensors: {exc}") from None
        optimizer_state = read("optimizer.pt")
        # weights_only: tensors and plain containers are unpickled, never other objects. torch
        # reports a damaged file as any of many exception types, some with advice to unpickle
        # anything (weights_only=False) that must not be taken: one line instead.
        try:
            learner.optimizer.load_state_dict(
                torch.load(io.BytesIO(optimizer_state), weights_only=True))
        except Exception:
            raise CheckpointError(f"{current / 'optimizer.pt'}: damaged (not an optimizer "
                                  "state of this network)") from None
        learner.memory.push(*self._memory_arrays(read("memory.safetensors"),
                                                 learner.memory.states.shape[1]))
        return progress

    def _check_continues(self, progress: dict, scenario: Scenario, config: TrainConfig) -> None:
        """Refuse the checkpoint of a run with other settings, of an older jamnav, or one
        that leaves no episodes to add."""
        path = self.dir / "progress.json"
        saved_config = progress.get("config")
        if isinstance(saved_config, dict):
            saved = progress.get("settings")
            if not isinstance(saved, dict):  # from before they were recorded: its config's
                saved = run_settings(scenario, replace(config, **{
                    name: saved_config[name] for name in ("method", "seed", "uavs")
                    if name in saved_config}))
            asked = run_settings(scenario, config)
            differing = [option for option in asked if saved.get(option) != asked[option]]
            if differing:
                raise CheckpointError(f"the checkpoint in {self.dir} was made with " + ", ".join(
                    f"{option} {saved.get(option)} (not {asked[option]})"
                    for option in differing))
        if not isinstance(progress.get("checkpoint_scores"), list):
            raise CheckpointError(f"{path} has no checkpoint scores (written by an older "
                                  "jamnav); start afresh without --resume")
        malformed = [name for name, kind in PROGRESS_FIELDS.items()
                     if not isinstance(progress.get(name), kind)]
        if malformed:
            raise CheckpointError(f"{path}: damaged (missing or malformed: "
                                  f"{', '.join(malformed)})")
        done = progress["episodes_done"]
        # Equal is allowed while the run's result is not written: a run killed after its last
        # checkpoint is finished by resuming it.
        if config.episodes < done or config.episodes == done and self._result_written(done):
            raise CheckpointError(f"the checkpoint in {self.dir} already holds {done} "
                                  "episodes; --episodes must exceed it")

    def _result_written(self, episodes: int) -> bool:
        """Whether the run's result is written, with the card of a run of ``episodes``."""
        try:
            card = json.loads(card_path(self.out / VALUE_NET_FILE).read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return False
        return isinstance(card, dict) and card.get("episodes") == episodes

    def _memory_arrays(self, data: bytes, state_size: int) -> tuple[np.ndarray, np.ndarray]:
        path = self.dir / "memory.safetensors"
        try:
            arrays = bytes_to_arrays(data)
            states, values = arrays["states"], arrays["values"]
        except (SafetensorError, KeyError):
            raise CheckpointError(f"{path}: damaged (not a replay memory)") from None
        if (states.dtype != np.float32 or values.dtype != np.float32 or values.ndim != 1
                or states.shape != (len(values), state_size)):
            raise CheckpointError(f"{path}: damaged (states {states.shape} {states.dtype} and "
                                  f"values {values.shape} {values.dtype}, expected (n, "
                                  f"{state_size}) and (n,) float32)")
        return states, values


class DeferredInterrupt:
    """Ctrl-C while training learns, as a request that the loop takes where the run's state
    is whole (at the end of an episode, or after a checkpoint's save) so that it can save it;
    a second Ctrl-C interrupts at once. Only the main thread receives signals, and a handler
    installed by someone else stays theirs: there, nothing is deferred."""

    def __init__(self):
        self.requested = False
        self.previous = None

    def __enter__(self) -> DeferredInterrupt:
        if (threading.current_thread() is threading.main_thread()
                and signal.getsignal(signal.SIGINT) is signal.default_int_handler):
            self.previous = signal.signal(signal.SIGINT, self._request)
        return self

    def _request(self, _signal, _frame) -> None:
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True

    def __exit__(self, *_exception) -> None:
        if self.previous is not None:
            signal.signal(signal.SIGINT, self.previous)


class StopRequested(Exception):
    """Raised at the end of an episode when Ctrl-C asked training to stop."""


def forget_logged_after(log_path: Path, episodes: int) -> None:
    """Keep the header and the rows of the first ``episodes`` episodes: the rows a killed run
    logged after its last checkpoint are flown and logged again by the resumed run."""
    lines = log_path.read_bytes().splitlines(keepends=True)
    staged = log_path.with_name(f"{log_path.name}.tmp")
    staged.write_bytes(b"".join(lines[: episodes + 1]))
    os.replace(staged, log_path)


def train(
    scenario: Scenario,
    config: TrainConfig,
    out: Path,
    resume: bool = False,
    progress: Callable[[dict], None] | None = None,
    command: str = "",
) -> dict:
    """Run Algorithm 1 and write value_net.safetensors, its card, train_log.csv and the
    reward curve into ``out``. Returns the card. Ctrl-C while learning saves a checkpoint of
    the episodes done before it raises KeyboardInterrupt (reported as phase "interrupted")."""
    out.mkdir(parents=True, exist_ok=True)
    commit = git_commit()  # the code that trains, even if the tree moves on meanwhile
    uavs = config.uav_count(scenario)
    device = torch.device(config.device)
    torch.set_num_threads(config.threads)
    torch.manual_seed(config.seed)
    rng = np.random.default_rng([config.seed, 1])
    options = METHODS[config.method]
    learner = Learner.fresh(scenario, config)
    net, target, best, memory = learner.net, learner.target, learner.best, learner.memory
    maps = perfect_maps(scenario)
    checkpoint = Checkpoint(out)
    log_path = out / "train_log.csv"
    report = progress or (lambda info: None)

    if resume:
        state = checkpoint.load(learner, scenario, config)
        done, next_episode = state["episodes_done"], state["next_episode"]
        scores = state["checkpoint_scores"]
        wall_before, decisions, td_seconds = (state["wall_seconds"], state["decisions"],
                                              state["td_seconds"])
        orca_info = state["orca"]
        rng = np.random.default_rng([config.seed, 1, done])
        forget_logged_after(log_path, done)
        report({"phase": "resume", "episodes_done": done})
    else:
        started = time.perf_counter()
        report({"phase": "orca", "episodes": config.orca_episodes})
        states, values = orca_pairs(scenario, config, uavs, maps, options)
        mse = fit_value_net(net, states, values, config.orca_epochs, config, rng)
        memory.push(states, values)
        orca_info = {"episodes": config.orca_episodes, "pairs": int(len(values)),
                     "epochs": config.orca_epochs, "final_mse": mse,
                     "seconds": time.perf_counter() - started}
        target.load_state_dict(net.state_dict())
        done, next_episode, wall_before, decisions, td_seconds = 0, 0, orca_info["seconds"], 0, 0.0
        scores: list[dict] = []
        with log_path.open("w", newline="") as handle:
            csv.writer(handle).writerow(LOG_FIELDS)

    # The lookahead the shipped networks were trained with (the TD targets are one-step, and
    # a deeper search would cost training 5-10x).
    policy = lookahead_policy(scenario, net.inference(), shield=False, **PUBLISHED_LOOKAHEAD)
    controller = LookaheadController(policy, maps, rng=rng)
    world = VectorWorld(scenario, config.envs, uavs)
    gamma = scenario.policy.gamma
    decay_episodes = max(1, int(config.episodes * config.epsilon_decay_share))
    recent: list[np.ndarray] = []
    session_start = time.perf_counter()
    log_handle = log_path.open("a", newline="")
    log = csv.writer(log_handle)
    interrupt = DeferredInterrupt()
    chunk_end = done

    def epsilon_at(episode: int) -> float:
        share = min(1.0, episode / decay_episodes)
        return config.epsilon_start + share * (config.epsilon_end - config.epsilon_start)

    def on_missions(missions: list[tuple[np.ndarray, np.ndarray]]) -> None:
        missions = [m for m in missions if len(m[0])]
        if missions:
            memory.push(*td_targets(target, missions, gamma, device))

    def on_episode(stats: EpisodeStats) -> None:
        nonlocal done
        done += 1
        controller.epsilon = epsilon_at(done)
        net.train()
        for _ in range(config.updates_per_episode if memory.size >= config.batch_size else 0):
            batch_states, batch_values = memory.sample(rng, config.batch_size)
            prediction = net(torch.from_numpy(batch_states).to(device))
            loss = torch.nn.functional.mse_loss(prediction,
                                                torch.from_numpy(batch_values).to(device))
            learner.optimizer.zero_grad()
            loss.backward()
            learner.optimizer.step()
        net.eval()
        # The lookahead takes the updated numpy form (off the CPU it is a copy), reading the
        # weights that decay has left subnormal as zeros: the same values, without the cost
        # some CPUs put on them (``Network.read_subnormals_as_zero``).
        policy.value_net = net.inference().read_subnormals_as_zero()
        if done % config.target_sync_episodes == 0:
            target.load_state_dict(net.state_dict())
        counts = [int(np.count_nonzero(stats.outcomes == o)) for o in
                  (Outcome.SUCCESS, Outcome.DISCONNECTION, Outcome.COLLISION, Outcome.TIMEOUT)]
        wall = wall_before + time.perf_counter() - session_start
        log.writerow([done, round(wall, 3), round(controller.epsilon, 4),
                      round(stats.mean_return, 5), round(stats.straight_bound, 5), *counts])
        recent.append(stats.outcomes)
        del recent[:-200]
        report({"phase": "td", "episodes_done": done, "episodes": config.episodes,
                "epsilon": controller.epsilon, "wall_seconds": wall,
                "recent_success": float(np.mean(np.concatenate(recent) == Outcome.SUCCESS))})
        # The chunk's last episode goes on to its validation: stopping there would leave it
        # to a resumed run that never validates at that episode.
        if interrupt.requested and done < chunk_end:
            raise StopRequested

    controller.epsilon = epsilon_at(done)
    try:
        with interrupt:
            while done < config.episodes:
                # Chunks end at multiples of checkpoint_every_episodes, so that a run resumed
                # from where Ctrl-C stopped it validates and checkpoints where any other does.
                every = config.checkpoint_every_episodes
                chunk_end = min(done + every - done % every, config.episodes)
                flight = TrainingFlight(world, maps, options, config.seed, on_missions,
                                        on_episode)
                chunk_start = time.perf_counter()
                try:
                    fly_episodes(world, controller, range(next_episode, next_episode +
                                                          chunk_end - done), flight)
                    stopped = False
                except StopRequested:
                    stopped = True
                decisions += flight.decisions
                td_seconds += time.perf_counter() - chunk_start
                # Stopped, the episodes in flight are dropped and the resumed run flies the
                # next unstarted ones instead: their missions count as any other.
                next_episode = flight.next_episode
                log_handle.flush()
                if not stopped:
                    scores.append({"episode": done, **validate(
                        scenario, net.inference().read_subnormals_as_zero(),
                        config.validation_episodes, uavs), "resident_mib": resident_mib()})
                    leader = best_score(scores)
                    if leader is scores[-1]:
                        best.load_state_dict(net.state_dict())
                    report({"phase": "validation", "episodes_done": done,
                            "success_rate": scores[-1]["success_rate"],
                            "best_episode": leader["episode"],
                            "best_success_rate": leader["success_rate"]})
                checkpoint.save(learner, {
                    "episodes_done": done, "next_episode": next_episode,
                    "wall_seconds": wall_before + time.perf_counter() - session_start,
                    "decisions": decisions, "td_seconds": td_seconds, "orca": orca_info,
                    "checkpoint_scores": scores, "config": asdict(config),
                    "settings": run_settings(scenario, config),
                })
                if interrupt.requested:
                    report({"phase": "interrupted", "episodes_done": done,
                            "checkpoint": str(checkpoint.dir)})
                    raise KeyboardInterrupt
    finally:
        log_handle.close()

    wall = wall_before + time.perf_counter() - session_start
    validation = dict(best_score(scores))
    selected_episode = validation.pop("episode")
    validation.pop("resident_mib", None)
    card = {
        "command": command,
        "scenario": scenario.name,
        "seed": config.seed,
        "episodes": done,
        "envs": config.envs,
        "uavs": uavs,
        "wall_seconds": round(wall, 1),
        "decisions": decisions,
        "decisions_per_second": round(decisions / td_seconds, 1) if td_seconds else None,
        "episodes_per_second": round(done / td_seconds, 2) if td_seconds else None,
        "orca_initialization": orca_info,
        "git_commit": commit,
        "torch": torch.__version__,
        "device": config.device,
        "cpu": cpu_description(),
        "config": asdict(config),
        "validation": validation,
        "selection": {
            "rule": "the checkpoint with the highest validation success; ties go to the later",
            "selected_episode": selected_episode,
            "checkpoints": [{"episode": s["episode"], "success_rate": s["success_rate"],
                             "resident_mib": s.get("resident_mib")} for s in scores],
        },
        "reproduce": command or "jamnav train",
    }
    save_network(best.inference(), out / VALUE_NET_FILE, card)
    from shared.plots import plot_reward_curve  # matplotlib only when writing

    plot_reward_curve(log_path, out / "reward_curve.png")
    return card


def orca_pairs(
    scenario: Scenario, config: TrainConfig, uavs: int, maps: RasterMaps, options: MethodOptions
) -> tuple[np.ndarray, np.ndarray]:
    """State-value pairs D from ORCA trajectories: discounted returns of each mission."""
    gamma = scenario.policy.gamma
    states: list[np.ndarray] = []
    values: list[np.ndarray] = []

    def on_missions(missions: list[tuple[np.ndarray, np.ndarray]]) -> None:
        for mission_states, rewards in missions:
            if len(rewards):
                states.append(mission_states)
                values.append(discounted_returns(rewards, gamma))

    world = VectorWorld(scenario, config.envs, uavs)
    # Offset seeds so ORCA flies other missions than TD training's first episodes.
    flight = TrainingFlight(world, maps, options, config.seed + 1_000_003, on_missions,
                            lambda stats: None)
    fly_episodes(world, OrcaController(scenario), range(config.orca_episodes), flight)
    return np.concatenate(states), np.concatenate(values).astype(np.float32)


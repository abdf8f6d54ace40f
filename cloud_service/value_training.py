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

``train`` is the driver; its parts live beside it: the settings (``training_config``), the
networks, memory and regressions (``value_learner``), the flown episodes as the learner sees
them (``training_flight``) and the checkpoints (``training_checkpoint``).
"""

from __future__ import annotations

import csv
import functools
import platform
import signal
import subprocess
import threading
import time
from collections.abc import Callable
from concurrent.futures import Executor
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import IO, Any

import numpy as np
import torch

from cloud_service.rollout import (
    LookaheadController,
    OrcaController,
    RasterMaps,
    fly_episodes,
)
from cloud_service.training_checkpoint import (
    VALUE_NET_FILE,
    Checkpoint,
    forget_logged_after,
    run_settings,
)
from cloud_service.training_config import TrainConfig
from cloud_service.training_flight import EpisodeStats, TrainingFlight, training_maps
from cloud_service.training_validation import validate, validation_helper
from cloud_service.value_learner import Learner, discounted_returns
from planning.chosen import lookahead_policy
from planning.features import METHODS, MethodOptions
from planning.networks import save_network
from planning.reference import PUBLISHED_LOOKAHEAD
from shared.outcomes import Outcome
from shared.resources import resident_mib
from shared.scenario import Scenario
from world_sim.core import VectorWorld

LOG_FILE = "train_log.csv"
LOG_FIELDS = ["episode", "wall_seconds", "epsilon", "mean_return", "straight_bound",
              "success", "disconnection", "collision", "timeout"]
RECENT_EPISODES = 200  # the success rate shown while training is over the last ones


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
    report = progress or (lambda info: None)
    torch.set_num_threads(config.threads)
    torch.manual_seed(config.seed)  # before the networks are made: it draws their weights
    learner = Learner.fresh(scenario, config)
    maps = training_maps(scenario)
    checkpoint = Checkpoint(out)
    log_path = out / LOG_FILE
    if resume:
        so_far = resume_learner(checkpoint, learner, scenario, config, log_path)
        # The random stream is not checkpointed: a resumed session draws one of its own.
        rng = np.random.default_rng([config.seed, 1, so_far.episodes_done])
        report({"phase": "resume", "episodes_done": so_far.episodes_done})
    else:
        rng = np.random.default_rng([config.seed, 1])
        so_far = initialize_with_orca(scenario, config, learner, maps, rng, report)
        with log_path.open("w", newline="") as handle:
            csv.writer(handle).writerow(LOG_FIELDS)
    with log_path.open("a", newline="") as log:
        learning = TdLearning(scenario, config, learner, maps, rng, so_far, log, report)
        learning.fly_all(checkpoint)
    card = run_card(scenario, config, learning, command, commit)
    save_network(learner.best.inference(), out / VALUE_NET_FILE, card)
    from shared.plots import plot_reward_curve  # matplotlib only when writing

    plot_reward_curve(log_path, out / "reward_curve.png")
    return card


@dataclass
class Progress:
    """How far a run has come: what its checkpoints record besides the learner and the
    settings (``training_checkpoint.PROGRESS_FIELDS``)."""

    episodes_done: int = 0
    next_episode: int = 0  # the first episode not yet started
    wall_seconds: float = 0.0  # as of the last save, the ORCA initialization included
    decisions: int = 0
    td_seconds: float = 0.0
    orca: dict = field(default_factory=dict)  # the initialization: its size, MSE and time
    checkpoint_scores: list[dict] = field(default_factory=list)


def resume_learner(checkpoint: Checkpoint, learner: Learner, scenario: Scenario,
                   config: TrainConfig, log_path: Path) -> Progress:
    """Load the checkpoint into ``learner``; the log forgets what was flown after it."""
    state = checkpoint.load(learner, scenario, config)
    so_far = Progress(**{part.name: state[part.name] for part in fields(Progress)})
    forget_logged_after(log_path, so_far.episodes_done)
    return so_far


def initialize_with_orca(scenario: Scenario, config: TrainConfig, learner: Learner,
                         maps: RasterMaps, rng: np.random.Generator,
                         report: Callable[[dict], None]) -> Progress:
    """Line 1 of Algorithm 1: ORCA's state-value pairs initialize the network and the
    replay memory D."""
    started = time.perf_counter()
    report({"phase": "orca", "episodes": config.orca_episodes})
    states, values = orca_pairs(scenario, config, config.uav_count(scenario), maps,
                                METHODS[config.method])
    mse = learner.initialize(states, values, config, rng)
    orca = {"episodes": config.orca_episodes, "pairs": int(len(values)),
            "epochs": config.orca_epochs, "final_mse": mse,
            "seconds": time.perf_counter() - started}
    return Progress(wall_seconds=orca["seconds"], orca=orca)


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


class TdLearning:
    """The episode loop of Algorithm 1 for one session of a run, fresh or resumed: the
    lookahead flies epsilon-greedy on the true map of the training jammer, each finished
    mission's TD targets go into the replay memory, and the network learns after every
    episode. Episodes fly in chunks, each ending where a checkpoint is due: there the network
    is validated and the run saved."""

    def __init__(self, scenario: Scenario, config: TrainConfig, learner: Learner,
                 maps: RasterMaps, rng: np.random.Generator, so_far: Progress, log: IO[str],
                 report: Callable[[dict], None]):
        self.scenario, self.config, self.learner, self.maps = scenario, config, learner, maps
        self.rng, self.progress, self.log, self.report = rng, so_far, log, report
        self.log_rows = csv.writer(log)
        # The lookahead the shipped networks were trained with: one step, as the TD targets
        # are, where a deeper search would multiply the cost of training.
        self.policy = lookahead_policy(scenario, learner.net.inference(), shield=False,
                                       **PUBLISHED_LOOKAHEAD)
        self.controller = LookaheadController(self.policy, maps, rng=rng)
        self.controller.epsilon = config.epsilon_at(so_far.episodes_done)
        self.world = VectorWorld(scenario, config.envs, config.uav_count(scenario))
        self.recent: list[np.ndarray] = []  # the outcomes of the last RECENT_EPISODES
        self.wall_before, self.session_start = so_far.wall_seconds, time.perf_counter()
        self.interrupt = DeferredInterrupt()
        self.chunk_end = so_far.episodes_done

    def wall_seconds(self) -> float:
        """The run's wall time so far, its earlier sessions included."""
        return self.wall_before + time.perf_counter() - self.session_start

    def fly_all(self, checkpoint: Checkpoint) -> None:
        """Fly chunk after chunk to the run's last episode, each validated and saved; Ctrl-C
        saves the episodes done and raises KeyboardInterrupt."""
        with self.interrupt, validation_helper() as helper:
            while self.progress.episodes_done < self.config.episodes:
                if self.fly_chunk():
                    self.validate_chunk(helper)
                self.progress.wall_seconds = self.wall_seconds()
                checkpoint.save(self.learner, {
                    **asdict(self.progress), "config": asdict(self.config),
                    "settings": run_settings(self.scenario, self.config)})
                if self.interrupt.requested:
                    self.report({"phase": "interrupted",
                                 "episodes_done": self.progress.episodes_done,
                                 "checkpoint": str(checkpoint.dir)})
                    raise KeyboardInterrupt

    def fly_chunk(self) -> bool:
        """Fly the episodes up to the next checkpoint; False if Ctrl-C stopped them."""
        progress, config = self.progress, self.config
        done = progress.episodes_done
        # Chunks end at multiples of checkpoint_every_episodes, so that a run resumed from
        # where Ctrl-C stopped it validates and checkpoints where any other does.
        every = config.checkpoint_every_episodes
        self.chunk_end = min(done + every - done % every, config.episodes)
        remember = functools.partial(self.learner.remember, gamma=self.scenario.policy.gamma,
                                     device=torch.device(config.device))
        flight = TrainingFlight(self.world, self.maps, METHODS[config.method], config.seed,
                                remember, self.after_episode)
        started = time.perf_counter()
        episodes = range(progress.next_episode, progress.next_episode + self.chunk_end - done)
        try:
            fly_episodes(self.world, self.controller, episodes, flight)
            finished = True
        except StopRequested:
            finished = False
        progress.decisions += flight.decisions
        progress.td_seconds += time.perf_counter() - started
        # Stopped, the episodes in flight are dropped and the resumed run flies the next
        # unstarted ones instead: their missions count as any other.
        progress.next_episode = flight.next_episode
        self.log.flush()
        return finished

    def after_episode(self, stats: EpisodeStats) -> None:
        """The network learns from the replay memory, the lookahead flies its new weights
        and the target network follows every ``target_sync_episodes``; then the episode is
        logged. Ctrl-C stops the chunk here, where the run's state is whole."""
        self.progress.episodes_done += 1
        done, config = self.progress.episodes_done, self.config
        self.controller.epsilon = config.epsilon_at(done)
        self.learner.learn(self.rng, config, done)
        # The lookahead takes the updated numpy form (off the CPU it is a copy), reading the
        # weights that decay has left subnormal as zeros: the same values, without the cost
        # some CPUs put on them (``Network.read_subnormals_as_zero``).
        self.policy.value_net = self.learner.net.inference().read_subnormals_as_zero()
        if done % config.target_sync_episodes == 0:
            self.learner.sync_target()
        self.log_episode(stats)
        # The chunk's last episode goes on to its validation: stopping there would leave it
        # to a resumed run that never validates at that episode.
        if self.interrupt.requested and done < self.chunk_end:
            raise StopRequested

    def log_episode(self, stats: EpisodeStats) -> None:
        """A row of train_log.csv, and the progress shown while training."""
        done, epsilon = self.progress.episodes_done, self.controller.epsilon
        counts = [int(np.count_nonzero(stats.outcomes == o)) for o in
                  (Outcome.SUCCESS, Outcome.DISCONNECTION, Outcome.COLLISION, Outcome.TIMEOUT)]
        wall = self.wall_seconds()
        self.log_rows.writerow([done, round(wall, 3), round(epsilon, 4),
                                round(stats.mean_return, 5), round(stats.straight_bound, 5),
                                *counts])
        self.recent.append(stats.outcomes)
        del self.recent[:-RECENT_EPISODES]
        self.report({"phase": "td", "episodes_done": done, "episodes": self.config.episodes,
                     "epsilon": epsilon, "wall_seconds": wall,
                     "recent_success": float(np.mean(np.concatenate(self.recent)
                                                     == Outcome.SUCCESS))})

    def validate_chunk(self, helper: Executor | None) -> None:
        """Score the network as it is now; the best-scoring one so far is kept aside."""
        done, scores = self.progress.episodes_done, self.progress.checkpoint_scores
        scores.append({"episode": done, **validate(
            self.scenario, self.learner.net.inference(), self.config.validation_episodes,
            self.config.uav_count(self.scenario), helper), "resident_mib": resident_mib()})
        leader = best_score(scores)
        if leader is scores[-1]:
            self.learner.keep_as_best()
        self.report({"phase": "validation", "episodes_done": done,
                     "success_rate": scores[-1]["success_rate"],
                     "best_episode": leader["episode"],
                     "best_success_rate": leader["success_rate"]})


def run_card(scenario: Scenario, config: TrainConfig, learning: TdLearning, command: str,
             commit: str) -> dict[str, Any]:
    """The card of the run's result: how it was made, where, and which checkpoint won."""
    progress = learning.progress
    done, td_seconds, scores = (progress.episodes_done, progress.td_seconds,
                                progress.checkpoint_scores)
    validation = dict(best_score(scores))
    selected_episode = validation.pop("episode")
    validation.pop("resident_mib", None)
    return {
        "command": command,
        "scenario": scenario.name,
        "seed": config.seed,
        "episodes": done,
        "envs": config.envs,
        "uavs": config.uav_count(scenario),
        "wall_seconds": round(learning.wall_seconds(), 1),
        "decisions": progress.decisions,
        "decisions_per_second": (round(progress.decisions / td_seconds, 1) if td_seconds
                                 else None),
        "episodes_per_second": round(done / td_seconds, 2) if td_seconds else None,
        "orca_initialization": progress.orca,
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

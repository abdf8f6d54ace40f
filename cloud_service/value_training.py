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
import platform
import signal
import subprocess
import threading
import time
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import torch

from cloud_service.rollout import (
    LookaheadController,
    OrcaController,
    RasterMaps,
    fly_episodes,
    outcome_rates,
    perfect_maps,
    run_episodes,
)
from cloud_service.training_checkpoint import (
    VALUE_NET_FILE,
    Checkpoint,
    forget_logged_after,
    run_settings,
)
from cloud_service.training_config import TrainConfig
from cloud_service.training_flight import EpisodeStats, TrainingFlight
from cloud_service.value_learner import Learner, discounted_returns, fit_value_net, td_targets
from planning.chosen import lookahead_policy
from planning.features import METHODS, MethodOptions
from planning.networks import ValueNetwork, save_network
from planning.reference import PUBLISHED_LOOKAHEAD
from shared.outcomes import Outcome
from shared.paper import TABLE_I_JAMMERS
from shared.resources import resident_mib
from shared.scenario import Scenario
from world_sim.core import VectorWorld

VALIDATION_SEED = 20210614  # fixed: every model is scored on the same episodes
LOG_FIELDS = ["episode", "wall_seconds", "epsilon", "mean_return", "straight_bound",
              "success", "disconnection", "collision", "timeout"]


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


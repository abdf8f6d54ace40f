"""Training's mini-batch step (one Adam step on 200 states of the extended network): torch's
step, the reference, against the compiled core's (``cloud_service.adam_step``), on the
same batches from the same start, in one run; and how far apart the two networks are after
300 steps."""

from __future__ import annotations

import copy
import time

import numpy as np
import torch

from benchmarks.common import Figure
from cloud_service.adam_step import CompiledStep, torch_step
from cloud_service.torch_networks import TorchValueNetwork
from cloud_service.training_config import TrainConfig
from cloud_service.value_learner import adam
from planning.features import EXTENDED_METHOD, joint_state_size
from shared.scenario import load_scenario

BATCH, STEPS, TIMED = 200, 300, 2000


def run() -> list[Figure]:
    scenario = load_scenario()
    size = joint_state_size(scenario, EXTENDED_METHOD)
    torch.manual_seed(0)
    start = TorchValueNetwork(size, scenario.policy.value_scale, EXTENDED_METHOD._asdict())
    rng = np.random.default_rng(0)
    states = (rng.standard_normal((20_000, size)) * 5 + 2).astype(np.float32)
    values = rng.uniform(-1.9, 1.9, 20_000).astype(np.float32)
    start.standardize.fit(torch.from_numpy(states))
    nets = {name: copy.deepcopy(start) for name in ("torch", "compiled")}
    config = TrainConfig(method="extended")
    steps = {"torch": torch_step(nets["torch"], adam(nets["torch"], config)),
             "compiled": CompiledStep(nets["compiled"], adam(nets["compiled"], config))}
    batches = [rng.integers(0, len(values), BATCH) for _ in range(STEPS)]
    for batch in batches:
        for step in steps.values():
            step(states[batch], values[batch])
    apart = max(float((a - b).detach().abs().max()) for a, b in
                zip(nets["torch"].parameters(), nets["compiled"].parameters(), strict=True))
    seconds = {name: step_seconds(step, states, values, rng) for name, step in steps.items()}
    return [
        Figure("training step, 200 states: torch's, median us", 1e6 * seconds["torch"], "us"),
        Figure("training step, 200 states: compiled, median us", 1e6 * seconds["compiled"],
               "us"),
        Figure("training step: compiled against torch's, x", seconds["torch"]
               / seconds["compiled"], "x"),
        Figure(f"parameters apart after {STEPS} steps of the same batches, 1e-6",
               1e6 * apart, "1e-6"),
    ]


def step_seconds(step, states: np.ndarray, values: np.ndarray,
                 rng: np.random.Generator) -> float:
    """The median of TIMED steps on fresh batches, each timed alone."""
    times = []
    for _ in range(TIMED):
        batch = rng.integers(0, len(values), BATCH)
        x, y = states[batch], values[batch]
        begun = time.perf_counter()
        step(x, y)
        times.append(time.perf_counter() - begun)
    return float(np.median(times))

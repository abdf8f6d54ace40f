"""Fitting a SINR-mapping network (the paper's training: Adam, mini-batches of 200, L2
1e-4, learning rate 5e-3): the only part of the online map that needs torch. The cloud
imports it on first use, so that it serves weights without waiting for torch to load; the
``jamnav fit-sinr`` survey fits its maps here too."""

from __future__ import annotations

import math
import time as wall
from collections.abc import Callable, Iterator
from typing import Any, NamedTuple

import numpy as np
import torch

from cloud_service.adam_step import adam_step
from cloud_service.simulated_measurements import (
    measurements_at,
    simulated_measurements,
    uniform_positions,
)
from cloud_service.torch_networks import TorchSinrMapNetwork
from planning.networks import SinrMapNetwork, accuracy_of, predict_levels
from shared.radio import JammerParams, RadioModel
from shared.scenario import Scenario
from shared.survey_maps import survey_world_digest

BATCH_SIZE = 200  # paper
LEARNING_RATE = 5e-3  # paper
L2 = 1e-4  # paper, as Adam's weight decay
# The level boundaries are sharp and the marginal band (-3 to -2.21 dB) is a few metres wide;
# at the paper's constant rate they stay blurred, and accuracy is lost (BENCHMARKS.md, "Online
# SINR mapping", the GBSs the map sees). A cosine decay to FINAL_LR over the step budget
# settles them; it starts at the paper's rate.
FINAL_LR = 1e-5
FRESH_MEASUREMENTS = 20_000  # scored after fitting: +-0.1 point on an accuracy near 98 %
_EVAL_EVERY = 100  # steps between held-out checks (early stop on target accuracy)


class TrainResult(NamedTuple):
    network: SinrMapNetwork
    accuracy: float  # on the held-out share of the data
    steps: int
    seconds: float


def warm_up(network: SinrMapNetwork) -> None:
    """Pay torch's one-off set-up of a fit before a jammer change needs one: the first fit in
    a process takes seconds longer than the next (BENCHMARKS.md, "Distributed runtime"). Two
    steps on rows of zeros, thrown away; torch's global random state is left as it was, so no
    later fit changes."""
    rows = np.zeros((8, network.input_size), dtype=np.float32)
    with torch.random.fork_rng():
        train_sinr_map(rows, np.zeros(8, dtype=np.int64), network.levels, network=network,
                       steps=2)


def train_sinr_map(
    features: np.ndarray,
    levels: np.ndarray,
    level_count: int,
    *,
    network: SinrMapNetwork | None = None,
    steps: int = 10_000,
    max_seconds: float | None = None,
    target_accuracy: float | None = None,
    holdout: float = 0.2,
    seed: int = 0,
    progress: Callable[[int, float], None] | None = None,
    stop: Callable[[], bool] | None = None,
) -> TrainResult:
    """Fit a SINR-mapping network to measurements ``features`` (n, F) -> ``levels`` (n,).

    A share ``holdout`` of the rows is kept out of training to measure accuracy. Training
    stops after ``steps`` mini-batches, or once ``max_seconds`` have passed, or as soon as the
    held-out accuracy reaches ``target_accuracy`` (checked every 100 steps), or at once when
    ``stop()`` says so (a cloud shutting down).

    Without ``network`` a fresh one is built and its standardization fitted on the training
    rows. With ``network`` (the current map) training continues from a copy of it, keeping
    its standardization: refitting would change what the learned weights mean, and positions
    are distributed alike before and after a jammer change anyway.

    ``progress(step, held_out_accuracy)`` is called at every check.
    """
    started = wall.perf_counter()
    features = torch.as_tensor(np.asarray(features, dtype=np.float32))
    levels = torch.as_tensor(np.asarray(levels, dtype=np.int64))
    if len(levels) < 2:
        raise ValueError("training needs at least two measurements")
    generator = torch.Generator().manual_seed(seed)
    (train_x, train_y), (test_x, test_y) = _held_out(features, levels, holdout, generator)
    module = _module_to_train(network, train_x, level_count, seed)
    test_x, test_y = test_x.numpy(), test_y.numpy()
    trained = module.inference()  # reads the module's memory: it follows every step
    optimizer = torch.optim.Adam(module.parameters(), lr=LEARNING_RATE, weight_decay=L2)
    step, rates = adam_step(module, optimizer), cosine_rates(steps)
    train_x, train_y = train_x.numpy(), train_y.numpy()
    batches = mini_batches(len(train_y), generator)
    accuracy, done = float("nan"), 0
    while done < steps:
        rows = next(batches).numpy()
        optimizer.param_groups[0]["lr"] = next(rates)
        step(train_x[rows], train_y[rows])
        done += 1
        if done % _EVAL_EVERY == 0 or done == steps:
            accuracy = accuracy_of(trained, test_x, test_y)
            if progress is not None:
                progress(done, accuracy)
            if target_accuracy is not None and accuracy >= target_accuracy:
                break
            if max_seconds is not None and wall.perf_counter() - started >= max_seconds:
                break
        if stop is not None and stop():
            break
    return TrainResult(trained, accuracy, done, wall.perf_counter() - started)


def cosine_rates(steps: int) -> Iterator[float]:
    """The learning rate of each of ``steps`` steps in turn: from the paper's rate down to
    FINAL_LR along half a cosine, by the recurrence torch's scheduler (CosineAnnealingLR)
    follows rather than the closed form, so that a map fitted by torch's step is, bit for bit,
    the one it gave before the compiled step was."""
    rate = LEARNING_RATE
    for done in range(1, steps + 1):
        yield rate
        rate = ((1 + math.cos(math.pi * done / steps))
                / (1 + math.cos(math.pi * (done - 1) / steps)) * (rate - FINAL_LR) + FINAL_LR)


def _held_out(features: torch.Tensor, levels: torch.Tensor, holdout: float,
              generator: torch.Generator):
    """The rows to train on and the share ``holdout`` kept out to score the fit (at least
    one of each), drawn with ``generator``: ((features, levels), (features, levels))."""
    n = len(levels)
    order = torch.randperm(n, generator=generator)
    held = min(n - 1, max(1, round(holdout * n)))
    kept, train = order[:held], order[held:]
    return (features[train], levels[train]), (features[kept], levels[kept])


def _module_to_train(network: SinrMapNetwork | None, train_x: torch.Tensor, level_count: int,
                     seed: int) -> TorchSinrMapNetwork:
    """A copy of ``network`` to train further, keeping its standardization; without one, a
    fresh network (initialized from ``seed``, torch's global random state left as it was)
    standardized on the training rows ``train_x``."""
    if network is None:
        with torch.random.fork_rng():
            torch.manual_seed(seed)
            module = TorchSinrMapNetwork(train_x.shape[1], level_count)
        module.standardize.fit(train_x)
    else:
        module = TorchSinrMapNetwork(network.input_size, network.levels)
        module.assign(network)
    return module


def mini_batches(count: int, generator: torch.Generator) -> Iterator[torch.Tensor]:
    """Rows of ``BATCH_SIZE`` out of ``count``, in an order ``generator`` reshuffles at each
    new epoch; an epoch's rows too few for a whole batch are left out."""
    order = torch.randperm(count, generator=generator)
    cursor = 0
    while True:
        if cursor + BATCH_SIZE > len(order):  # a new epoch: reshuffle
            order = torch.randperm(count, generator=generator)
            cursor = 0
        yield order[cursor : cursor + BATCH_SIZE]
        cursor += BATCH_SIZE


def fit_sinr_map(
    scenario: Scenario,
    jammer: JammerParams | None,
    samples: int,
    steps: int,
    seed: int,
    progress: Callable[[int, float], None] | None = None,
) -> tuple[SinrMapNetwork, dict[str, Any]]:
    """A SINR map for one jammer (or none) from ``samples`` simulated measurements, scored on
    fresh measurements drawn apart from the training ones: against their reported levels, and
    against the true levels at the same positions. Returns the network and the figures for
    its card."""
    started = wall.perf_counter()
    train_rng, test_rng = (np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(2))
    data = simulated_measurements(scenario, jammer, samples, train_rng)
    result = train_sinr_map(data.features, data.levels, scenario.channel.level_count,
                            steps=steps, seed=seed, progress=progress)
    radio = RadioModel(scenario)
    fresh_xy = uniform_positions(scenario, FRESH_MEASUREMENTS, test_rng)
    fresh = measurements_at(scenario, radio, jammer, fresh_xy, test_rng)
    true_levels = radio.evaluate(fresh_xy, jammer).level
    right = predict_levels(result.network, fresh.features) == true_levels
    counts = np.bincount(true_levels, minlength=scenario.channel.level_count)
    figures = {
        "scenario": scenario.name,
        "survey_world": survey_world_digest(scenario),
        "jammer": None if jammer is None else dict(jammer._asdict()),
        "seed": seed,
        "samples": samples,
        "steps": result.steps,
        "accuracy": accuracy_of(result.network, fresh.features, fresh.levels),
        # Reports carry the receivers' noise, which caps any map's score on them; this is the
        # map's score on the world itself.
        "accuracy_on_true_levels": float(right.mean()),
        # Where the map errs: of the points at each true level, the share it gets right, and
        # how much of the area each level holds. With noisy reports a band narrower than the
        # noise is rarely the level reported most, so a map of reports seldom shows it.
        "accuracy_by_true_level": [float(right[true_levels == level].mean()) if count else None
                                   for level, count in enumerate(counts.tolist())],
        "true_level_shares": (counts / counts.sum()).tolist(),
        "fresh_measurements": FRESH_MEASUREMENTS,
        "held_out_accuracy": result.accuracy,
        "wall_seconds": round(wall.perf_counter() - started, 2),
    }
    return result.network, figures

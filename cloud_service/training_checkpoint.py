"""Checkpoints of a value-network training run, and the durable writes they rest on.

A checkpoint holds everything ``jamnav train --resume`` needs to go on as if never stopped:
the networks, the optimizer, the replay memory and the run's progress, under
``<out>/checkpoint/``. A kill at any moment of a save leaves a whole set to resume from, and a
resumed run refuses one made with other settings or damaged since.
"""

from __future__ import annotations

import io
import json
import os
import shutil
import tempfile
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from safetensors import SafetensorError
from safetensors.numpy import load as bytes_to_arrays
from safetensors.numpy import save as arrays_to_bytes

from cloud_service.training_config import TrainConfig
from cloud_service.value_learner import Learner
from planning.networks import WeightsError, card_path, from_bytes, sha256, to_bytes
from shared.scenario import Scenario


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
    falling = config.final_learning_rate is not None
    return {"--scenario": f"{scenario.name} [sha256 {sha256(content.encode())[:12]}]",
            "--method": config.method, "--seed": config.seed,
            "--uavs": config.uav_count(scenario), "--final-lr": config.final_learning_rate,
            # A falling rate falls over the run's episodes: more of them would raise it again.
            "--episodes": config.episodes if falling else None}


def _shown(option: str, value: Any) -> Any:
    """A setting as the option that sets it is written."""
    return "constant" if option == "--final-lr" and value is None else value


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
                    f"{option} {_shown(option, saved.get(option))} "
                    f"(not {_shown(option, asked[option])})"
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


def forget_logged_after(log_path: Path, episodes: int) -> None:
    """Keep the header and the rows of the first ``episodes`` episodes: the rows a killed run
    logged after its last checkpoint are flown and logged again by the resumed run."""
    lines = log_path.read_bytes().splitlines(keepends=True)
    staged = log_path.with_name(f"{log_path.name}.tmp")
    staged.write_bytes(b"".join(lines[: episodes + 1]))
    os.replace(staged, log_path)

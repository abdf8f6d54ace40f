"""Checkpoints survive a kill at any moment of a save: the training process is SIGKILLed
while it writes its second checkpoint, and the run resumes from whichever set is whole."""

from __future__ import annotations

import collections
import csv
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from cloud_service import value_training
from cloud_service.value_training import Checkpoint, TrainConfig, train
from jamnav.cli import _check_checkpoint as check_checkpoint
from shared.networks import WeightsError, from_bytes
from shared.scenario import load_scenario

ROOT = Path(__file__).resolve().parent.parent


def tiny(episodes: int) -> TrainConfig:
    return TrainConfig(episodes=episodes, envs=8, orca_episodes=40, orca_epochs=2,
                       checkpoint_every_episodes=20, validation_episodes=1)


def train_and_die(out: str, victim: str) -> None:
    """Child process: train 40 episodes and SIGKILL itself in the second checkpoint's save,
    halfway through writing the file named ``victim``, or on removing the first checkpoint
    when ``victim`` is "rmtree"."""
    writes: collections.Counter[str] = collections.Counter()
    write = value_training.write_synced

    def die(*_args) -> None:
        os.kill(os.getpid(), signal.SIGKILL)

    def write_or_die(path: Path, data: bytes) -> None:
        writes[path.name] += 1
        if path.name == victim and writes[path.name] == 2:
            write(path, data[: len(data) // 2])
            die()
        write(path, data)

    value_training.write_synced = write_or_die
    if victim == "rmtree":
        value_training.shutil.rmtree = die
    train(load_scenario(), tiny(40), Path(out))


def killed_run(out: Path, victim: str) -> None:
    child = subprocess.run(
        [sys.executable, "-c",
         f"from tests.test_checkpoint import train_and_die; train_and_die({str(out)!r}, "
         f"{victim!r})"],
        cwd=ROOT, env=dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1"),
        capture_output=True, text=True, timeout=300)
    assert child.returncode == -signal.SIGKILL, child.stderr


def resume(scenario, out: Path, episodes: int) -> tuple[int, dict]:
    """Resume the run in ``out`` to ``episodes``: the episode it resumed at, and its card."""
    resumed_at = []

    def progress(info: dict) -> None:
        if info["phase"] == "resume":
            resumed_at.append(info["episodes_done"])

    card = train(scenario, tiny(episodes), out, resume=True, progress=progress)
    return resumed_at[0], card


def logged_episodes(out: Path) -> list[int]:
    with (out / "train_log.csv").open() as handle:
        return [int(row["episode"]) for row in csv.DictReader(handle)]


def progress_of(directory: Path) -> dict:
    return json.loads((directory / "progress.json").read_text())


def test_killed_mid_file_the_previous_checkpoint_resumes(scenario, tmp_path):
    killed_run(tmp_path, "value.safetensors")
    checkpoint = Checkpoint(tmp_path)
    assert progress_of(checkpoint.dir)["episodes_done"] == 20
    # Not vacuous: the newest files are broken, and the in-place layout would have read them.
    unfinished = [d for d in checkpoint.root.iterdir() if d.is_dir() and d != checkpoint.dir]
    assert len(unfinished) == 1 and not (unfinished[0] / "progress.json").exists()
    with pytest.raises(WeightsError):
        from_bytes((unfinished[0] / "value.safetensors").read_bytes())
    check_checkpoint(tmp_path, scenario, "paper")  # what `jamnav train --resume` checks first

    resumed_at, card = resume(scenario, tmp_path, 40)
    assert resumed_at == 20 and card["episodes"] == 40
    assert [c["episode"] for c in card["selection"]["checkpoints"]] == [20, 40]
    assert logged_episodes(tmp_path) == list(range(1, 41))
    assert progress_of(checkpoint.dir)["episodes_done"] == 40
    # The save that ended the resumed run removed the killed save's and the older set.
    assert sorted(entry.name for entry in checkpoint.root.iterdir()) == sorted(
        ["current", checkpoint.dir.name])


@pytest.mark.parametrize(("victim", "whole"), [("current.tmp", 20), ("rmtree", 40)],
                         ids=["before the pointer switch", "after the pointer switch"])
def test_killed_around_the_pointer_switch_one_set_resumes(scenario, tmp_path, victim, whole):
    killed_run(tmp_path, victim)
    checkpoint = Checkpoint(tmp_path)
    sets = sorted(progress_of(d)["episodes_done"] for d in checkpoint.root.iterdir()
                  if d.is_dir())
    assert sets == [20, 40]  # both complete: only the pointer tells which one counts
    resumed_at, card = resume(scenario, tmp_path, 40)
    assert resumed_at == whole and card["episodes"] == 40
    assert logged_episodes(tmp_path) == list(range(1, 41))

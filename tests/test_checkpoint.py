"""Checkpoints survive a kill at any moment of a save: the training process is SIGKILLed
while it writes its second checkpoint, and the run resumes from whichever set is whole.
Ctrl-C saves one. `jamnav train` refuses, in one line, a checkpoint it cannot continue (a file
missing or damaged, other settings, no episodes to add) and a fresh start that would throw
one away."""

from __future__ import annotations

import collections
import csv
import functools
import json
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from cloud_service import training_checkpoint, training_config, value_training
from cloud_service.training_checkpoint import Checkpoint
from cloud_service.training_config import TrainConfig
from cloud_service.value_training import train
from jamnav.cli import main
from jamnav.cli_training import _check_checkpoint as check_checkpoint
from planning.networks import WeightsError, from_bytes
from shared.scenario import SCENARIO_DIR, load_scenario

ROOT = Path(__file__).resolve().parent.parent


def tiny(episodes: int) -> TrainConfig:
    return TrainConfig(episodes=episodes, envs=8, orca_episodes=40, orca_epochs=2,
                       checkpoint_every_episodes=20, validation_episodes=1)


def train_and_die(out: str, victim: str) -> None:
    """Child process: train 40 episodes and SIGKILL itself in the second checkpoint's save,
    halfway through writing the file named ``victim``, or on removing the first checkpoint
    when ``victim`` is "rmtree"."""
    writes: collections.Counter[str] = collections.Counter()
    write = training_checkpoint.write_synced

    def die(*_args) -> None:
        os.kill(os.getpid(), signal.SIGKILL)

    def write_or_die(path: Path, data: bytes) -> None:
        writes[path.name] += 1
        if path.name == victim and writes[path.name] == 2:
            write(path, data[: len(data) // 2])
            die()
        write(path, data)

    training_checkpoint.write_synced = write_or_die
    if victim == "rmtree":
        training_checkpoint.shutil.rmtree = die
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
    check_checkpoint(tmp_path, scenario, tiny(40), True)  # what `train --resume` checks first

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


# -- Ctrl-C ------------------------------------------------------------------------------------
def ctrl_c_at(episode: int, presses: int = 1, phases: list | None = None):
    """A progress callback that presses Ctrl-C ``presses`` times when ``episode`` is done,
    and keeps what it was told in ``phases``."""
    def progress(info: dict) -> None:
        if phases is not None:
            phases.append(info)
        if info["phase"] == "td" and info["episodes_done"] == episode:
            for _ in range(presses):
                signal.raise_signal(signal.SIGINT)
    return progress


def test_ctrl_c_saves_a_checkpoint_that_resumes_like_any_other(scenario, tmp_path):
    phases: list[dict] = []
    with pytest.raises(KeyboardInterrupt):
        train(scenario, tiny(40), tmp_path, progress=ctrl_c_at(13, phases=phases))
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # given back
    assert phases[-1] == {"phase": "interrupted", "episodes_done": 13,
                          "checkpoint": str(Checkpoint(tmp_path).dir)}
    saved = progress_of(Checkpoint(tmp_path).dir)
    assert saved["episodes_done"] == 13 and saved["checkpoint_scores"] == []
    # The episodes in flight are dropped; the resumed run flies the unstarted ones.
    assert 13 < saved["next_episode"] <= 20
    assert logged_episodes(tmp_path) == list(range(1, 14))

    resumed_at, card = resume(scenario, tmp_path, 40)
    assert resumed_at == 13 and card["episodes"] == 40
    # Validated where an uninterrupted run validates, and logged without a gap.
    assert [c["episode"] for c in card["selection"]["checkpoints"]] == [20, 40]
    assert logged_episodes(tmp_path) == list(range(1, 41))


def test_ctrl_c_during_validation_loses_nothing(scenario, tmp_path, monkeypatch):
    validate = value_training.validate

    def pressed_during(*args):
        signal.raise_signal(signal.SIGINT)
        return validate(*args)

    monkeypatch.setattr(value_training, "validate", pressed_during)
    with pytest.raises(KeyboardInterrupt):
        train(scenario, tiny(40), tmp_path)
    saved = progress_of(Checkpoint(tmp_path).dir)
    assert saved["episodes_done"] == 20
    assert [s["episode"] for s in saved["checkpoint_scores"]] == [20]


def test_a_second_ctrl_c_stops_at_once(scenario, tmp_path):
    with pytest.raises(KeyboardInterrupt):
        train(scenario, tiny(40), tmp_path, progress=ctrl_c_at(13, presses=2))
    assert not Checkpoint(tmp_path).exists()  # the first regular one is at 20
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_jamnav_train_says_where_ctrl_c_left_the_run(tmp_path, monkeypatch, capsys):
    from jamnav.progress import ProgressBar

    monkeypatch.setattr(training_config, "TrainConfig", functools.partial(
        TrainConfig, orca_episodes=40, orca_epochs=2, checkpoint_every_episodes=20,
        validation_episodes=1))
    update = ProgressBar.update

    def update_and_press(bar, done, *args, **kwargs):
        update(bar, done, *args, **kwargs)
        if done == 13:
            signal.raise_signal(signal.SIGINT)

    monkeypatch.setattr(ProgressBar, "update", update_and_press)
    out = tmp_path / "run"
    argv = ["train", "--episodes", "40", "--envs", "8", "--out", str(out)]
    assert main(argv) == 130
    stopped = capsys.readouterr().err.splitlines()[-2:]
    assert stopped == [f"train: stopped after 13 episodes, all of them in the checkpoint in "
                       f"{Checkpoint(out).dir}: --resume continues it", "jamnav: interrupted"]
    monkeypatch.setattr(ProgressBar, "update", update)
    assert main([*argv, "--resume"]) == 0
    assert json.loads(capsys.readouterr().out)["episodes"] == 40


# -- what `jamnav train` refuses -----------------------------------------------------------------
class Reached(Exception):
    """train() was reached: the arguments were accepted."""


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory) -> Path:
    """A finished run of 20 episodes on the default scenario (4 UAVs), seed 0, paper method."""
    out = tmp_path_factory.mktemp("finished") / "run"
    train(load_scenario(), tiny(20), out)
    return out


@pytest.fixture
def run(finished_run, tmp_path, monkeypatch) -> Path:
    """A copy of ``finished_run`` to spoil, with train() replaced by a trap."""
    def trap(*_args, **_kwargs):
        raise Reached

    monkeypatch.setattr(value_training, "train", trap)
    copy = tmp_path / "run"
    shutil.copytree(finished_run, copy)
    return copy


def refusal(capsys, *argv: str) -> str:
    """The one line `jamnav train ARGV` refuses with (exit 2, no traceback)."""
    assert main(["train", *argv]) == 2
    out, err = capsys.readouterr()
    assert out == "" and len(err.splitlines()) == 1, err
    assert err.startswith("jamnav: error: ")
    return err.strip()


def spoil_truncated(path: Path) -> None:
    path.write_bytes(path.read_bytes()[:300])


def spoil_missing(path: Path) -> None:
    path.unlink()


def spoil_one_bit(path: Path) -> None:
    data = bytearray(path.read_bytes())
    data[len(data) * 3 // 4] ^= 0x10  # inside the tensors: it still parses
    path.write_bytes(bytes(data))


CHECKPOINT_FILES = ["value.safetensors", "target.safetensors", "best.safetensors",
                    "memory.safetensors", "optimizer.pt"]


@pytest.mark.parametrize("spoil", [spoil_truncated, spoil_missing, spoil_one_bit],
                         ids=["truncated", "missing", "one bit flipped"])
@pytest.mark.parametrize("name", CHECKPOINT_FILES)
def test_a_damaged_checkpoint_file_is_refused_in_one_line(run, capsys, name, spoil):
    damaged = Checkpoint(run).dir / name
    spoil(damaged)
    line = refusal(capsys, "--resume", "--out", str(run), "--episodes", "40")
    assert line.startswith(f"jamnav: error: --resume: {damaged}: ")


@pytest.mark.parametrize("name", CHECKPOINT_FILES)
def test_a_damaged_file_of_a_checkpoint_without_digests_is_refused(run, capsys, name):
    """Checkpoints written before progress.json recorded the files' digests: each file's own
    format tells (torch's advice to unpickle with weights_only=False never shows)."""
    progress = Checkpoint(run).dir / "progress.json"
    saved = json.loads(progress.read_text())
    del saved["sha256"]
    progress.write_text(json.dumps(saved))
    damaged = Checkpoint(run).dir / name
    spoil_truncated(damaged)
    line = refusal(capsys, "--resume", "--out", str(run), "--episodes", "40")
    assert line.startswith(f"jamnav: error: --resume: {damaged}: ")
    assert "weights_only" not in line


def edited_icc2021(directory: Path) -> Path:
    """icc2021 under its own name, with another arrival reward."""
    text = (SCENARIO_DIR / "icc2021.toml").read_text()
    assert "\narrival = 2.0 " in text
    directory.mkdir()
    (directory / "icc2021.toml").write_text(text.replace("\narrival = 2.0 ", "\narrival = 1.5 "))
    return directory / "icc2021.toml"


@pytest.mark.parametrize(("argv", "named"), [
    (["--uavs", "3"], ["--uavs 4 (not 3)"]),
    (["--seed", "5"], ["--seed 0 (not 5)"]),
    (["--method", "extended"], ["--method paper (not extended)"]),
    (["--seed", "5", "--uavs", "2"], ["--seed 0 (not 5)", "--uavs 4 (not 2)"]),
    (["--scenario", "icc2021-tt6"], ["--scenario icc2021 [sha256 "]),
    (["--scenario", "{edited}"], ["--scenario icc2021 [sha256 ", "(not icc2021 [sha256 "]),
], ids=["uavs", "seed", "method", "seed and uavs", "scenario", "scenario edited"])
def test_resuming_with_other_settings_is_refused(run, capsys, tmp_path, argv, named):
    edited = edited_icc2021(tmp_path / "edited")
    argv = [part.format(edited=edited) for part in argv]
    card = (run / "value_net.json").read_bytes()
    line = refusal(capsys, "--resume", "--out", str(run), "--episodes", "40", *argv)
    assert line.startswith(f"jamnav: error: --resume: the checkpoint in {Checkpoint(run).dir} "
                           "was made with ")
    assert all(setting in line for setting in named), line
    assert (run / "value_net.json").read_bytes() == card


def test_resuming_with_the_same_settings_spelt_out_is_accepted(run):
    with pytest.raises(Reached):  # 4 UAVs is the scenario's own count
        main(["train", "--resume", "--out", str(run), "--episodes", "40", "--uavs", "4",
              "--seed", "0", "--method", "paper", "--scenario", "icc2021"])


@pytest.mark.parametrize("episodes", ["10", "20"])
def test_resuming_must_add_episodes(run, capsys, episodes):
    line = refusal(capsys, "--resume", "--out", str(run), "--episodes", episodes)
    assert line == (f"jamnav: error: --resume: the checkpoint in {Checkpoint(run).dir} already "
                    "holds 20 episodes; --episodes must exceed it")
    with pytest.raises(Reached):
        main(["train", "--resume", "--out", str(run), "--episodes", "21"])


def test_a_fresh_start_over_a_checkpoint_is_refused(run, capsys):
    before = {path: path.read_bytes() for path in run.rglob("*") if path.is_file()}
    line = refusal(capsys, "--out", str(run), "--episodes", "40")
    assert line == (f"jamnav: error: --out {run} holds a checkpoint of 20 episodes: --resume "
                    f"continues it; to start afresh, remove {run / 'checkpoint'} or choose "
                    "another --out")
    assert {path: path.read_bytes() for path in run.rglob("*") if path.is_file()} == before

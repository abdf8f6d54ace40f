"""The examples (examples/README.md) run as a user runs them: as scripts, against a system
``jamnav up`` started on a free loopback port, then against that system's recording."""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

from jamnav.recording import Recording
from tests.support import Drained, free_endpoint, wait_until

ROOT = Path(__file__).resolve().parent.parent


def example(name: str, *argv: str, timeout: float = 120, check: bool = True) -> list[str]:
    """The lines ``examples/<name>.py`` prints; it must exit 0 (``check``; else the lines
    of a run that did, and None for one that did not)."""
    done = subprocess.run([sys.executable, str(ROOT / "examples" / f"{name}.py"), *argv],
                          cwd=ROOT, capture_output=True, text=True, timeout=timeout)
    assert done.returncode == 0 or not check, done.stderr[-2000:]
    return done.stdout.splitlines() if done.returncode == 0 else None


def test_watch_move_the_jammer_and_read_the_recording_of_a_live_system(supervisor, tmp_path):
    endpoint, run_dir = free_endpoint(), tmp_path / "run"
    system = supervisor("--uavs", "2", "--realtime", "--rate", "20", "--map", "perfect",
                        "--no-figures", "--endpoint", endpoint, "--run-dir", str(run_dir),
                        "--record", str(run_dir / "run.mcap"))
    drained = Drained(system)  # the supervisor's lines, read as they come
    # A line a world step, once the system is up (a client gives up on a router it does not
    # reach in 15 s: a loaded machine may start the router later).
    lines = wait_until(lambda: example("watch", "--connect", endpoint, "--count", "5",
                                       check=False), 90, "the system's first steps")
    steps = [line for line in lines if line.startswith("world: episode ")]
    assert len(lines) == 5 and all(line.startswith(("world: ", "cloud: ")) for line in lines)
    assert steps and steps[-1].endswith("jammers 0 at (0, 0)")  # the scenario's

    # Watching while the jammer moves: 300 lines are 15 s of the world's steps at 20 a second.
    watch = subprocess.Popen([sys.executable, str(ROOT / "examples" / "watch.py"), "--connect",
                              endpoint, "--count", "300"], cwd=ROOT, stdout=subprocess.PIPE,
                             text=True)
    try:
        assert watch.stdout.readline().startswith("world: ")  # it listens
        moved = example("move_jammer", "--connect", endpoint, "25,-10,1")
        assert len(moved) == 1 and moved[0].startswith("accepted: jammer moved to (25, -10), 1 W")
        refused = subprocess.run([sys.executable, str(ROOT / "examples" / "move_jammer.py"),
                                  "--connect", endpoint, "500,0,1"], capture_output=True,
                                 text=True, timeout=60)
        assert refused.returncode == 2 and "refused (position (500, 0) outside" in refused.stdout
        watched, _ = watch.communicate(timeout=120)
    finally:
        watch.kill()
        watch.wait(30)
    assert watch.returncode == 0
    # The world flies on the new jammer, and the cloud puts the true map of it.
    assert "cloud: SINR map v2 (perfect)" in watched.splitlines()
    assert [line for line in watched.splitlines()
            if line.startswith("world: ")][-1].endswith("jammers 0 at (25, -10)")

    system.send_signal(signal.SIGINT)  # Ctrl-C: the run ends, the recording is closed
    out, err = drained.wait(60)
    assert system.returncode == 0, err[-2000:]
    lines = example("read_recording", str(run_dir / "run.mcap"))
    events = [line.split(" ", 1)[1] for line in lines if not line.split()[0].isdigit()]
    assert "jammer moved to (25, -10), 1 W" in "\n".join(events)
    counts = {parts[1]: int(parts[0]) for parts in map(str.split, lines) if parts[0].isdigit()}
    with Recording(run_dir / "run.mcap") as recording:
        keys = [item.key for item in recording.messages()]
    assert counts == {key: keys.count(key) for key in set(keys)}
    assert counts["jamnav/world/state"] > 5 and counts["jamnav/event/jammer_changed"] == 1


def test_a_pettingzoo_episode_flown_by_the_planner_ends_each_uav_once():
    lines = example("pettingzoo_episode", "--uavs", "4", "--seed", "0")
    assert sorted(line.split(":")[0] for line in lines) == ["uav_0", "uav_1", "uav_2", "uav_3"]
    assert all(line.split(": ")[1].split(" at step ")[0]
               in ("success", "disconnection", "collision", "timeout") for line in lines)
    assert example("pettingzoo_episode", "--uavs", "4", "--seed", "0") == lines  # seeded

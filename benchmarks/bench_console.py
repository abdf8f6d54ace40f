"""What the operator's console costs and keeps up with, with its page open in a headless
Chromium (Debian's, as the browser test drives it):

- the lockstep step rate of 4 agent processes with the console and its page, against the same
  run with ``--no-web`` (alternated, best of each), and, steadier on a busy machine, the CPU
  time of the console and the browser against that of the system's own processes;
- the updates a page receives per second, and the console's own CPU time, with 50 UAVs: a
  synthetic world on a private router puts a 50-UAV ``WorldState`` 20 times a second (twice
  the pushes: every push has something new), with its outcomes, a jammer and a SINR map.
"""

from __future__ import annotations

import json
import math
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from benchmarks.common import Figure
from planning.networks import sha256
from shared import bus
from shared.cloud_messages import SinrMap
from shared.events import UavOutcomes
from shared.jammer_messages import JammerInfo, JammerReply
from shared.shipped import SINR_MAP_NO_JAMMER
from shared.topics import Topics
from shared.wire import encode
from shared.world_messages import WorldState
from tests import browser as chromium

ROOT = Path(__file__).resolve().parent.parent
UAVS, EPISODES, REPEATS = 4, "80", 3
WATCHED = {"system": ("jamnav.cli router", "world_sim.process", "cloud_service.process",
                      "uav_agent.process"),
           "console": ("jamnav.cli console",), "browser": ("chromium",)}
FLEET, FLEET_HZ, EPISODE_STEPS = 50, 20.0, 60
WARM_S, WINDOW_S = 5.0, 20.0


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def console_url(process: subprocess.Popen) -> str:
    """The URL a starting ``jamnav up`` or ``jamnav console`` prints; its other lines are
    drained on a thread from then on."""
    for line in process.stderr:
        if "console: http" in line:
            threading.Thread(target=process.stderr.read, daemon=True).start()
            return line.split("console: ")[1].split()[0]
    raise RuntimeError("the console never said where it serves")


def _stat(pid: int | str) -> list[str]:
    """The fields of /proc/PID/stat after the command's name: [1] ppid, [11:13] CPU ticks."""
    return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()


def _cpu_seconds(fields: list[str]) -> float:
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _cpu_of_descendants() -> dict[int, tuple[str, float]]:
    """pid -> (which of ``WATCHED``, CPU seconds so far) of this process's descendants."""
    parents, found = {}, {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            fields = _stat(entry.name)
            command = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode()
        except (OSError, UnicodeDecodeError):  # not a process, or gone meanwhile
            continue
        pid = int(entry.name)
        parents[pid] = int(fields[1])
        which = next((name for name, marks in WATCHED.items()
                      if any(mark in command for mark in marks)), None)
        if which is not None:
            found[pid] = (which, _cpu_seconds(fields))
    me = os.getpid()

    def descends(pid: int) -> bool:
        while pid > 1:
            pid = parents.get(pid, 0)
            if pid == me:
                return True
        return False

    return {pid: seen for pid, seen in found.items() if descends(pid)}


def _cpu_during(process: subprocess.Popen) -> dict[str, float]:
    """CPU seconds per ``WATCHED`` group from now until ``process`` exits (sampled each
    second: a child counts with its last sample)."""
    before, last = _cpu_of_descendants(), {}
    while process.poll() is None:
        last.update(_cpu_of_descendants())
        time.sleep(1.0)
    totals = dict.fromkeys(WATCHED, 0.0)
    for pid, (which, seconds) in last.items():
        totals[which] += seconds - before.get(pid, (which, 0.0))[1]
    return totals


def _lockstep(run_dir: Path, browser=None) -> tuple[float, dict[str, float]]:
    """(steps/s, CPU seconds per group) of a lockstep run, its console's page open in
    ``browser`` if one is given (else with ``--no-web``)."""
    argv = [sys.executable, "-m", "jamnav.cli", "up", "--lockstep", "--uavs", str(UAVS),
            "--episodes", EPISODES, "--map", "perfect", "--no-figures", "--endpoint",
            f"tcp/127.0.0.1:{free_port()}", "--run-dir", str(run_dir)]
    argv += ["--no-web"] if browser is None else ["--web", f"127.0.0.1:{free_port()}"]
    process = subprocess.Popen(argv, cwd=ROOT, stdout=subprocess.DEVNULL, text=True,
                               stderr=subprocess.DEVNULL if browser is None else subprocess.PIPE)
    page = None if browser is None else browser.new_page()
    if page is not None:
        page.goto(console_url(process))
    cpu = _cpu_during(process)
    if page is not None:
        page.close()
    return json.loads((run_dir / "report.json").read_text())["steps_per_second"], cpu


def _fly_synthetic_fleet(endpoint: str, stop: threading.Event) -> None:
    """A world and a cloud as the console sees them: 50 UAVs circling, an outcome per
    episode, a jammer to ``show`` and the shipped SINR map to fetch."""
    topics = Topics()
    data = SINR_MAP_NO_JAMMER.read_bytes()
    served = encode(SinrMap(version=1, sha256=sha256(data), data=data, mode="online"))
    jammer = JammerInfo(x=0, y=0, power_w=1, height_m=30)
    with bus.open_session("client", endpoint) as session:
        session.declare_queryable(topics.sinr_map, lambda q: q.reply(topics.sinr_map, served))
        session.declare_queryable(topics.jammer_control, lambda q: q.reply(
            topics.jammer_control, encode(JammerReply(accepted=True, jammer=jammer, episode=0,
                                                      step=0))))
        states = session.declare_publisher(topics.state)
        step, tick = 0, time.monotonic()
        while not stop.is_set():
            episode, at = divmod(step, EPISODE_STEPS)
            angles = [2 * math.pi * (uav / FLEET + at / EPISODE_STEPS) for uav in range(FLEET)]
            states.put(encode(WorldState(
                episode=episode, step=at, clock="realtime", t=time.time(),
                position=[(40 * math.cos(a), 40 * math.sin(a)) for a in angles],
                velocity=[(0.0, 0.0)] * FLEET, sinr_db=[1.0] * FLEET, level=[1] * FLEET,
                status=["active"] * FLEET, destination=[(0.0, 0.0)] * FLEET)))
            if at == EPISODE_STEPS - 1:
                bus.publish_event(session, topics, UavOutcomes(
                    t=time.time(), source="bench", episode=episode, seed=episode,
                    steps=EPISODE_STEPS, outcomes=["success"] * FLEET))
            step += 1
            tick += 1 / FLEET_HZ
            stop.wait(max(0.0, tick - time.monotonic()))




def _fifty_uavs(playwright) -> tuple[float, float]:
    """(updates the page received per second, the console's CPU in % of a core)."""
    endpoint, stop = f"tcp/127.0.0.1:{free_port()}", threading.Event()
    with bus.open_session("router", endpoint):
        fleet = threading.Thread(target=_fly_synthetic_fleet, args=(endpoint, stop))
        fleet.start()
        console = subprocess.Popen(
            [sys.executable, "-m", "jamnav.cli", "console", "--endpoint", endpoint, "--web",
             f"127.0.0.1:{free_port()}"], cwd=ROOT, text=True, stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE)
        try:
            browser = chromium.launch(playwright)
            page = browser.new_page()
            page.goto(console_url(console))
            page.wait_for_function("window.consoleStats.frames > 0", timeout=60_000)
            time.sleep(WARM_S)
            seen = "[window.consoleStats.frames, window.consoleStats.lastAt]"
            (frames, first), cpu = page.evaluate(seen), _cpu_seconds(_stat(console.pid))
            start = time.monotonic()
            time.sleep(WINDOW_S)
            (later, last), elapsed = page.evaluate(seen), time.monotonic() - start
            # Frames over the time between two of their arrivals, in the page's own clock:
            # good to about 1 ms in 20 s, so to 0.01 update/s.
            updates = round((later - frames) / ((last - first) / 1000), 2)
            load = 100 * (_cpu_seconds(_stat(console.pid)) - cpu) / elapsed
            browser.close()
        finally:
            console.terminate()
            console.wait(30)
            stop.set()
            fleet.join()
    return updates, load


def run() -> list[Figure]:
    from playwright.sync_api import sync_playwright

    without, with_page, shares = [], [], []
    with tempfile.TemporaryDirectory() as tmp, sync_playwright() as playwright:
        browser = chromium.launch(playwright)  # open before, as an operator's would be
        for repeat in range(REPEATS):
            without.append(_lockstep(Path(tmp) / f"plain{repeat}")[0])
            rate, cpu = _lockstep(Path(tmp) / f"page{repeat}", browser)
            with_page.append(rate)
            shares.append(100 * (cpu["console"] + cpu["browser"]) / cpu["system"])
        browser.close()
        updates, load = _fifty_uavs(playwright)
    return [
        Figure(f"lockstep steps/s, {UAVS} agents, --no-web, best of {REPEATS}", max(without),
               "steps/s"),
        Figure(f"lockstep steps/s, {UAVS} agents, console + page open, best of {REPEATS}",
               max(with_page), "steps/s"),
        Figure("console's cost to the lockstep step rate", 100 * (1 - max(with_page)
                                                                  / max(without)), "%", 5, True),
        Figure("console + page CPU, in % of the system's CPU in the same run (median)",
               sorted(shares)[len(shares) // 2], "%"),
        Figure(f"console page updates/s, {FLEET} UAVs ({FLEET_HZ:g} states/s)", updates, "/s",
               10),
        Figure(f"console server CPU, {FLEET} UAVs, page open", load, "% core", 10, True),
    ]

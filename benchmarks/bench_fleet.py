"""Many agent processes on one machine (``jamnav up --no-web``): lockstep steps/s with 4 and
50 agents, launch to first step, an agent's memory and its cold start (process start to its
first action, measured on an agent the supervisor restarts in a running system); what a
lockstep step costs each process in CPU, with 4 agents and with 50 on the city, and the
agents' private memory there; and a hundred
agents in real time at 5 steps/s, whose every action must be in time."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from benchmarks.bench_bus import ROOT, free_endpoint, up_report
from benchmarks.common import Figure
from shared import bus
from shared.process_status import ProcessStatus
from shared.resources import resident_mib
from shared.topics import Topics
from shared.wire import decode
from shared.world_messages import Action, WorldState

COLD_START_RUN_S = 60  # wall seconds the live system may run for the cold-start measurement
CPU_WARM_S, CPU_WINDOW_S = 20, 10  # wall seconds flown before the CPU is read, and between reads
HUNDRED_RUN_S = 60  # seconds of flight of the hundred agents in real time
# A process's role, by what its command line runs.
ROLES = {"world_sim.process": "world", "uav_agent.process": "agent",
         "cloud_service.process": "cloud", "router": "router"}


def agent_pids(endpoint: str) -> dict[str, int]:
    out = subprocess.run([sys.executable, "-m", "jamnav.cli", "status", "--json", "--endpoint",
                          endpoint], cwd=ROOT, check=True, capture_output=True, text=True).stdout
    return {p["id"]: p["pid"] for p in json.loads(out) if p["role"] == "agent" and "pid" in p}


def wait_for(condition, timeout: float, what: str):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if value := condition():
            return value
        time.sleep(0.05)
    raise RuntimeError(f"no {what} within {timeout:g} s")


def cold_start(run_dir: Path) -> tuple[float, float]:
    """Agents' worst resident memory (MiB) in a running 4-UAV system, and the seconds from
    killing an agent to the first action of the one the supervisor starts in its place (real
    time, 10 steps/s): its cold start, plus the supervisor's restart (up to 0.1 s)."""
    endpoint = free_endpoint()
    supervisor = subprocess.Popen(
        [sys.executable, "-m", "jamnav.cli", "up", "--uavs", "4", "--realtime", "--duration",
         str(COLD_START_RUN_S), "--no-web", "--no-figures", "--map", "perfect", "--endpoint",
         endpoint, "--run-dir", str(run_dir)], cwd=ROOT, stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL)
    # An action of the killed agent may still be in flight after the kill: the successor's
    # first action is the first one for a step the world began after it.
    actions: list[tuple[float, int, int]] = []  # arrival, episode, step
    step_began: dict[tuple[int, int], float] = {}
    lock = threading.Lock()

    def on_action(sample) -> None:
        action = decode(Action, sample.payload.to_bytes())
        with lock:
            actions.append((time.time(), action.episode, action.step))

    def on_state(sample) -> None:
        state = decode(WorldState, sample.payload.to_bytes())
        with lock:
            step_began[(state.episode, state.step)] = state.t

    def successor_acted(killed: float) -> float | None:
        with lock:
            return next((arrival for arrival, episode, step in actions
                         if step_began.get((episode, step), 0.0) > killed), None)

    try:
        time.sleep(2.0)  # the router is up
        with bus.open_session("client", endpoint) as session:
            topics = Topics()
            session.declare_subscriber(topics.action(0), on_action)
            session.declare_subscriber(topics.state, on_state)
            wait_for(lambda: len(actions) > 20, 60, "steady flight")
            pids = agent_pids(endpoint)
            memory = max(resident_mib(pid) for pid in pids.values())
            os.kill(pids["0"], signal.SIGKILL)
            killed = time.time()
            first = wait_for(lambda: successor_acted(killed), 30,
                             "first action of the restarted agent")
    finally:
        supervisor.send_signal(signal.SIGTERM)
        supervisor.wait(60)
    return memory, first - killed


def cpu_seconds(pid: int) -> float:
    """User and system CPU a process has used so far (``/proc/PID/stat``)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def private_mib(pid: int) -> float:
    """Memory a process holds for itself alone, shared libraries' pages left out: its private
    clean and dirty pages (``/proc/PID/smaps_rollup``), in MiB."""
    fields = dict(line.split(":", 1) for line in
                  Path(f"/proc/{pid}/smaps_rollup").read_text().splitlines()[1:])
    return sum(int(fields[key].split()[0]) for key in ("Private_Clean", "Private_Dirty")) / 1024


def role_of(pid: int) -> str | None:
    words = Path(f"/proc/{pid}/cmdline").read_bytes().decode().split("\0")
    return next((role for key, role in ROLES.items() if key in words), None)


def cpu_per_step(run_dir: Path, *argv: str) -> tuple[dict[str, tuple[float, int]], list[float]]:
    """Milliseconds of CPU per lockstep step of each role of a ``jamnav up`` run (the
    supervisor's included), and how many processes share it: read twice, CPU_WINDOW_S apart,
    once the run has flown CPU_WARM_S, against the steps the world published meanwhile. And
    each agent's private memory (MiB) at the second reading."""
    endpoint = free_endpoint()
    supervisor = subprocess.Popen(
        [sys.executable, "-m", "jamnav.cli", "up", *argv, "--no-web", "--no-figures",
         "--endpoint", endpoint, "--run-dir", str(run_dir)], cwd=ROOT,
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        time.sleep(2.0)  # the router is up
        with bus.open_session("client", endpoint) as session:
            def steps() -> int:
                status = bus.query(session, Topics().status("world", 0), ProcessStatus,
                                   timeout=5.0)
                return int(status.details["steps"])

            wait_for(lambda: _answers(steps), 120, "a first step")
            time.sleep(CPU_WARM_S)
            children = [int(pid) for pid in Path(f"/proc/{supervisor.pid}/task/"
                                                 f"{supervisor.pid}/children").read_text().split()]
            roles = {pid: role_of(pid) for pid in children} | {supervisor.pid: "supervisor"}
            first, before = steps(), {pid: cpu_seconds(pid) for pid in roles}
            time.sleep(CPU_WINDOW_S)
            after, flown = {pid: cpu_seconds(pid) for pid in roles}, steps() - first
            private = [private_mib(pid) for pid, role in roles.items() if role == "agent"]
    finally:
        supervisor.send_signal(signal.SIGINT)
        supervisor.wait(60)
    cost: dict[str, tuple[float, int]] = {}
    for pid, role in roles.items():
        if role is not None:
            ms, count = cost.get(role, (0.0, 0))
            cost[role] = (ms + 1e3 * (after[pid] - before[pid]) / flown, count + 1)
    return cost, private


def _answers(steps) -> bool:
    """Whether the world has flown a step yet (False while it does not answer)."""
    try:
        return steps() > 0
    except bus.BusError:
        return False


def cpu_figures(tmp: Path) -> list[Figure]:
    figures = []
    for label, argv in (("4 agents", ("--uavs", "4")),
                        ("50 agents, city", ("--scenario", "city", "--uavs", "50"))):
        cost, private = cpu_per_step(tmp / f"cpu-{label[:2].strip()}", "--lockstep", "--map",
                                     "perfect", *argv)
        for role in ("world", "agent", "cloud", "router", "supervisor"):
            ms, count = cost[role]
            each = f" (each of {count}: {ms / count:.2f} ms)" if count > 1 else ""
            figures.append(Figure(f"CPU per lockstep step, {label}: {role}{each}", ms, "ms"))
        figures.append(Figure(f"CPU per lockstep step, {label}: all",
                              sum(ms for ms, _ in cost.values()), "ms"))
        figures.append(Figure(f"private memory of the {len(private)} running agents, {label}: "
                              f"in all (each {min(private):.1f}-{max(private):.1f} MiB)",
                              sum(private), "MiB"))
    return figures


def run() -> list[Figure]:
    figures = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for uavs, episodes, target in ((4, 30, 300), (50, 3, 30)):
            report = up_report(tmp / f"lockstep{uavs}", "--uavs", str(uavs), "--episodes",
                               str(episodes), "--map", "perfect", "--no-web")
            figures.append(Figure(f"lockstep steps/s, {uavs} agent processes, --no-web",
                                  report["steps_per_second"], "steps/s", target))
            figures.append(Figure(f"jamnav up --uavs {uavs}: launch -> first step",
                                  report["first_step_after_s"], "s",
                                  3 if uavs == 4 else None, True))
        memory, start = cold_start(tmp / "cold")
        figures += cpu_figures(tmp)
        hundred = up_report(tmp / "hundred", "--scenario", "city", "--uavs", "100",
                            "--realtime", "--rate", "5", "--duration", str(HUNDRED_RUN_S),
                            "--map", "perfect", "--no-web")
    figures.append(Figure("agent resident memory (worst of 4, flying)", memory, "MiB", 80, True))
    figures.append(Figure("agent killed -> its successor's first action (10 steps/s)",
                          start, "s", 1, True))
    figures.append(Figure(f"100 agents, city, real time at 5 steps/s for {HUNDRED_RUN_S} s: "
                          "missed deadlines", hundred["missed_deadlines"], "", 0, True))
    return figures

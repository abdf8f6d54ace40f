"""``jamnav up``: the whole system as separate OS processes on one machine.

Starts a zenoh router, the cloud, the world and one agent per UAV with ``subprocess`` (the
child execs at once: no child ever runs on a copy of our open zenoh session, which would hang),
follows them over the bus (liveliness, events, world state), shows live progress on stderr,
restarts a child that dies, and stops everything at the end or on Ctrl-C / SIGTERM: children
first with SIGTERM (they close their sessions), SIGKILL for stragglers, the router last.
Children run in their own process group, so a Ctrl-C in the terminal reaches only the
supervisor, and each child stops by itself if the supervisor disappears. The run directory
receives the children's logs, the report JSON and the figures.
"""

from __future__ import annotations

import json
import os
import queue
import signal
import socket
import subprocess
import sys
import threading
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

import zenoh

from cloud_service.sinr_memory import RUN_DIR_FILE
from shared import access, bus
from shared.messages import (
    JammerCommand,
    JammerEstimate,
    JammerInfo,
    JammerReply,
    MessageError,
    ProcessStatus,
    WorldState,
    decode,
    decode_event,
    describe_estimate,
    mapper_summary,
)
from shared.outcomes import FINAL_OUTCOMES
from shared.scenario import Scenario
from shared.topics import Topics
from world_sim.process import initial_jammer, jammer_params

ROOT = Path(__file__).resolve().parent.parent
STOP_GRACE_S = 10.0
RESTART_LIMIT = 5
STATUS_EVERY_S = 2.0
FLUSH_WAIT_S = 5.0


@dataclass
class UpConfig:
    endpoint: str
    run_dir: Path
    prefix: str = "jamnav"
    scenario: str | None = None
    uavs: int = 4
    episodes: int | None = None
    duration: float | None = None
    clock: str = "lockstep"
    rate: float = 10.0
    deadline: float = 2.0
    map: str = "online"
    jammer: str | None = None  # X,Y,P[,H]
    no_jammer: bool = False
    seed: int = 0
    report: Path | None = None
    swap_at: float | None = None  # seconds after the first step
    swap_to: str | None = None  # X,Y,P[,H] or "off"
    retrain_samples: int | None = None
    model: Path | None = None  # the value network the cloud serves
    figures: bool = True
    command: str = "jamnav up"
    secure: bool = False  # logins and access rules enforced by the router
    credentials: Path | None = None  # secure: this file, else fresh ones in run_dir


@dataclass
class Child:
    role: str
    ident: int
    log_path: Path
    process: subprocess.Popen | None = None
    restarts: int = 0

    @property
    def name(self) -> str:
        return self.role if self.role in ("router", "world", "cloud") else f"agent-{self.ident}"


def check_endpoint_free(endpoint: str) -> None:
    """Refuse to start a second router on a port in use (another ``jamnav up``?)."""
    proto, _, address = endpoint.partition("/")
    host, _, port = address.rpartition(":")
    if proto != "tcp" or not port.isdigit():
        return
    with socket.socket(socket.AF_INET6 if ":" in host.strip("[]") else socket.AF_INET) as probe:
        # As a listener binds: connections of a previous run in TIME_WAIT do not count.
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind((host.strip("[]"), int(port)))
        except OSError as exc:
            raise ValueError(f"{endpoint} is in use ({exc.strerror}): is another system "
                             "running? choose --endpoint") from None


class Supervisor:
    def __init__(self, config: UpConfig, scenario: Scenario, stream: TextIO = sys.stderr):
        self.config = config
        self.scenario = scenario
        self.stream = stream
        self.interactive = stream.isatty()
        self.topics = Topics(config.prefix)
        self.stop = threading.Event()
        self.children: dict[str, Child] = {}
        self.launched: list[dict[str, Any]] = []
        self.inbox: queue.SimpleQueue = queue.SimpleQueue()  # events and states, from zenoh
        self.live: set[str] = set()
        self._live_lock = threading.Lock()
        self.events: list[dict[str, Any]] = []
        self.outcomes: dict[int, list[str]] = {}
        self.trajectories: dict[int, list[list[tuple[float, float]]]] = {}
        self.state: WorldState | None = None
        self.first_step: float | None = None
        self.finished: dict[str, Any] | None = None
        self.initial_jammer = initial_jammer(scenario, config.jammer, config.no_jammer)
        self.jammer = self.initial_jammer
        self.swapped = False
        self.stopped_by = "end"
        self.world_status: ProcessStatus | None = None
        self.cloud_status: ProcessStatus | None = None
        self.dropped = bus.Dropped(bus.setup_logging("supervisor"))
        self.credentials_path = (config.credentials or config.run_dir / access.CREDENTIALS_FILE
                                 ) if config.secure else None
        self._last_status = 0.0
        self._last_draw = 0.0

    # -- children ---------------------------------------------------------------------------
    def _argv(self, child: Child) -> list[str]:
        c, python = self.config, [sys.executable, "-m"]
        common = ["--endpoint", c.endpoint, "--prefix", c.prefix]
        if self.credentials_path is not None:
            common += ["--credentials", str(self.credentials_path)]
        if child.role == "router":
            return python + ["jamnav.cli", "router", *common]
        if c.scenario:
            common += ["--scenario", c.scenario]
        jammer = ["--no-jammer"] if self.jammer is None else [
            "--jammer", f"{self.jammer.x!r},{self.jammer.y!r},{self.jammer.power_w!r},"
                        f"{self.jammer.height_m!r}"]
        if child.role == "cloud":
            argv = python + ["cloud_service.process", *common, "--map", c.map,
                             "--run-dir", str(c.run_dir), *jammer]
            if c.retrain_samples is not None:
                argv += ["--retrain-samples", str(c.retrain_samples)]
            if c.model is not None:
                argv += ["--value-net", str(c.model.resolve())]
            return argv
        if child.role == "agent":
            return python + ["uav_agent.process", *common, "--uav", str(child.ident)]
        # A restarted world carries on after the last finished episode, with the jammer in force.
        done = len(self.outcomes)
        argv = python + ["world_sim.process", *common, "--uavs", str(c.uavs), "--seed",
                         str(c.seed), "--clock", c.clock, "--rate", str(c.rate), "--deadline",
                         str(c.deadline), "--first-episode", str(done), *jammer]
        if c.episodes is not None:
            argv += ["--episodes", str(c.episodes - done)]
        if c.duration is not None:
            elapsed = 0.0 if self.first_step is None else time.monotonic() - self.first_step
            argv += ["--duration", str(max(c.duration - elapsed, 0.1))]
        return argv

    def _launch(self, child: Child) -> None:
        env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", PYTHONUNBUFFERED="1")
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
        with child.log_path.open("ab") as log:
            child.process = subprocess.Popen(
                self._argv(child), stdin=subprocess.DEVNULL, stdout=log, stderr=log, env=env,
                start_new_session=True)
        self.launched.append({"role": child.role, "id": child.ident, "pid": child.process.pid})

    def _start(self, role: str, ident: int = 0) -> None:
        child = Child(role, ident, self.config.run_dir / "logs" / f"{role}-{ident}.log")
        self.children[child.name] = child
        self._launch(child)

    def _check_children(self) -> bool:
        """Restart children that died; False once one keeps dying."""
        for child in self.children.values():
            code = child.process.poll()
            if code is None:
                continue
            if code == 2:  # the child refused its arguments: restarting would not help
                self._say(f"{child.name} refused to start, see {child.log_path}")
                return False
            if child.restarts >= RESTART_LIMIT:
                self._say(f"{child.name} died {child.restarts + 1} times (exit {code}); "
                          f"giving up, see {child.log_path}")
                return False
            if child.role == "world" and self.config.episodes is not None and (
                    len(self.outcomes) >= self.config.episodes):
                continue
            child.restarts += 1
            self._say(f"{child.name} (pid {child.process.pid}) exited with {code}; restarting")
            self._launch(child)
        return True

    def _stop_children(self, roles: tuple[str, ...]) -> None:
        chosen = [c for c in self.children.values() if c.role in roles]
        for child in chosen:
            if child.process.poll() is None:
                child.process.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + STOP_GRACE_S
        for child in chosen:
            try:
                child.process.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                self._say(f"{child.name} did not stop in {STOP_GRACE_S:g} s; killing it")
                child.process.kill()
                child.process.wait()

    # -- bus ----------------------------------------------------------------------------------
    def _on_event(self, sample: zenoh.Sample) -> None:
        try:
            self.inbox.put(decode_event(sample.payload.to_bytes()))
        except MessageError as exc:
            self.dropped.add(self.topics.event("*"), str(exc))

    def _on_state(self, sample: zenoh.Sample) -> None:
        try:
            self.inbox.put(decode(WorldState, sample.payload.to_bytes()))
        except MessageError as exc:
            self.dropped.add(self.topics.state, str(exc))

    def _on_presence(self, sample: zenoh.Sample) -> None:
        role, ident = self.topics.role_and_id(str(sample.key_expr))
        name = f"{role}-{ident}"
        with self._live_lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self.live.add(name)
            else:
                self.live.discard(name)

    def _drain(self) -> None:
        while not self.inbox.empty():
            item = self.inbox.get_nowait()
            if isinstance(item, WorldState):
                self._on_world_state(item)
            else:
                self._record_event(item)

    def _on_world_state(self, state: WorldState) -> None:
        if self.first_step is None:
            self.first_step = time.monotonic()
        self.state = state
        self.trajectories.setdefault(state.episode, []).append(state.position)

    def _record_event(self, event) -> None:
        record = event.model_dump(mode="json")
        self.events.append(record)
        if event.type == "uav_outcomes":
            self.outcomes[event.episode] = list(event.outcomes)
            return
        if event.type == "run_finished":
            self.finished = record
            return
        if event.type == "jammer_changed":
            self.jammer = event.jammer
            what = "off" if event.jammer is None else (
                f"({event.jammer.x:g}, {event.jammer.y:g}) {event.jammer.power_w:g} W")
            self._say(f"jammer changed to {what} (episode {event.episode}, step {event.step})")
        elif event.type == "change_detected":
            self._say(f"jammer change detected by the cloud (map v{event.version} right on "
                      f"{event.accuracy:.0%} of recent uploads)")
        elif event.type == "jammer_estimated":
            self._say(f"jammer estimated with map v{event.estimate.map_version}: "
                      f"{describe_estimate(event.estimate)}")
        elif event.type == "weights_refused":
            self._say(f"agent {event.uav} refused {event.weights} weights "
                      f"v{event.version if event.version is not None else '?'} "
                      f"({event.reason}); flying on v{event.flying_on}")
        elif event.type == "sinr_weights_published":
            self._say(f"SINR map v{event.version} published (held-out accuracy "
                      f"{event.accuracy:.1%})")
        else:
            self._say(f"{event.type}: {record}")

    def _poll_status(self, session: zenoh.Session) -> None:
        if time.monotonic() - self._last_status < STATUS_EVERY_S:
            return
        self._last_status = time.monotonic()
        try:
            self.world_status = bus.query(session, self.topics.status("world", 0), ProcessStatus,
                                          timeout=0.5)
        except bus.BusError:
            return
        if self.world_status.details.get("finished") and self.finished is None:
            self.finished = {"type": "run_finished", **self.world_status.details}
        try:
            self.cloud_status = bus.query(session, self.topics.status("cloud", 0),
                                          ProcessStatus, timeout=0.5)
        except bus.BusError:
            pass

    def _statuses(self, session: zenoh.Session) -> list[ProcessStatus]:
        found = []
        for reply in session.get(self.topics.status(), timeout=2.0):
            if reply.ok is not None:
                try:
                    found.append(decode(ProcessStatus, reply.ok.payload.to_bytes()))
                except MessageError as exc:
                    self.dropped.add(self.topics.status(), str(exc))
        return found

    def _uploads_handed_over(self, session: zenoh.Session, statuses: list[ProcessStatus]
                             ) -> list[ProcessStatus]:
        """Statuses once every agent's outbox is empty (the report's measurement counts are
        then final), or after ``FLUSH_WAIT_S``."""
        deadline = time.monotonic() + FLUSH_WAIT_S
        while time.monotonic() < deadline and any(
                s.details.get("measurements_buffered") for s in statuses if s.role == "agent"):
            time.sleep(0.2)
            statuses = self._statuses(session)
        return statuses

    def _maybe_swap(self, session: zenoh.Session) -> None:
        c = self.config
        if (self.swapped or c.swap_at is None or self.first_step is None
                or time.monotonic() - self.first_step < c.swap_at):
            return
        self.swapped = True
        if c.swap_to == "off":
            command = JammerCommand(action="off")
        else:
            jammer = JammerInfo.parse(c.swap_to, self.scenario.jammer.height_m)
            command = JammerCommand(action="set", x=jammer.x, y=jammer.y,
                                    power_w=jammer.power_w, height_m=jammer.height_m)
        try:
            reply = bus.query(session, self.topics.jammer_control, JammerReply, command)
        except bus.BusError as exc:
            self._say(f"jammer swap failed: {exc}")
            return
        self._say(f"jammer swap requested on {self.topics.jammer_control}: "
                  f"{'accepted' if reply.accepted else 'refused: ' + str(reply.reason)}")

    # -- display -----------------------------------------------------------------------------
    def _say(self, text: str) -> None:
        elapsed = 0.0 if self.first_step is None else time.monotonic() - self.first_step
        prefix = "\r\x1b[2K" if self.interactive else ""
        self.stream.write(f"{prefix}[{elapsed:6.1f}s] {text}\n")
        self.stream.flush()

    def _progress(self) -> None:
        now = time.monotonic()
        if now - self._last_draw < (0.25 if self.interactive else 5.0):
            return
        self._last_draw = now
        with self._live_lock:
            live = len(self.live)
        expected = self.config.uavs + 3
        if self.state is None:
            line = f"starting: {live}/{expected} processes live"
        else:
            s = self.state
            uavs = " ".join(
                f"u{i}:{f'{s.sinr_db[i]:+.0f}dB' if status == 'active' else status[:4]}"
                for i, status in enumerate(s.status[:8]))
            rate = self.world_status.details.get("steps_per_second") if self.world_status else 0
            line = (f"ep {s.episode} step {s.step:3d} | {len(self.outcomes)} done | "
                    f"{rate or 0:.0f} steps/s | {mapper_summary(self.cloud_status)} | {uavs} | "
                    f"live {live}/{expected}")
        if self.interactive:
            self.stream.write("\r\x1b[2K" + line[:160])
        else:
            self.stream.write(line + "\n")
        self.stream.flush()

    # -- the run -----------------------------------------------------------------------------
    def run(self) -> dict[str, Any]:
        c = self.config
        # The cloud's memory persists in the run directory: a rerun in the same directory
        # starts with what earlier runs stored.
        self.memory_existed = (c.run_dir / RUN_DIR_FILE).exists()
        (c.run_dir / "logs").mkdir(parents=True, exist_ok=True)
        previous = {sig: signal.signal(sig, lambda *_: self.stop.set())
                    for sig in (signal.SIGINT, signal.SIGTERM)}
        statuses: list[ProcessStatus] = []
        login = self._operator_login()
        try:
            self._start("router")
            with bus.open_session("client", c.endpoint, login=login) as session:
                self._declared = [
                    session.declare_subscriber(self.topics.event("*"), self._on_event),
                    session.declare_subscriber(self.topics.state, self._on_state),
                    session.liveliness().declare_subscriber(self.topics.alive(), self._on_presence,
                                                            history=True),
                ]
                self._start("cloud")
                self._start("world")
                for uav in range(c.uavs):
                    self._start("agent", uav)
                while not self.stop.is_set():
                    self._drain()
                    if self.finished is not None:
                        break
                    if not self._check_children():
                        self.stopped_by = "failure"
                        break
                    self._maybe_swap(session)
                    self._poll_status(session)
                    self._progress()
                    self.stop.wait(0.1)
                else:
                    self.stopped_by = "signal"
                time.sleep(0.2)  # the last events of a run in flight
                self._drain()
                statuses = self._statuses(session)
                if self.stopped_by == "end":
                    statuses = self._uploads_handed_over(session, statuses)
                if self.interactive:
                    self.stream.write("\n")
                self._say("stopping")
                # The world first (no new measurements), then the agents, which hand their
                # outboxes to the cloud as they stop, then the cloud.
                for role in ("world", "agent", "cloud"):
                    self._stop_children((role,))
        finally:
            self._stop_children(("world", "agent", "cloud", "router"))
            for sig, handler in previous.items():
                signal.signal(sig, handler)
        return self._report(statuses)

    def _operator_login(self) -> access.Login | None:
        """Secure: the supervisor logs in as the operator; without a given credentials file,
        every role gets a fresh login, written (mode 0600) in the run directory."""
        if self.credentials_path is None:
            return None
        if self.config.credentials is None:
            access.save(access.generate(self.config.uavs), self.credentials_path)
        self._say(f"secure: logins and access rules enforced by the router; credentials in "
                  f"{self.credentials_path} (for jamnav status/jammer --credentials)")
        return access.login_for(self.credentials_path, access.OPERATOR)

    def _report(self, statuses: list[ProcessStatus]) -> dict[str, Any]:
        c = self.config
        outcomes = [self.outcomes[k] for k in sorted(self.outcomes)]
        labels = [label for row in outcomes for label in row]
        rates = {f"{o.label}_rate": (labels.count(o.label) / len(labels) if labels else None)
                 for o in FINAL_OUTCOMES}
        dropped: Counter = Counter(self.dropped.as_dict())
        for status in statuses:
            dropped.update(status.dropped)
        world = next((s for s in statuses if s.role == "world"), self.world_status)
        details = world.details if world is not None else {}
        restarts = {role: 0 for role in ("router", "world", "cloud", "agent")}
        for child in self.children.values():
            restarts[child.role] += child.restarts
        return {
            "command": c.command,
            "run_dir": str(c.run_dir),
            "endpoint": c.endpoint,
            "scenario": self.scenario.name,
            "clock": c.clock,
            "map": c.map,
            "uavs": c.uavs,
            "seed": c.seed,
            "secure": c.secure,
            "stopped_by": self.stopped_by,
            "processes": self.launched,
            "episodes": len(outcomes),
            "outcomes": outcomes,
            **rates,
            "steps_per_second": (self.finished or details).get("steps_per_second"),
            "missed_deadlines": (self.finished or details).get("missed_deadlines"),
            "events": self.events,
            "restarts": restarts,
            "dropped_messages": dict(dropped),
            "versions": {f"{s.role}-{s.ident}": {"value": s.value_version, "sinr": s.sinr_version}
                         for s in statuses if s.role in ("cloud", "agent")},
            "agents": {s.ident: {k: s.details.get(k) for k in (
                "decisions", "decision_p50_us", "decision_p99_us", "decision_cpu_p99_us")}
                for s in statuses if s.role == "agent"},
            "measurements": {**measurement_counts(statuses),
                             "memory_of_earlier_runs": self.memory_existed},
        }


def measurement_counts(statuses: list[ProcessStatus]) -> dict[str, int | None]:
    """Where the UAVs' measurements went: taken by the agents now running, still in their
    outboxes, dropped from a full outbox, and held by the cloud's memory (which survives a
    restart of the cloud). An agent restarted after a crash starts its counts afresh."""
    agents = [s.details for s in statuses if s.role == "agent"]
    cloud = next((s.details for s in statuses if s.role == "cloud"), None)
    counts: dict[str, int | None] = {
        name: sum(int(a.get(f"measurements_{name}") or 0) for a in agents)
        for name in ("taken", "acknowledged", "buffered", "overflowed", "refused",
                     "duplicates")}
    counts["upload_failures"] = sum(int(a.get("upload_failures") or 0) for a in agents)
    counts["in_memory"] = None if cloud is None else cloud.get("stored")
    return counts


# -- after the run ------------------------------------------------------------------------------
def summary_table(report: dict[str, Any]) -> str:
    rows = [f"jamnav up: {report['episodes']} episodes x {report['uavs']} UAVs, "
            f"{report['clock']}, map {report['map']}, stopped by {report['stopped_by']}"]
    for outcome in FINAL_OUTCOMES:
        rate = report[f"{outcome.label}_rate"]
        rows.append(f"  {outcome.label:<14} {'-' if rate is None else f'{rate:6.1%}':>7}")
    sps = report["steps_per_second"]
    rows.append(f"  steps/s        {'-' if sps is None else f'{sps:7.0f}'}   missed deadlines "
                f"{report['missed_deadlines']}")
    rows.append("  restarts       " + ", ".join(f"{k} {v}" for k, v in report["restarts"].items()))
    dropped = report["dropped_messages"]
    rows.append("  dropped        " + (", ".join(f"{k} {v}" for k, v in dropped.items())
                                       or "none"))
    m = report["measurements"]
    earlier = " (with earlier runs')" if m["memory_of_earlier_runs"] else ""
    rows.append(f"  measurements   {m['taken']} taken, {m['in_memory']} in the cloud's memory"
                f"{earlier}, "
                f"{m['buffered']} still buffered, {m['overflowed']} dropped from full outboxes, "
                f"{m['upload_failures']} uploads retried")
    rows += [f"  {line}" for line in map_history(report["events"])]
    return "\n".join(rows)


def map_history(events: list[dict[str, Any]]) -> list[str]:
    """The jammer's changes and the cloud's answers, one line each; a run of refinements
    (new estimate and map, again and again) shows as its first and last line."""
    lines: list[str] = []
    refinements: list[str] = []

    def close_run() -> None:
        if len(refinements) > 2:
            lines.append(f"{'':<23} ... {len(refinements) - 2} refinements ...")
        if len(refinements) > 1:
            lines.append(refinements[-1])
        refinements.clear()

    for event in events:
        kind = event["type"]
        if kind == "jammer_estimated":
            estimate = JammerEstimate(**event["estimate"])
            line = (f"{'map v' + str(estimate.map_version) + ', jammer at':<23} "
                    f"{describe_estimate(estimate)}")
            if not refinements:
                lines.append(line)
            refinements.append(line)
        elif kind in ("jammer_changed", "change_detected"):
            close_run()
            extra = {k: event[k] for k in ("version", "accuracy", "jammer") if k in event}
            lines.append(f"{kind:<23} {json.dumps(extra)}")
        elif kind == "sinr_weights_published" and not refinements:
            lines.append(f"{kind:<23} {json.dumps({'version': event['version']})}")
    close_run()
    return lines


def save_trajectory_figures(report: dict[str, Any], supervisor: Supervisor) -> list[str]:
    """Trajectories over the coverage map in force: the last episode before the jammer was
    swapped and the last episode of the run (or just the last one without a swap)."""
    import matplotlib.pyplot as plt

    from shared.plots import draw_coverage

    changes = [e for e in report["events"] if e["type"] == "jammer_changed"]
    done = sorted(supervisor.outcomes)
    if not done:
        return []
    panels = []
    if changes:
        swap = changes[0]
        before = [k for k in done if k < swap["episode"]]
        if before:
            panels.append(("before_swap", before[-1], supervisor.initial_jammer))
        jammer = changes[-1]["jammer"]
        panels.append(("after_swap", done[-1],
                       None if jammer is None else JammerInfo.model_validate(jammer)))
    else:
        panels.append(("last_episode", done[-1], supervisor.initial_jammer))
    written = []
    for label, episode, jammer in panels:
        fig, ax = plt.subplots(figsize=(5.6, 5.6))
        draw_coverage(ax, supervisor.scenario, jammer_params(jammer), resolution=201)
        path = [p for p in supervisor.trajectories.get(episode, []) if p]
        if path:
            for uav, outcome in enumerate(supervisor.outcomes[episode]):
                xs = [p[uav][0] for p in path]
                ys = [p[uav][1] for p in path]
                (line,) = ax.plot(xs, ys, "-", lw=1.6, label=f"UAV {uav}: {outcome}")
                ax.plot(xs[0], ys[0], "o", color=line.get_color(), ms=5)
                ax.plot(xs[-1], ys[-1], "*", color=line.get_color(), ms=9)
        ax.set_title(f"episode {episode} ({label.replace('_', ' ')})\n{ax.get_title()}",
                     fontsize=9)
        ax.legend(loc="upper right", fontsize=7, framealpha=0.85)
        fig.tight_layout()
        out = Path(report["run_dir"]) / f"trajectories_{label}.png"
        fig.savefig(out, dpi=110)
        plt.close(fig)
        written.append(str(out))
    return written


def up(config: UpConfig, scenario: Scenario) -> int:
    check_endpoint_free(config.endpoint)
    supervisor = Supervisor(config, scenario)
    report = supervisor.run()
    if config.figures:
        report["figures"] = save_trajectory_figures(report, supervisor)
    path = config.report or config.run_dir / "report.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
    print(summary_table(report))
    print(f"report: {path}" + (f", figures: {', '.join(report['figures'])}"
                               if report.get("figures") else ""))
    if supervisor.credentials_path is not None:
        print(f"credentials: {supervisor.credentials_path}")
    return 1 if report["stopped_by"] == "failure" else 0

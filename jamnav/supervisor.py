"""``jamnav up``: the whole system as separate OS processes on one machine.

Starts a zenoh router (or two linked over mTLS: the world and the cloud on the first, the
agents on the second), the cloud, the world and one agent per UAV with ``subprocess`` (the
child execs at once: no child ever runs on a copy of our open zenoh session, which would hang),
follows them over the bus (liveliness, events, world state), shows live progress on stderr,
restarts a child that dies, and stops everything at the end or on Ctrl-C / SIGTERM, in an
order that stores every measurement taken: the world (no new measurements), the agents once
their outboxes are in the cloud, the cloud, the routers last; each with SIGTERM (they close
their sessions), SIGKILL for stragglers.
Children run in their own process group, so a Ctrl-C in the terminal reaches only the
supervisor, and each child stops by itself if the supervisor disappears. The run directory
receives the children's logs, the report JSON and the figures.
"""

from __future__ import annotations

import glob
import json
import os
import queue
import re
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

import numpy as np
import zenoh

from cloud_service.sinr_memory import RUN_DIR_FILE
from jamnav.console.listen import TOKEN_FILE, WebAddress, new_token
from jamnav.event_lines import describe_event
from shared import access, bus, tls
from shared.events import decode_event
from shared.jammer_messages import JammerCommand, JammerInfo, JammerReply
from shared.outcomes import FINAL_OUTCOMES
from shared.process_status import ProcessStatus, mapper_summary
from shared.scenario import Scenario
from shared.shipped import value_net_name
from shared.threads import one_blas_thread
from shared.topics import Topics
from shared.wire import MessageError, decode
from shared.world_messages import WorldState
from world_sim.process import initial_jammer

ROOT = Path(__file__).resolve().parent.parent
STOP_GRACE_S = 10.0
# A child that dies more than RESTART_LIMIT times in a row, each within STEADY_S of its start,
# would die again: the supervisor gives up. One that ran a while is restarted however often.
RESTART_LIMIT = 5
STEADY_S = 10.0
STATUS_EVERY_S = 2.0
FLUSH_WAIT_S = 5.0
# How long the world waits for every agent's first token (and first action): agents start in
# parallel, so on a machine of few cores their start takes time in proportion to their number.
START_TIMEOUT_S = 60.0
START_PER_AGENT_S = 1.0
OUTBOX_DIR = "outbox"  # in the run directory: one file per UAV, which outlives its agent


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
    swap_every: int | None = None  # a fresh random jammer every K episodes
    cloud_latency: float | None = None  # lockstep, online: the scenario's, unless given
    retrain_samples: int | None = None
    model: Path | None = None  # the value network the cloud serves
    sinr_map: Path | None = None  # the survey map the online map starts from
    figures: bool = True
    command: str = "jamnav up"
    secure: bool = False  # logins and access rules enforced by the router
    credentials: Path | None = None  # secure: this file, else fresh ones in run_dir
    routers: int = 1  # 2: the agents on a router of their own, linked to the first over mTLS
    agent_endpoint: str | None = None  # routers=2: the agents' router
    link_endpoint: str | None = None  # routers=2: TLS, where the first router awaits the second
    durable_outboxes: bool = True  # agents keep their outboxes in run_dir too (else memory)
    record: Path | None = None  # MCAP file of every message (a restarted recorder: FILE.N.mcap)
    web: WebAddress | None = None  # where the console serves its page (None: no console)
    # The socket listening at ``web``, held for the whole run and handed to each console
    # started (None: the console binds ``web`` itself).
    web_listener: socket.socket | None = None


@dataclass
class Child:
    role: str
    ident: int
    log_path: Path
    process: subprocess.Popen | None = None
    restarts: int = 0
    started: float = 0.0  # time.monotonic() of the last launch
    quick_deaths: int = 0  # in a row, each within STEADY_S of its start

    @property
    def name(self) -> str:
        return self.role if self.role in ("world", "cloud") else f"{self.role}-{self.ident}"


# Whose logins each router of a two-router system accepts (``jamnav router --roles``).
ROUTER_ROLES = (f"{access.OPERATOR},{access.WORLD},{access.CLOUD}", "agent-*")
LINK_DIR = "tls"  # in the run directory: the routers' certificates and TLS settings


def next_endpoint(endpoint: str, step: int, protocol: str | None = None) -> str:
    """``endpoint`` ``step`` ports up (with another ``protocol``): where the second router and
    the link between the routers listen unless told."""
    proto, _, address = endpoint.partition("/")
    host, _, port = address.rpartition(":")
    return f"{protocol or proto}/{host}:{int(port) + step}"


def check_endpoint_free(endpoint: str, option: str = "--endpoint") -> None:
    """Refuse to start a router on a port in use (another ``jamnav up``?)."""
    proto, _, address = endpoint.partition("/")
    host, _, port = address.rpartition(":")
    if proto not in ("tcp", "tls") or not port.isdigit():
        return
    with socket.socket(socket.AF_INET6 if ":" in host.strip("[]") else socket.AF_INET) as probe:
        # As a listener binds: connections of a previous run in TIME_WAIT do not count.
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind((host.strip("[]"), int(port)))
        except OSError as exc:
            raise ValueError(f"{endpoint} is in use ({exc.strerror}): is another system "
                             f"running? choose {option}") from None


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
        self.destinations: dict[int, list[tuple[float, float]]] = {}
        self.state: WorldState | None = None
        self.first_step: float | None = None
        self.launched_at = time.monotonic()
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
        self.link_files: dict[str, tls.RouterCertificate] = {}
        self._last_status = 0.0
        self._last_draw = 0.0

    # -- children ---------------------------------------------------------------------------
    def _router_argv(self, ident: int) -> list[str]:
        """With two routers, router 0 serves the supervisor, the world and the cloud and
        awaits router 1 on the TLS link; router 1 serves the agents and links to router 0."""
        c = self.config
        argv = ["--prefix", c.prefix, "--id", str(ident)]
        if c.routers == 1:
            argv += ["--endpoint", c.endpoint]
        else:
            link = ["--listen" if ident == 0 else "--connect", c.link_endpoint]
            argv += ["--endpoint", c.endpoint if ident == 0 else c.agent_endpoint, *link,
                     "--zenoh-config", str(self.link_files[str(ident)].zenoh_config)]
        argv += self._credentials_argv()
        if self.credentials_path is not None and c.routers > 1:
            # The recorder logs in beside the supervisor.
            recorder = f",{access.RECORDER}" if ident == 0 and c.record is not None else ""
            argv += ["--roles", ROUTER_ROLES[ident] + recorder]
        return argv

    def _credentials_argv(self) -> list[str]:
        return [] if self.credentials_path is None else [
            "--credentials", str(self.credentials_path)]

    def _argv(self, child: Child) -> list[str]:
        c, python = self.config, [sys.executable, "-m"]
        if child.role == "router":
            return python + ["jamnav.cli", "router", *self._router_argv(child.ident)]
        if child.role == "recorder":
            return python + ["jamnav.cli", "record", "--endpoint", c.endpoint, "--prefix",
                             c.prefix, "--out", str(recording_path(c.record, child.restarts)),
                             *self._credentials_argv()]
        endpoint = c.agent_endpoint if child.role == "agent" and c.routers > 1 else c.endpoint
        common = ["--endpoint", endpoint, "--prefix", c.prefix, *self._credentials_argv()]
        if c.scenario:
            common += ["--scenario", c.scenario]
        if child.role == "console":
            token = [] if self.credentials_path is None else [
                "--token-file", str(c.run_dir / TOKEN_FILE)]
            inherited = [arg for fd in self._handed_fds(child) for arg in ("--listen-fd", str(fd))]
            return python + ["jamnav.cli", "console", *common, "--web", c.web.text, *token,
                             *inherited]
        jammer = ["--no-jammer"] if self.jammer is None else [
            "--jammer", f"{self.jammer.x!r},{self.jammer.y!r},{self.jammer.power_w!r},"
                        f"{self.jammer.height_m!r}"]
        if child.role == "cloud":
            argv = python + ["cloud_service.process", *common, "--map", c.map,
                             "--run-dir", str(c.run_dir), *jammer]
            if c.retrain_samples is not None:
                argv += ["--retrain-samples", str(c.retrain_samples)]
            if self.cloud_clock:
                argv += ["--clock", "lockstep"]
            if c.cloud_latency is not None:
                argv += ["--cloud-latency", repr(c.cloud_latency)]
            if c.model is not None:
                argv += ["--value-net", str(c.model.resolve())]
            if c.sinr_map is not None:
                argv += ["--sinr-map", str(c.sinr_map.resolve())]
            return argv
        if child.role == "agent":
            outbox = ["--outbox-dir", str(c.run_dir / OUTBOX_DIR)] if c.durable_outboxes else []
            return python + ["uav_agent.process", *common, "--uav", str(child.ident), *outbox]
        # A restarted world carries on after the last finished episode, with the jammer in force.
        done = len(self.outcomes)
        argv = python + ["world_sim.process", *common, "--uavs", str(c.uavs), "--seed",
                         str(c.seed), "--clock", c.clock, "--rate", str(c.rate), "--deadline",
                         str(c.deadline), "--first-episode", str(done), "--start-timeout",
                         str(START_TIMEOUT_S + START_PER_AGENT_S * c.uavs), *jammer]
        if self.cloud_clock:
            argv += ["--cloud-clock"]
        if c.swap_every is not None:
            argv += ["--swap-every", str(c.swap_every)]
        if c.episodes is not None:
            argv += ["--episodes", str(c.episodes - done)]
        if c.duration is not None:
            elapsed = 0.0 if self.first_step is None else time.monotonic() - self.first_step
            argv += ["--duration", str(max(c.duration - elapsed, 0.1))]
        return argv

    @property
    def cloud_clock(self) -> bool:
        """The cloud on the world's clock: lockstep with the online map (``jamnav eval``'s
        maps, steps and outcomes for the same seed)."""
        return self.config.clock == "lockstep" and self.config.map == "online"

    def _handed_fds(self, child: Child) -> tuple[int, ...]:
        """The descriptors ``child`` inherits: a console, the run's listening socket."""
        listener = self.config.web_listener
        return (listener.fileno(),) if child.role == "console" and listener is not None else ()

    def _launch(self, child: Child) -> None:
        env = one_blas_thread(dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1",
                                   PYTHONUNBUFFERED="1"))
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
        with child.log_path.open("ab") as log:
            child.process = subprocess.Popen(
                self._argv(child), stdin=subprocess.DEVNULL, stdout=log, stderr=log, env=env,
                start_new_session=True, pass_fds=self._handed_fds(child))
        child.started = time.monotonic()
        self.launched.append({"role": child.role, "id": child.ident, "pid": child.process.pid})

    def _start(self, role: str, ident: int = 0) -> None:
        child = Child(role, ident, self.config.run_dir / "logs" / f"{role}-{ident}.log")
        self.children[child.name] = child
        self._launch(child)

    def _start_recorder(self) -> None:
        """Start the recorder and wait until its subscription is in (its liveliness token
        says so), so that the file holds the run from its first message. A recorder that
        does not come up is the main loop's to restart or give up on."""
        self._start("recorder")
        process = self.children["recorder-0"].process
        deadline = time.monotonic() + bus.CONNECT_TIMEOUT_MS / 1000
        while process.poll() is None and time.monotonic() < deadline:
            with self._live_lock:
                if f"recorder-{process.pid}" in self.live:
                    return
            time.sleep(0.02)

    def _start_console(self) -> None:
        """The console, and its URL, printed once it listens: on a secure system the URL
        holds the token that the page and the API demand (fresh for each run, kept in the
        run directory). A console that does not come up is the main loop's to restart."""
        c = self.config
        token = None if self.credentials_path is None else new_token(c.run_dir / TOKEN_FILE)
        self._start("console")
        process = self.children["console-0"].process
        deadline = time.monotonic() + bus.CONNECT_TIMEOUT_MS / 1000
        while (process.poll() is None and time.monotonic() < deadline
               and not c.web.accepting()):
            time.sleep(0.05)
        moved = f" (port {c.web.taken_default} is in use)" if c.web.taken_default else ""
        self._say(f"console: {c.web.url(token)}{moved}")

    def _check_children(self) -> bool:
        """Restart children that died; False once one keeps dying."""
        for child in self.children.values():
            code = child.process.poll()
            if code is None:
                continue
            if code == 2:  # the child refused its arguments: restarting would not help
                self._say(f"{child.name} refused to start, see {child.log_path}")
                return False
            quick = time.monotonic() - child.started < STEADY_S
            child.quick_deaths = child.quick_deaths + 1 if quick else 0
            if child.quick_deaths > RESTART_LIMIT:
                self._say(f"{child.name} died {child.quick_deaths} times in a row, each within "
                          f"{STEADY_S:g} s of its start (exit {code}); giving up, see "
                          f"{child.log_path}")
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
        self.destinations.setdefault(state.episode, state.destination)

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
        if (text := describe_event(record)) is not None:
            self._say(text)

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
        recorder = self.children.get("recorder-0")
        own_recorder = None if recorder is None or recorder.process is None else (
            f"recorder-{recorder.process.pid}")
        with self._live_lock:
            # A recorder started by hand against this system is live too, but not the run's.
            live = sum(1 for name in self.live
                       if not name.startswith("recorder-") or name == own_recorder)
        expected = self.config.uavs + 2 + self.config.routers + (self.config.record is not None)
        if self.state is None:
            line = f"starting: {live}/{expected} processes live"
        else:
            s = self.state
            uavs = fleet_line(s)
            rate = self.world_status.details.get("steps_per_second") if self.world_status else 0
            cloud = self.cloud_status
            maps = mapper_summary(cloud) if self.config.map == "online" else (
                f"map {self.config.map}" + (f" v{cloud.sinr_version}" if cloud else ""))
            line = (f"ep {s.episode} step {s.step:3d} | {len(self.outcomes)} done | "
                    f"{rate or 0:.0f} steps/s | {maps} | {uavs} | live {live}/{expected}")
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
        if self.memory_existed:
            self._say(f"the cloud goes on with the memory of earlier runs in {c.run_dir}; "
                      "a new --run-dir starts afresh")
        (c.run_dir / "logs").mkdir(parents=True, exist_ok=True)
        previous = {sig: signal.signal(sig, lambda *_: self.stop.set())
                    for sig in (signal.SIGINT, signal.SIGTERM)}
        statuses: list[ProcessStatus] = []
        login = self._operator_login()
        self._make_link_certificates()
        try:
            for ident in range(c.routers):
                self._start("router", ident)
            with bus.open_session("client", c.endpoint, login=login) as session:
                self._declared = [
                    # Outcomes missed while the router restarts come again (the world
                    # keeps them), once each.
                    bus.recovering_subscriber(session, self.topics.event("*"), self._on_event),
                    session.declare_subscriber(self.topics.state, self._on_state),
                    session.liveliness().declare_subscriber(self.topics.alive(), self._on_presence,
                                                            history=True),
                ]
                if c.record is not None:
                    self._start_recorder()
                self._start("cloud")
                self._start("world")
                for uav in range(c.uavs):
                    self._start("agent", uav)
                if c.web is not None:
                    self._start_console()
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
                if self.interactive:
                    self.stream.write("\n")
                self._say("stopping")
                statuses = self._stop_in_order(session)
        finally:
            for role in ("world", "agent", "cloud", "recorder", "console", "router"):
                self._stop_children((role,))
            for sig, handler in previous.items():
                signal.signal(sig, handler)
        return self._report(statuses)

    def _stop_in_order(self, session: zenoh.Session) -> list[ProcessStatus]:
        """Stop the world (no new measurements), wait until the agents have handed their
        outboxes to the cloud, then stop them and the cloud: every measurement taken is
        stored, and the statuses taken in between hold the run's final counts. The recorder
        goes last, with everything the others put."""
        world = [s for s in self._statuses(session) if s.role == "world"]
        self._stop_children(("world",))
        statuses = self._uploads_handed_over(session, self._statuses(session))
        self._stop_children(("agent",))
        self._stop_children(("cloud",))
        self._stop_children(("recorder",))
        return world + statuses

    def _operator_login(self) -> access.Login | None:
        """Secure: the supervisor logs in as the operator; without a given credentials file,
        every role gets a fresh login, written (mode 0600) in the run directory."""
        if self.credentials_path is None:
            return None
        if self.config.credentials is None:
            access.save(access.generate(self.config.uavs, linked=self.config.routers > 1),
                        self.credentials_path)
        self._say(f"secure: logins and access rules enforced by the routers; credentials in "
                  f"{self.credentials_path} (for jamnav status/jammer --credentials)")
        return access.login_for(self.credentials_path, access.OPERATOR)

    def _make_link_certificates(self) -> None:
        """Two routers: a fresh authority and a certificate for each, valid for the link's
        host, with the routers' TLS settings, in the run directory."""
        c = self.config
        if c.routers == 1:
            return
        host = c.link_endpoint.partition("/")[2].rpartition(":")[0].strip("[]")
        directory = c.run_dir / LINK_DIR
        self.link_files = tls.make_router_certificates(
            directory, ["0", "1"], tuple(dict.fromkeys([*tls.LOOPBACK_NAMES, host])))
        self._say(f"two routers: world and cloud on {c.endpoint}, agents on "
                  f"{c.agent_endpoint}, linked over mTLS at {c.link_endpoint} (certificates "
                  f"in {directory})")

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
        restarts = dict.fromkeys(("router", "world", "cloud", "agent"), 0)
        for child in self.children.values():
            restarts[child.role] = restarts.get(child.role, 0) + child.restarts
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
            "routers": c.routers,
            "stopped_by": self.stopped_by,
            "processes": self.launched,
            "model": value_net_name(c.model),
            "episodes": len(outcomes),
            "outcomes": outcomes,
            **rates,
            "swap": swap_rates(self.events, dict(zip(sorted(self.outcomes), outcomes,
                                                     strict=True))),
            "first_step_after_s": None if self.first_step is None
            else self.first_step - self.launched_at,
            "steps_per_second": (self.finished or details).get("steps_per_second"),
            "missed_deadlines": (self.finished or details).get("missed_deadlines"),
            # UAV-steps flown on at the last velocity while their agent was dead or restarting.
            "unattended_steps": details.get("unattended_steps"),
            "events": self.events,
            "restarts": restarts,
            # Which processes, as the live output named them when they died.
            "restarted": {child.name: child.restarts for child in self.children.values()
                          if child.restarts},
            "dropped_messages": dict(dropped),
            "versions": {f"{s.role}-{s.ident}": {"value": s.value_version, "sinr": s.sinr_version}
                         for s in statuses if s.role in ("cloud", "agent")},
            "agents": {s.ident: {k: s.details.get(k) for k in (
                "decisions", "decision_p50_us", "decision_p99_us", "decision_cpu_p99_us")}
                for s in statuses if s.role == "agent"},
            "measurements": {**measurement_counts(statuses),
                             "memory_of_earlier_runs": self.memory_existed},
            "cloud_latency": self._cloud_latency(),
        }

    def _cloud_latency(self) -> dict[str, Any] | None:
        """What the cloud's work cost in flight: on the lockstep clock the latency the maps
        flew after (the scenario's, or --cloud-latency); in real time each map's delay after
        the detection of its change, in wall seconds and in seconds of flight at the run's
        pace."""
        c = self.config
        if c.map != "online":
            return None
        if self.cloud_clock:
            return {"clock": "lockstep", "latency_s": self.scenario.online_map.cloud_latency_s
                    if c.cloud_latency is None else c.cloud_latency}
        return {"clock": "wall", "maps": map_delays(
            self.events, c.rate * self.scenario.timing.step_s)}


def recording_path(path: Path, restarts: int) -> Path:
    """Where the recorder writes: ``path``, and after its n-th restart ``<stem>.<n><suffix>``
    (the earlier file stays as it was closed)."""
    return path if restarts == 0 else path.with_name(f"{path.stem}.{restarts}{path.suffix}")


def restarted_recordings(path: Path) -> list[Path]:
    """The files ``recording_path`` names after restarts that exist now (an earlier run's)."""
    restarted = re.compile(rf"{re.escape(path.stem)}\.[1-9][0-9]*{re.escape(path.suffix)}")
    return sorted(earlier for earlier in path.parent.glob(f"{glob.escape(path.stem)}.*")
                  if restarted.fullmatch(earlier.name))


def measurement_counts(statuses: list[ProcessStatus]) -> dict[str, int | None]:
    """Where the UAVs' measurements went: taken by the agents, still in their outboxes,
    dropped from a full outbox, and held by the cloud's memory (which survives a restart of
    the cloud). An agent's outbox file keeps its counts, so a restarted agent carries them on,
    and a rerun in the same run directory counts what earlier runs took, as the memory
    holds what they stored."""
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
def swap_rates(events: list[dict[str, Any]], outcomes: dict[int, list[str]]
               ) -> dict[str, Any] | None:
    """Success before the jammer first changed and from the episode it changed in on (its
    UAVs lived through the change); None without a change."""
    change = next((e for e in events if e["type"] == "jammer_changed"), None)
    if change is None:
        return None

    def success(episodes: list[int]) -> dict[str, Any]:
        labels = [label for k in episodes for label in outcomes[k]]
        return {"episodes": len(episodes),
                "success_rate": labels.count("success") / len(labels) if labels else None}

    return {"episode": change["episode"],
            "before": success([k for k in outcomes if k < change["episode"]]),
            "after": success([k for k in outcomes if k >= change["episode"]])}


def map_delays(events: list[dict[str, Any]], flight_per_wall_s: float) -> list[dict[str, Any]]:
    """Each map published after a detected change: how long after the detection, in wall
    seconds and in seconds of flight."""
    delays, detected = [], None
    for event in events:
        if event["type"] == "change_detected":
            detected = event["t"]
        elif event["type"] == "sinr_weights_published" and detected is not None:
            wall = event["t"] - detected
            delays.append({"version": event["version"], "after_detection_s": round(wall, 3),
                           "flight_s": round(wall * flight_per_wall_s, 3)})
    return delays


def latency_line(latency: dict[str, Any]) -> str | None:
    if latency["clock"] == "lockstep":
        return f"maps fly {latency['latency_s']:g} s of flight after their uploads (lockstep)"
    if not latency["maps"]:
        return None
    first = latency["maps"][0]
    return (f"first map {first['after_detection_s']:.1f} s after the detection (wall), "
            f"{first['flight_s']:.0f} s of flight; {len(latency['maps'])} maps in all")


def fleet_line(state: WorldState, shown: int = 8) -> str:
    """The UAVs for the progress line: each of a small fleet, else counts by status and the
    weakest link among those flying."""
    if len(state.status) <= shown:
        return " ".join(
            f"u{i}:{f'{state.sinr_db[i]:+.0f}dB' if status == 'active' else status[:4]}"
            for i, status in enumerate(state.status))
    counts = Counter(state.status)
    flying = [db for db, status in zip(state.sinr_db, state.status, strict=True)
              if status == "active"]
    weakest = f" (weakest {min(flying):+.0f}dB)" if flying else ""
    return f"{len(state.status)} UAVs: " + ", ".join(
        f"{n} {label[:4]}" + (weakest if label == "active" else "")
        for label, n in sorted(counts.items()))


def agents_line(agents: dict[str, dict[str, Any]]) -> str:
    """The agents at the end, for people: how many, their decisions, the slowest of them
    (the report has every one)."""
    p99 = {ident: a.get("decision_p99_us") for ident, a in agents.items()}
    p99 = {ident: value for ident, value in p99.items() if value is not None}
    decisions = sum(int(a.get("decisions") or 0) for a in agents.values())
    text = f"{len(agents)} reported, {decisions} decisions"
    if p99:
        worst = max(p99, key=p99.get)
        text += (f", decision p99 median {float(np.median(list(p99.values()))):.0f} us, "
                 f"worst {p99[worst]:.0f} us (agent {worst})")
    return text


def _percent(rate: float | None) -> str:
    return "-" if rate is None else f"{rate:.1%}"


def summary_table(report: dict[str, Any]) -> str:
    """The run for people: rounded figures, a word where a number is missing."""
    rows = [f"jamnav up: {report['episodes']} episodes x {report['uavs']} UAVs, "
            f"{report['clock']}, map {report['map']}, value network {report['model']}, "
            f"stopped by {report['stopped_by']}"]
    if report["episodes"] == 0:
        rows.append("  no episode finished")
    else:
        rows.append("  " + ", ".join(f"{o.label} {_percent(report[f'{o.label}_rate'])}"
                                     for o in FINAL_OUTCOMES))
    if (swap := report.get("swap")) is not None:
        rows.append(f"  success        {_percent(swap['before']['success_rate'])} before the "
                    f"jammer changed ({swap['before']['episodes']} episodes), "
                    f"{_percent(swap['after']['success_rate'])} from episode {swap['episode']} "
                    f"on ({swap['after']['episodes']} episodes)")
    if (sps := report["steps_per_second"]) is not None:
        missed = report["missed_deadlines"]
        unattended = report.get("unattended_steps")
        rows.append(f"  pace           {sps:.0f} steps/s"
                    + ("" if missed is None else f", {missed} missed deadlines")
                    + (f", {unattended} UAV-steps without a live agent" if unattended else ""))
    if agents := report.get("agents"):
        rows.append(f"  agents         {agents_line(agents)}")
    restarted = report.get("restarted", {})
    rows.append("  restarts       " + (", ".join(
        f"{name} {'once' if times == 1 else f'{times} times'}"
        for name, times in restarted.items()) or "none"))
    dropped = report["dropped_messages"]
    rows.append("  dropped        " + (", ".join(f"{k} {v}" for k, v in dropped.items())
                                       or "none"))
    rows.append(f"  measurements   {measurement_line(report['measurements'])}")
    if (latency := report.get("cloud_latency")) and (line := latency_line(latency)):
        rows.append(f"  cloud latency  {line}")
    rows += [f"  {line}" for line in map_history(report["events"])]
    return "\n".join(rows)


def measurement_line(m: dict[str, Any]) -> str:
    stored = ("the cloud's memory was not reached" if m["in_memory"] is None
              else f"{m['in_memory']} in the cloud's memory"
              + (" (with earlier runs')" if m["memory_of_earlier_runs"] else ""))
    extra = [f"{m[key]} {what}" for key, what in (
        ("buffered", "still buffered"), ("overflowed", "dropped from full outboxes"),
        ("upload_failures", "uploads retried")) if m.get(key)]
    return ", ".join([f"{m['taken']} taken", stored, *extra])


def map_history(events: list[dict[str, Any]]) -> list[str]:
    """The jammer's changes and the cloud's answers, one line each; a run of refinements (new
    estimate and map, again and again) or of provisional maps shows as its first and last
    line."""
    lines: list[str] = []
    run: list[str] = []
    run_kind = ""

    def close_run() -> None:
        if len(run) > 2:
            between = len(run) - 2
            lines.append(f"  ... {between} {run_kind}{'s' if between > 1 else ''} ...")
        if len(run) > 1:
            lines.append(run[-1])
        run.clear()

    for event in events:
        kind = event["type"]
        provisional = kind == "sinr_weights_published" and event.get("provisional", False)
        if kind == "jammer_estimated" or provisional:
            what = "provisional map" if provisional else "refinement"
            if what != run_kind:
                close_run()
                run_kind = what
            line = describe_event(event)
            if not run:
                lines.append(line)
            run.append(line)
        elif kind in ("jammer_changed", "change_detected"):
            close_run()
            lines.append(describe_event(event))
        elif kind == "sinr_weights_published" and not (run and run_kind == "refinement"):
            close_run()
            lines.append(describe_event(event))
    close_run()
    return lines


def save_trajectory_figures(report: dict[str, Any], supervisor: Supervisor) -> list[str]:
    """Trajectories over the coverage map in force: the last episode before the jammer was
    swapped and the last episode of the run (or just the last one without a swap)."""
    from shared.plots import save_trajectory_figure

    changes = [e for e in report["events"] if e["type"] == "jammer_changed"]
    done = [k for k in sorted(supervisor.outcomes)
            if any(supervisor.trajectories.get(k, [])) and supervisor.destinations.get(k)]
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
        positions = np.array([p for p in supervisor.trajectories[episode] if p], dtype=float)
        out = Path(report["run_dir"]) / f"trajectories_{label}.png"
        save_trajectory_figure(supervisor.scenario, [(
            f"episode {episode} ({label.replace('_', ' ')})", JammerInfo.params(jammer), positions,
            np.array(supervisor.destinations[episode], dtype=float),
            supervisor.outcomes[episode])], out, dpi=110)
        written.append(str(out))
    return written


def up(config: UpConfig, scenario: Scenario) -> int:
    try:
        check_endpoint_free(config.endpoint)
        if config.routers > 1:
            check_endpoint_free(config.agent_endpoint, "--agent-endpoint")
            check_endpoint_free(config.link_endpoint, "--link-endpoint")
        supervisor = Supervisor(config, scenario)
        report = supervisor.run()
    finally:
        if config.web_listener is not None:
            config.web_listener.close()  # the run's consoles have ended with it
    if config.figures:
        report["figures"] = save_trajectory_figures(report, supervisor)
    path = config.report or config.run_dir / "report.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
    print(summary_table(report))
    print(f"report: {path}" + (f", figures: {', '.join(report['figures'])}"
                               if report.get("figures") else ""))
    if config.record is not None:
        print(f"recording: {config.record}")
    if supervisor.credentials_path is not None:
        print(f"credentials: {supervisor.credentials_path}")
    return 1 if report["stopped_by"] == "failure" else 0

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
receives the children's logs, and after the run the report and the figures of
``jamnav.run_report``.
"""

from __future__ import annotations

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
from jamnav.console.listen import TOKEN_FILE, WebAddress, new_token
from jamnav.event_lines import describe_event
from jamnav.recording import recording_path
from jamnav.routers import (
    LINK_DIR,
    check_endpoint_free,
    credentials_argv,
    make_link_certificates,
    router_argv,
)
from jamnav.run_report import build_report, publish_report
from shared import access, bus, tls
from shared.events import decode_event
from shared.jammer_messages import (
    JammerCommand,
    JammerInfo,
    JammerReply,
    initial_jammers,
    jammer_arguments,
)
from shared.process_status import ProcessStatus, mapper_summary
from shared.scenario import Scenario
from shared.threads import one_blas_thread
from shared.topics import Topics
from shared.wire import MessageError, decode
from shared.world_messages import WorldState

ROOT = Path(__file__).resolve().parent.parent
STOP_GRACE_S = 10.0
# The recorder writes the file only as it closes it (its summary, and the chunks it still
# holds), from a thread that yields to the system it records (RECORDER_NICENESS): on a
# machine busy with other work it may need longer than STOP_GRACE_S, and killed, it leaves
# an empty file (one did so under the whole test suite).
RECORDER_STOP_GRACE_S = 60.0
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


class Supervisor:
    """Runs the processes of a ``jamnav up`` system and follows them over the bus until the run
    ends; a child that dies is restarted by ``_check_children``, which gives up on one that
    keeps dying at once (``RESTART_LIMIT``, ``STEADY_S``). ``run`` returns the run's report."""

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
        self.initial_jammers = initial_jammers(scenario, config.jammer, None, config.no_jammer)
        self.jammers = self.initial_jammers
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
    def _argv(self, child: Child) -> list[str]:
        c, python = self.config, [sys.executable, "-m"]
        if child.role == "router":
            return python + ["jamnav.cli", "router", *router_argv(
                c, child.ident, self.credentials_path, self.link_files)]
        if child.role == "recorder":
            return python + ["jamnav.cli", "record", "--endpoint", c.endpoint, "--prefix",
                             c.prefix, "--out", str(recording_path(c.record, child.restarts)),
                             *credentials_argv(self.credentials_path)]
        endpoint = c.agent_endpoint if child.role == "agent" and c.routers > 1 else c.endpoint
        common = ["--endpoint", endpoint, "--prefix", c.prefix,
                  *credentials_argv(self.credentials_path)]
        if c.scenario:
            common += ["--scenario", c.scenario]
        if child.role == "console":
            token = [] if self.credentials_path is None else [
                "--token-file", str(c.run_dir / TOKEN_FILE)]
            inherited = [arg for fd in self._handed_fds(child) for arg in ("--listen-fd", str(fd))]
            return python + ["jamnav.cli", "console", *common, "--web", c.web.text, *token,
                             *inherited]
        jammer = jammer_arguments(self.jammers)
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
        # A restarted world carries on after the last finished episode, with the jammers in
        # force.
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

    def _stop_children(self, roles: tuple[str, ...], grace_s: float = STOP_GRACE_S) -> None:
        chosen = [c for c in self.children.values() if c.role in roles]
        for child in chosen:
            if child.process.poll() is None:
                child.process.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + grace_s
        for child in chosen:
            try:
                child.process.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                self._say(f"{child.name} did not stop in {grace_s:g} s; killing it")
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
            self.jammers = tuple(event.jammers)
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
        statuses: list[ProcessStatus] = []
        login = self._operator_login()
        self._make_link_certificates()
        previous = {sig: signal.signal(sig, lambda *_: self.stop.set())
                    for sig in (signal.SIGINT, signal.SIGTERM)}
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
        return build_report(self, statuses)

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
        self._stop_children(("recorder",), RECORDER_STOP_GRACE_S)
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
        c = self.config
        if c.routers == 1:
            return
        self.link_files = make_link_certificates(c)
        self._say(f"two routers: world and cloud on {c.endpoint}, agents on "
                  f"{c.agent_endpoint}, linked over mTLS at {c.link_endpoint} (certificates "
                  f"in {c.run_dir / LINK_DIR})")


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
    publish_report(report, supervisor)
    return 1 if report["stopped_by"] == "failure" else 0

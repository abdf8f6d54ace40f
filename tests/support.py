"""Helpers of the tests that run the system on the bus."""

from __future__ import annotations

import logging
import socket
import subprocess
import sys
import threading
import time
import traceback
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cloud_service.change_handling import RetrainConfig
from cloud_service.process import CloudService
from shared import bus
from shared.cloud_messages import MeasurementUpload, encode_upload
from shared.events import decode_event
from shared.jammer_messages import JammerCommand, JammerInfo, JammerReply
from shared.measurements import FEATURES_DTYPE, Measurement
from shared.process_status import ProcessStatus
from shared.topics import Topics
from shared.wire import MessageError, decode
from uav_agent.process import AgentService
from world_sim.process import WorldConfig, WorldService


def free_endpoint() -> str:
    """A loopback endpoint on a port nobody listens on now."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{probe.getsockname()[1]}"


def gone(pid: int) -> bool:
    """The process has exited (a zombie left for its parent to reap counts as exited)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0]
    except FileNotFoundError:
        return True
    return state == "Z"


def wait_until(condition, timeout: float, what: str = "a condition", every: float = 0.1):
    """The first truthy value of ``condition()``; AssertionError after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
        time.sleep(every)
    raise AssertionError(f"timed out waiting for {what}")


@dataclass
class System:
    topics: Topics
    events: list  # every event seen, in arrival order
    world: WorldService
    cloud: CloudService
    agents: list[AgentService]
    sessions: list = field(default_factory=list)
    threads: list = field(default_factory=list)  # world, cloud, one per agent

    def wait_for(self, kind: str, timeout: float, after: int = 0):
        """The first ``kind`` event from index ``after`` of the event list on."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            for event in self.events[after:]:
                if event.type == kind:
                    return event
            time.sleep(0.05)
        raise AssertionError(f"no {kind} event within {timeout} s")

    def of_type(self, kind: str) -> list:
        return [event for event in self.events if event.type == kind]

    def jammer(self, command: JammerCommand | bytes) -> JammerReply:
        """Ask the world; raw bytes show what it makes of a payload no model would build."""
        if isinstance(command, JammerCommand):
            return bus.query(self.sessions[0], self.topics.jammer_control, JammerReply, command)
        replies = self.sessions[0].get(self.topics.jammer_control, payload=command, timeout=2)
        return decode(JammerReply, next(iter(replies)).ok.payload.to_bytes())


@contextmanager
def running(scenario, tmp_path, *, mode: str, uavs: int, jammer: JammerInfo | None,
            episodes: int | None, seed: int = 0, retrain: RetrainConfig | None = None
            ) -> Iterator[System]:
    endpoint, topics = free_endpoint(), Topics()
    log = logging.getLogger("test-bus")
    stop = threading.Event()
    router = bus.open_session("router", endpoint)
    sessions, threads = [], []
    try:
        def client():
            sessions.append(bus.open_session("client", endpoint))
            return sessions[-1]

        monitor = client()
        events: list = []

        def on_event(sample) -> None:
            try:
                events.append(decode_event(sample.payload.to_bytes()))
            except MessageError:  # the fuzz test sends junk here too
                pass

        monitor.declare_subscriber(topics.event("*"), on_event)
        jammers = () if jammer is None else (jammer,)
        cloud = CloudService(client(), topics, scenario, mode, tmp_path, log, jammers=jammers,
                             retrain=retrain)
        world = WorldService(client(), topics, scenario,
                             WorldConfig(uavs=uavs, seed=seed, episodes=episodes), jammers, log)
        agents = [AgentService(client(), topics, scenario, uav, log) for uav in range(uavs)]

        def fly(agent: AgentService) -> None:
            if agent.start(stop):
                agent.run(stop)

        threads = [threading.Thread(target=cloud.run, args=(stop,), name="cloud"),
                   threading.Thread(target=world.run, args=(stop,), name="world")]
        threads += [threading.Thread(target=fly, args=(agent,), name=f"agent-{agent.uav}")
                    for agent in agents]
        for thread in threads:
            thread.start()
        yield System(topics, events, world, cloud, agents, sessions, threads)
    finally:
        stop.set()
        for thread in threads:
            thread.join(30)
        for session in sessions:
            session.close()
        router.close()
    stuck = [thread for thread in threads if thread.is_alive()]
    assert not stuck, "\n".join(
        f"{thread.name} still running, at:\n" + "".join(traceback.format_stack(
            sys._current_frames()[thread.ident])) for thread in stuck)


def statuses(session, topics: Topics, timeout: float = 5.0) -> dict[str, ProcessStatus]:
    """Every live process's status reply, by name: ``world-0``, ``cloud-0``, ``agent-1``..."""
    found = {}
    for reply in session.get(topics.status(), timeout=timeout):
        if reply.ok is not None:
            status = decode(ProcessStatus, reply.ok.payload.to_bytes())
            found[f"{status.role}-{status.ident}"] = status
    return found


class Drained:
    """What a process started with stdout and stderr pipes writes, read as it comes: a
    process that writes more than a pipe holds would otherwise stall until someone reads."""

    def __init__(self, process: subprocess.Popen):
        self.process = process
        self._parts: dict[str, list[str]] = {"out": [], "err": []}
        self._readers = [threading.Thread(target=self._read, args=(pipe, self._parts[name]),
                                          daemon=True)
                         for name, pipe in (("out", process.stdout), ("err", process.stderr))]
        for reader in self._readers:
            reader.start()

    @staticmethod
    def _read(pipe, parts: list[str]) -> None:
        for line in pipe:
            parts.append(line)

    def wait(self, timeout: float) -> tuple[str, str]:
        """Wait for the process to exit; what it wrote to stdout and to stderr."""
        self.process.wait(timeout)
        for reader in self._readers:
            reader.join(timeout)
        return "".join(self._parts["out"]), "".join(self._parts["err"])


def upload_of(uav: int, measurements: list[Measurement],
              round_number: int | None = None) -> MeasurementUpload:
    """The upload an agent of UAV ``uav`` sends of ``measurements``, as the cloud decodes it."""
    records = [(m.id, m.source, m.step, m.time,
                np.asarray(m.features, dtype=FEATURES_DTYPE).tobytes(), m.level, m.sinr_db)
               for m in measurements]
    return decode(MeasurementUpload, encode_upload(uav, f"uav-{uav}", records, round_number))

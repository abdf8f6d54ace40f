"""One UAV's agent: decides its own moves with the shared lookahead policy.

At start it fetches the value network and the current SINR map from the cloud (queries), then
follows new versions (subscriptions), checking each one's digest and shape and keeping the
last good one otherwise. For every observation the world sends it, it publishes an action and
records its SINR measurement; measurements go to the cloud in small batches.

On the lockstep clock with the online map (``shared.world_messages``, MeasurementRound) it
uploads each round's reports at once and decides on the map version the world names.

It knows what the paper's UAV knows: its own state and missions, its own SINR measurements, the
other UAVs' positions and velocities, and the maps the cloud sends. Nothing else reaches it
(no jammer, no other UAV's destination), and it imports only ``shared``.
"""

from __future__ import annotations

import argparse
import itertools
import logging
import os
import queue
import secrets
import sys
import threading
import time
from collections import deque
from pathlib import Path

import numpy as np
import zenoh

from planning.chosen import lookahead_policy, require_planner
from planning.maps import LevelRaster, RasterMap, sinr_network_raster
from planning.measuring import SpotFilter, scenario_features
from planning.networks import WeightsError, from_bytes
from planning.reference import LookaheadPolicy
from shared import access, bus
from shared.cloud_messages import MAX_UPLOAD, SinrMap, ValueWeights
from shared.events import WeightsRefused
from shared.measurements import FEATURES_DTYPE, MeasurementSpec
from shared.process_status import ProcessStatus
from shared.scenario import MAX_UAVS, Scenario, load_scenario
from shared.topics import ArgumentParser, Topics, add_bus_arguments, endpoint_from
from shared.wire import encode
from shared.world_messages import Action, AgentObservation, JoinReply, MeasurementRound
from uav_agent.uploads import (
    DEFAULT_BATCH,
    DEFAULT_CAPACITY,
    DEFAULT_MAX_AGE_S,
    Uploader,
    open_outbox,
)

ROLE = "agent"
TIMINGS_KEPT = 4096
# Route fields an agent keeps per map: its current destination's and its next one's, and room
# for the destinations of an episode the world flies again after a restart. Kept for every
# destination, they would pile up for as long as one map is flown (BENCHMARKS.md, "Fleets of
# agent processes").
ROUTE_FIELDS_KEPT = 4
MAP_WAIT_S = 30.0  # how long a decision waits for the map version the world names
MAP_QUERY_S = 2.0  # how long it waits for the cloud's answer about a version not heard of
# A round's receipt comes once the cloud has taken the whole round, a refit included, which
# runs without a wall-clock budget on the lockstep clock.
ROUND_RECEIPT_S = 60.0


class Models:
    """The value network and SINR map in use, and the checks a new version must pass."""

    def __init__(self, scenario: Scenario, log: logging.Logger):
        self.scenario = scenario
        self.log = log
        self.policy: LookaheadPolicy | None = None
        self.radio_map: RasterMap | None = None
        self.value_version: int | None = None
        self.sinr_version: int | None = None
        # Built maps by version. On the lockstep clock the world names the version in service
        # (``pinned``), which newer ones not due yet may have followed: those are kept until
        # named. Otherwise the newest flies, and only it is kept.
        self.maps: dict[int, RasterMap] = {}
        self.pinned: int | None = None
        self.destination: tuple[float, float] | None = None  # where the UAV is flying now

    @property
    def ready(self) -> bool:
        return self.policy is not None and self.radio_map is not None

    def accept(self, update: ValueWeights | SinrMap) -> None:
        """Swap in ``update`` if it is newer and sound; raise WeightsError otherwise (the
        caller keeps flying with what it has)."""
        self.commit(update, self.prepare(update))

    def prepare(self, update: ValueWeights | SinrMap) -> LookaheadPolicy | RasterMap | None:
        """What ``update`` is flown with, built (None if it is not newer); WeightsError if it
        cannot be used. The digest was checked when the message was decoded; here the tensors'
        names, shapes and dtypes are. Any thread may prepare: a map's raster takes tens of
        milliseconds, which must not hold up a decision."""
        if not self._newer(update):
            return None
        if isinstance(update, ValueWeights):
            return lookahead_policy(self.scenario, from_bytes(update.data,
                                                              expected={"kind": "value"}))
        raster = self._raster(update)
        raster.route_fields_kept = ROUTE_FIELDS_KEPT
        radio_map = RasterMap(self.scenario, [raster], np.zeros(1, dtype=np.int64))
        self._route_ahead(radio_map)
        return radio_map

    def _route_ahead(self, radio_map: RasterMap) -> None:
        """Build the route field to where the UAV flies now on a new map, with its raster:
        the first decision on the map would build it otherwise."""
        destination, policy = self.destination, self.policy
        if destination is not None and policy is not None and policy.options.route_distance:
            radio_map.prepare_route(np.array(destination, dtype=np.float64))

    def commit(self, update: ValueWeights | SinrMap,
               built: LookaheadPolicy | RasterMap | None) -> None:
        """Fly with what ``prepare`` built, unless a newer version came first (the thread
        that decides calls this)."""
        if built is None or not self._newer(update):
            return
        if isinstance(update, ValueWeights):
            self.policy, self.value_version = built, update.version
        else:
            self.maps[update.version] = built
            if self.pinned is None:
                self.radio_map, self.sinr_version = built, update.version
            self._forget_before(self.sinr_version)
        self.log.info("%s %s version %d", "holding" if self.pinned is not None else "using",
                      type(update).__name__, update.version)

    def pin(self) -> None:
        """The lockstep clock has begun: from now on the world names the version to fly, and
        it flies this one until then."""
        if self.pinned is None:
            self.pinned = self.sinr_version

    def fly_version(self, version: int) -> bool:
        """Fly SINR map ``version``, the one the lockstep clock puts in service, from now on;
        False while it may still come. One that never will (older than every version held:
        an agent that started after it) is stood in for by the oldest held."""
        held = sorted(self.maps)
        if version not in self.maps and (not held or version > held[-1]):
            return False
        version = version if version in self.maps else next(v for v in held if v > version)
        self.radio_map, self.sinr_version, self.pinned = self.maps[version], version, version
        self._forget_before(version)
        return True

    def _forget_before(self, version: int) -> None:
        for older in [kept for kept in self.maps if kept < version]:
            del self.maps[older]

    def _newer(self, update: ValueWeights | SinrMap) -> bool:
        current = self.value_version if isinstance(update, ValueWeights) else self.sinr_version
        return current is None or update.version > current

    def _raster(self, update: SinrMap) -> LevelRaster:
        scenario = self.scenario
        level_count = scenario.channel.level_count
        if update.grid is None:
            spec = MeasurementSpec.of(scenario)
            network = from_bytes(update.data, expected={
                "kind": "sinr_map", "input_size": spec.feature_size, "levels": level_count})

            return sinr_network_raster(network, scenario)
        grid, area = update.grid, scenario.area
        if (grid.x0 > area.x_min or grid.y0 > area.y_min
                or grid.x0 + grid.spacing * (grid.cols - 1) < area.x_max
                or grid.y0 + grid.spacing * (grid.rows - 1) < area.y_max):
            raise WeightsError("raster does not cover the area")
        levels = update.levels()
        if levels.min() < 0 or levels.max() >= level_count:
            raise WeightsError(f"raster holds levels outside 0..{level_count - 1}")
        return LevelRaster(levels, grid.x0, grid.y0, grid.spacing)


class AgentService:
    """One UAV's agent process: decide an action for each observation the world sends, with
    the networks the cloud serves, and upload its measurements to the cloud (kept in an
    outbox until stored)."""

    def __init__(self, session, topics: Topics, scenario: Scenario, uav: int,
                 log: logging.Logger, upload_every: int = DEFAULT_BATCH,
                 upload_after: float = DEFAULT_MAX_AGE_S,
                 outbox: int = DEFAULT_CAPACITY, outbox_dir: Path | None = None):
        self.session, self.topics, self.scenario, self.uav, self.log = (
            session, topics, scenario, uav, log)
        self.models = Models(scenario, log)
        self.dropped = bus.Dropped(log)
        self.observations: queue.SimpleQueue = queue.SimpleQueue()
        # New weights as they arrive (or the reasons they could not be read), and the same
        # once the preparing thread has built what they are flown with.
        self.updates: queue.SimpleQueue = queue.SimpleQueue()
        self.prepared: queue.SimpleQueue = queue.SimpleQueue()
        # State in -> action out: wall time from arrival (it includes waiting for a core), the
        # part of it before the deciding thread took the state up, and the CPU time that
        # thread spent on it.
        self.timings_us: deque[float] = deque(maxlen=TIMINGS_KEPT)
        self.waits_us: deque[float] = deque(maxlen=TIMINGS_KEPT)
        self.cpu_us: deque[float] = deque(maxlen=TIMINGS_KEPT)
        self.decisions = 0
        # The map and the next destination whose route field was last built between decisions.
        self.ahead: tuple[RasterMap, tuple[float, float]] | None = None
        self.episode: int | None = None
        self.step: int | None = None
        self.upload_every = upload_every
        self.outbox = open_outbox(outbox, outbox_dir, uav, log)
        self.source = f"uav-{uav}"
        self.uploader = Uploader(session, topics.measurements(uav), uav, self.source,
                                 self.outbox, log, upload_every, upload_after)
        self.spots = SpotFilter(scenario, 1)
        self.spots_row = np.zeros(1, dtype=np.int64)  # this UAV, the filter's only one
        # Measurement ids: this process's nonce and a count. Not (episode, step): a restarted
        # world flies its interrupted episode again, and those are new measurements.
        self.nonce = secrets.token_hex(4)
        self.id_prefix = f"{uav}-{self.nonce}-"
        self.measured = itertools.count()
        self.action_pub = bus.reliable_publisher(session, topics.action(uav), express=True)
        self._declared = [
            bus.subscribe(session, topics.observation(uav), AgentObservation,
                          self._on_observation, self.dropped),
            bus.subscribe(session, topics.measurement_round(uav), MeasurementRound,
                          self._on_observation, self.dropped),
            bus.subscribe(session, topics.value_weights, ValueWeights, self.updates.put,
                          self.dropped, lambda why: self.updates.put(("value", None, why))),
            bus.subscribe(session, topics.sinr_map, SinrMap, self._on_sinr_map, self.dropped,
                          lambda why: self.updates.put(("sinr_map", None, why))),
            bus.serve_status(session, topics, ROLE, uav, self.status),
        ]
        self.token = None
        # The newest SINR map version received: one the world names beyond it was never
        # published (the cloud publishes a map before the world can name it).
        self.heard_sinr = -1
        self.unknown_version_told = False

    def _on_sinr_map(self, update: SinrMap) -> None:
        self.heard_sinr = max(self.heard_sinr, update.version)
        self.updates.put(update)

    def _on_observation(self, observation: AgentObservation | MeasurementRound) -> None:
        self.observations.put((time.perf_counter(), observation))

    def status(self) -> ProcessStatus:
        # list() copies a deque atomically (GIL held) while the main loop appends to it.
        timings = np.array(list(self.timings_us) or [0.0])
        cpu = np.array(list(self.cpu_us) or [0.0])
        waits = np.array(list(self.waits_us) or [0.0])
        p50, p99 = np.percentile(timings, [50, 99])
        return ProcessStatus(
            role=ROLE, ident=str(self.uav), pid=os.getpid(), t=time.time(),
            episode=self.episode, step=self.step, value_version=self.models.value_version,
            sinr_version=self.models.sinr_version, dropped=self.dropped.as_dict(),
            details={"decisions": self.decisions, **self.uploader.counts(),
                     "decision_p50_us": float(p50), "decision_p99_us": float(p99),
                     "decision_cpu_p99_us": float(np.percentile(cpu, 99)),
                     "decision_wait_p99_us": float(np.percentile(waits, 99)),
                     "ready": self.models.ready},
        )

    # -- start ------------------------------------------------------------------------------
    def start(self, stop: threading.Event) -> bool:
        """Fetch both maps, then declare presence (the world waits for it): False if stopped
        first."""
        for key, kind in ((self.topics.value_weights, ValueWeights),
                          (self.topics.sinr_map, SinrMap)):
            while not stop.is_set():
                try:
                    self.models.accept(bus.query(self.session, key, kind, timeout=2.0))
                    break
                except (bus.BusError, WeightsError) as exc:
                    self.log.info("waiting for the cloud: %s", exc)
                    stop.wait(0.5)
        if stop.is_set():
            return False
        self.token = bus.declare_alive(self.session, self.topics, ROLE, self.uav)
        return True

    # -- main loop --------------------------------------------------------------------------
    def run(self, stop: threading.Event) -> None:
        """Fly until ``stop``, then hand the outbox over to the cloud before returning."""
        helpers = [threading.Thread(target=self.uploader.run, args=(stop,), name="uploads"),
                   threading.Thread(target=self._prepare_updates, args=(stop,), name="maps")]
        for helper in helpers:
            helper.start()
        try:
            self._fly(stop)
        finally:
            stop.set()
            for helper in helpers:
                helper.join()
            self.outbox.close()

    def _fly(self, stop: threading.Event) -> None:
        while not stop.is_set():
            try:
                received = [self.observations.get(timeout=0.2)]
            except queue.Empty:  # idle (UAV landed, world paused): prepare the maps
                self._take_updates()
                continue
            while not self.observations.empty():  # behind (realtime): act on the newest
                received.append(self.observations.get_nowait())
            self._take_updates()
            seen = []
            for arrived, item in received:
                if isinstance(item, MeasurementRound):
                    self._upload_round(item)
                else:
                    seen.append((arrived, item))
            if not seen:
                continue
            arrived, observation = seen[-1]
            self._act(arrived, observation)
            for _, each in seen:
                self._measure(each)
            self._prepare_next_route(observation)

    def _prepare_next_route(self, observation: AgentObservation) -> None:
        """Build the route field to the UAV's next destination on the map in use, between
        decisions while no observation waits: the next mission's first decision then finds it
        ready instead of building it (which made those decisions an agent's slowest). Only the
        extended method reads route fields."""
        radio_map, destination = self.models.radio_map, observation.next_destination
        if destination is None or not self.models.policy.options.route_distance:
            return
        if self.ahead != (radio_map, destination) and self.observations.empty():
            self.ahead = (radio_map, destination)
            radio_map.prepare_route(np.array(destination, dtype=np.float64))

    def _prepare_updates(self, stop: threading.Event) -> None:
        """Build what each new version is flown with, beside the deciding thread."""
        while not stop.is_set():
            try:
                update = self.updates.get(timeout=0.2)
            except queue.Empty:
                continue
            if isinstance(update, tuple):  # unreadable: nothing to build
                self.prepared.put(update)
                continue
            try:
                self.prepared.put((update, self.models.prepare(update)))
            except WeightsError as exc:
                self.prepared.put((update, exc))

    def _take_updates(self) -> None:
        """Fly with the new weights prepared since the last decision; refusals (unreadable
        payloads, queued as (kind, None, reason), or sound messages with unusable weights) are
        reported as events."""
        while not self.prepared.empty():
            item = self.prepared.get_nowait()
            if len(item) == 3:
                self._report_refusal(*item)
                continue
            update, built = item
            if not isinstance(built, WeightsError):
                self.models.commit(update, built)
                continue
            kind = "value" if isinstance(update, ValueWeights) else "sinr_map"
            key = self.topics.value_weights if kind == "value" else self.topics.sinr_map
            if self.dropped.add(key, f"version {update.version} refused: {built}"):
                self._report_refusal(kind, update.version, str(built))

    def _report_refusal(self, kind: str, version: int | None, reason: str) -> None:
        flying_on = self.models.value_version if kind == "value" else self.models.sinr_version
        bus.publish_event(self.session, self.topics, WeightsRefused(
            t=time.time(), source=f"agent-{self.uav}", uav=self.uav, weights=kind,
            version=version, reason=reason[:500], flying_on=flying_on))

    def _fly_version(self, version: int) -> None:
        """Fly the map version the world names, once built. It was published before the
        world named it, but comes by another route than the world's observation and can
        still be on its way: a version not heard of yet is asked of the cloud, whose answer
        is its newest map. One the cloud has not published either never comes (a forgery);
        then, or after MAP_WAIT_S, the agent flies on with what it has."""
        deadline = time.monotonic() + MAP_WAIT_S
        asked = False
        while not self.models.fly_version(version):
            if version > self.heard_sinr and not asked:
                asked = True
                self._ask_for_sinr_map()
            if version > self.heard_sinr or time.monotonic() > deadline:
                if not self.unknown_version_told:
                    self.unknown_version_told = True
                    self.log.warning("SINR map version %d is not to be had; flying version %s "
                                     "(further ones are not logged)", version,
                                     self.models.sinr_version)
                return
            time.sleep(0.002)
            self._take_updates()

    def _ask_for_sinr_map(self) -> None:
        """The cloud's newest SINR map, taken as if it had just been published; nothing if the
        cloud does not answer in time."""
        try:
            self._on_sinr_map(bus.query(self.session, self.topics.sinr_map, SinrMap,
                                        timeout=MAP_QUERY_S))
        except bus.BusError as exc:
            self.log.info("asking the cloud for its SINR map: %s", exc)

    def _act(self, arrived: float, observation: AgentObservation) -> None:
        self.waits_us.append((time.perf_counter() - arrived) * 1e6)
        if (observation.sinr_version is not None
                and observation.sinr_version != self.models.sinr_version):
            self._fly_version(observation.sinr_version)
        cpu = time.thread_time()
        self.models.destination = observation.destination
        decision = self.models.policy.decide(observation.observation(), self.models.radio_map)
        self.action_pub.put(encode(Action(
            episode=observation.episode, step=observation.step, uav=self.uav,
            speed=float(decision.speed[0]), heading=float(decision.heading[0]))))
        self.timings_us.append((time.perf_counter() - arrived) * 1e6)
        self.cpu_us.append((time.thread_time() - cpu) * 1e6)
        self.decisions += 1
        self.episode, self.step = observation.episode, observation.step

    def _measure(self, observation: AgentObservation) -> None:
        """Queue for upload what the receiver reported along the step, the same reports
        (de-duplicated by the same rule) as an in-process evaluation uploads."""
        taken = self._kept(observation.measured, observation.measured_db, observation.step,
                           time.time())
        if taken:
            self.outbox.add(taken, self.upload_every)

    def _upload_round(self, measurement_round: MeasurementRound) -> None:
        """Upload a round's reports at once, stamped with the run's flight time along the
        step as ``jamnav eval`` stamps them."""
        self.models.pin()
        count = len(measurement_round.measured)
        taken_at = measurement_round.flown_s - self.scenario.timing.step_s * (
            1 - np.arange(1, count + 1) / max(count, 1))
        self.uploader.send_round(
            self._kept(measurement_round.measured, measurement_round.measured_db,
                       measurement_round.step, taken_at),
            measurement_round.round, ROUND_RECEIPT_S)

    def _kept(self, measured: list, measured_db: list, step: int,
              taken_at: float | np.ndarray) -> list[tuple]:
        """The records of the reports ``measured`` (x, y, level), with their SINRs
        ``measured_db`` where the receiver reports them, that the spot filter keeps, each
        taken at ``taken_at`` (one time, or one per report)."""
        if not measured:
            return []
        reports = np.array(measured, dtype=np.float64)
        levels = reports[:, 2].astype(np.int64)
        kept = self.spots.keep(self.spots_row, reports[None, :, :2], levels[None])[0]
        if not kept.any():
            return []
        features = scenario_features(self.scenario, reports[kept, :2])
        times = np.broadcast_to(np.asarray(taken_at, dtype=np.float64), kept.shape)[kept]
        sinr_db = (np.asarray(measured_db)[kept].tolist() if measured_db
                   else [None] * int(kept.sum()))
        # Records as the outbox holds them, not models: the agent's own numbers, a few a step,
        # and the cloud checks every measurement on receipt (MeasurementSpec).
        return [(f"{self.id_prefix}{next(self.measured)}", self.source, step, when,
                 row.tobytes(), level, db)
                for row, level, when, db in zip(features.astype(FEATURES_DTYPE, copy=False),
                                                levels[kept].tolist(), times.tolist(), sinr_db,
                                                strict=True)]


def join(session, topics: Topics, stop: threading.Event, log: logging.Logger) -> int | None:
    """Ask the world for a UAV without an agent (agents started as identical replicas)."""
    while not stop.is_set():
        try:
            return bus.query(session, topics.join, JoinReply, timeout=2.0).uav
        except bus.BusError as exc:
            log.info("waiting for a UAV: %s", exc)
            stop.wait(1.0)
    return None


# -- process shell ------------------------------------------------------------------------------
def build_parser() -> argparse.ArgumentParser:
    parser = ArgumentParser(prog="python -m uav_agent.process", description=__doc__)
    add_bus_arguments(parser)
    parser.add_argument("--scenario", default=None)
    parser.add_argument("--uav", type=int, default=None,
                        help="UAV to fly (default: ask the world for a free one)")
    parser.add_argument("--upload-every", type=int, default=DEFAULT_BATCH, metavar="N",
                        help="measurements per upload (or fewer, once the oldest is "
                             f"{DEFAULT_MAX_AGE_S:g} s old)")
    parser.add_argument("--outbox", type=int, default=DEFAULT_CAPACITY, metavar="N",
                        help="measurements kept while the cloud does not acknowledge them "
                             "(beyond that the oldest are dropped, and counted)")
    parser.add_argument("--outbox-dir", type=Path, default=None, metavar="DIR",
                        help="keep the outbox in DIR/uav-<uav>.outbox too, so that it "
                             "survives the agent (default: in memory only)")
    return parser


def agent_setup(args: argparse.Namespace) -> bus.ServiceSetup:
    """The agent the arguments ask for; a ValueError names the first wrong one, and a
    PlannerError a planner that cannot run."""
    require_planner()
    scenario = load_scenario(args.scenario)
    if args.uav is not None and not 0 <= args.uav < MAX_UAVS:
        raise ValueError(f"--uav must be between 0 and {MAX_UAVS - 1}")
    if not 1 <= args.upload_every <= MAX_UPLOAD:
        raise ValueError(f"--upload-every must be between 1 and {MAX_UPLOAD}")
    if args.outbox < 1:
        raise ValueError("--outbox must be at least 1")
    if args.outbox_dir is not None:
        try:
            args.outbox_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise ValueError(f"--outbox-dir {args.outbox_dir}: {exc.strerror}") from None
    topics = Topics(args.prefix)
    endpoint = endpoint_from(args.endpoint)
    login = None
    if args.credentials is not None:
        if args.uav is None:
            raise ValueError("--credentials needs --uav: an agent logs in as agent-<uav>")
        login = access.login_for(args.credentials, access.agent_role(args.uav))

    def run(session: zenoh.Session, stop: threading.Event, log: logging.Logger) -> int:
        uav = args.uav if args.uav is not None else join(session, topics, stop, log)
        if uav is None:
            return 0
        agent = AgentService(session, topics, scenario, uav, log, args.upload_every,
                             outbox=args.outbox, outbox_dir=args.outbox_dir)
        if agent.start(stop):
            agent.run(stop)
        return 0

    return bus.ServiceSetup(endpoint, login, run,
                            log_name=f"agent-{'?' if args.uav is None else args.uav}")


def main(argv: list[str] | None = None) -> int:
    return bus.run_service("agent", build_parser(), agent_setup, argv)


if __name__ == "__main__":
    sys.exit(main())

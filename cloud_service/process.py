"""The cloud process: serves the latest weights of both networks and keeps the SINR map current.

- The value network and the SINR map are each a queryable (the latest version, for agents
  that start) plus a publication on every new version.
- Measurement uploads (queries) go into the replay memory through the online SINR mapper,
  which watches the map's accuracy, detects jammer changes and retrains in its own worker; each
  new version is saved in the run directory and published, with events. An upload is answered
  with a receipt only once it is stored: an agent keeps what has no receipt and sends it again.
- ``--map perfect`` and ``--map outdated`` replace the learned map, for comparison: the true
  map of the current jammer (followed through the world's ``jammer_changed`` events) or the
  map without any jammer, both as rasters.
- ``--clock lockstep`` (with the online map) puts the cloud on the world's clock: uploads come
  in rounds, one per world step, and each is taken whole, in simulated time, before the world
  goes on (``cloud_service.rounds``); a map flies from the round its latency says.

Zenoh callbacks only queue what arrives; one worker thread does the storing and learning.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import queue
import re
import sys
import threading
import time
from pathlib import Path
from typing import Any

import zenoh

from cloud_service.change_handling import RetrainConfig
from cloud_service.estimated_jammer import JammerEstimate as EstimatedJammer
from cloud_service.mapper_outputs import PublishedWeights
from cloud_service.rollout import RasterMaps
from cloud_service.rounds import RoundDesk, delay_rounds
from cloud_service.sinr_mapping import OnlineSinrMapper
from cloud_service.sinr_memory import RUN_DIR_FILE, SinrMemory
from planning.compiled import require_modules
from planning.networks import SinrMapNetwork, WeightsError, card_path, load_network, sha256
from shared import access, bus
from shared.cloud_messages import (
    MapMode,
    MeasurementUpload,
    RasterGrid,
    SinrMap,
    UploadReceipt,
    ValueWeights,
)
from shared.events import (
    ChangeDetected,
    JammerChanged,
    JammerEstimated,
    RetrainFailed,
    SinrWeightsPublished,
)
from shared.jammer_messages import (
    JammerEstimate,
    JammerInfo,
    JammersInForce,
    describe_count,
    describe_estimate,
    describe_jammers,
    initial_jammers,
)
from shared.measurements import MeasurementBatch, MeasurementSpec
from shared.process_status import ProcessStatus
from shared.radio import radio_core
from shared.scenario import Scenario, load_scenario
from shared.shipped import EXTENDED_VALUE_NET, VALUE_NET_HELP, value_net_for
from shared.survey_maps import foreign_survey_map, sinr_map_for
from shared.topics import ArgumentParser, Topics, add_bus_arguments, endpoint_from
from shared.wire import MessageError, encode
from shared.world_messages import RoundClosed, RoundOpened

ROLE = "cloud"
# Measurements are stamped with the agent's clock: a stamp further ahead than this is a bad
# clock or a forgery, and would stay "recent" in the memory for ever.
CLOCK_SKEW_S = 60.0
_VERSION_FILE = re.compile(r"^sinr_map_v(\d+)\.safetensors$")


def raster_map(scenario: Scenario, maps: RasterMaps, mode: MapMode, version: int,
               jammers: JammersInForce) -> SinrMap:
    """The true (``perfect``) or no-jammer (``outdated``) map as the lookahead's raster."""
    raster = maps.raster(JammerInfo.params(jammers) if mode == "perfect" else None)
    data = raster.levels.tobytes()
    rows, cols = raster.levels.shape
    return SinrMap(version=version, mode=mode, sha256=sha256(data), data=data,
                   grid=RasterGrid(x0=raster.x0, y0=raster.y0, spacing=raster.spacing,
                                   rows=rows, cols=cols))


def map_card(weights: PublishedWeights, published: float,
             flown_s: float | None = None) -> dict[str, Any]:
    """The card saved beside a published SINR map: what a restarted cloud carries on with;
    on the lockstep clock, also the run's seconds of flight when it was published."""
    return {"version": weights.version, "accuracy": weights.accuracy, "sha256": weights.sha256,
            "published": published, "flown_s": flown_s,
            "estimate": None if weights.estimate is None else weights.estimate.record(),
            "refining_since": weights.refining_since, "provisional": weights.provisional}


def estimate_of(card: dict[str, Any]) -> EstimatedJammer | None:
    """The jammer estimate a saved map's card holds (None: the map had none, or a card this
    cloud cannot read it from, which only costs the detector the estimate's model)."""
    fields = card.get("estimate")
    if not isinstance(fields, dict):
        return None
    try:
        return EstimatedJammer.of_record(fields)
    except TypeError:
        return None


def _saved_maps(directory: Path) -> list[tuple[int, Path]]:
    """The SINR maps previous runs of this cloud published, with their versions."""
    return [(int(m.group(1)), p) for p in directory.glob("sinr_map_v*.safetensors")
            if (m := _VERSION_FILE.match(p.name))]


def latest_saved(directory: Path) -> Path | None:
    """The newest SINR map a previous run of this cloud published (to carry on after it)."""
    versions = _saved_maps(directory)
    return max(versions)[1] if versions else None


def first_change_start(directory: Path) -> float | None:
    """When the earliest change that a saved corrected map answered began (its card's
    ``refining_since``); None when no card tells of one. A card that cannot be read tells of
    none rather than stop the cloud: the reports since its change then enter the rebuilt
    no-jammer reference."""
    starts = []
    for _, path in _saved_maps(directory):
        try:
            card = json.loads(card_path(path).read_text(encoding="utf-8"))
        except (OSError, json.JSONDecodeError):
            continue
        if isinstance(start := card.get("refining_since"), int | float):
            starts.append(float(start))
    return min(starts, default=None)


class CloudService:
    """The cloud process's work: serve both networks, store every upload, keep the SINR map
    current (or follow the true one), and, on the lockstep clock, close each round."""

    def __init__(self, session, topics: Topics, scenario: Scenario, mode: MapMode,
                 run_dir: Path, log: logging.Logger, *, value_net: Path = EXTENDED_VALUE_NET,
                 sinr_net: Path | None = None, jammers: JammersInForce = (),
                 retrain: RetrainConfig | None = None, lockstep: bool = False):
        self.session, self.topics, self.scenario, self.mode, self.log = (
            session, topics, scenario, mode, log)
        self.flown_s = 0.0  # on the lockstep clock: the mapper's time, the round's
        self.rounds: RoundDesk | None = None
        self.maps_dir = run_dir / "sinr_maps"
        self.maps_dir.mkdir(parents=True, exist_ok=True)
        self.dropped = bus.Dropped(log)
        self.tasks: queue.SimpleQueue = queue.SimpleQueue()
        self.receipts = {"measurements_stored": 0, "measurements_duplicates": 0,
                         "measurements_refused": 0}  # since this process started
        self._lock = threading.Lock()  # guards the two current messages
        self.value = self._value_weights(value_net)
        self.memory = SinrMemory(run_dir / RUN_DIR_FILE, MeasurementSpec.of(scenario))
        self.mapper: OnlineSinrMapper | None = None
        self._events_seen = 0
        if mode == "online":
            self.sinr = self._start_mapper(sinr_net or sinr_map_for(scenario), retrain, lockstep)
            if lockstep:
                self.rounds = RoundDesk(delay_rounds(scenario.online_map.cloud_latency_s,
                                                     scenario.timing.step_s), self.sinr.version)
        else:
            self.raster_maps = RasterMaps(scenario)
            self.sinr = raster_map(scenario, self.raster_maps, mode, 1, jammers)
        self.value_pub = bus.reliable_publisher(session, topics.value_weights)
        self.sinr_pub = bus.reliable_publisher(session, topics.sinr_map)
        self.estimate_pub = bus.reliable_publisher(session, topics.jammer_estimate)
        # Agents that outlived a restart of the cloud (and missed what it published while it
        # was down) catch up; agents that start later ask the queryables.
        self.value_pub.put(encode(self.value))
        self.sinr_pub.put(encode(self.sinr))
        self.upload_desk = session.declare_queryable(topics.measurements("*"), self._on_upload)
        self._declared = [
            session.declare_queryable(topics.value_weights, self._serve_value),
            session.declare_queryable(topics.sinr_map, self._serve_sinr),
            bus.serve_status(session, topics, ROLE, 0, self.status),
        ]
        if mode == "perfect":
            self._declared.append(bus.subscribe(session, topics.event("jammer_changed"),
                                                JammerChanged, self.tasks.put, self.dropped))
        if self.rounds is not None:
            self.round_pub = bus.reliable_publisher(session, topics.round_closed)
            self._declared.append(bus.subscribe(session, topics.round_opened, RoundOpened,
                                                self.tasks.put, self.dropped))
        self._declared.append(bus.declare_alive(session, topics, ROLE, 0))

    def _value_weights(self, path: Path) -> ValueWeights:
        """The value network to serve, checked as an agent will check it; its card may carry
        a version, so that a replaced file reaches running agents."""
        _, card = load_network(path, {"kind": "value"})
        data = path.read_bytes()
        return ValueWeights(version=int(card.get("version", 1)), sha256=sha256(data), data=data)

    def _start_mapper(self, sinr_net: Path, retrain: RetrainConfig | None,
                      lockstep: bool) -> SinrMap:
        spec = MeasurementSpec.of(self.scenario)
        path = latest_saved(self.maps_dir) or sinr_net
        network, card = load_network(path, {"kind": "sinr_map", "input_size": spec.feature_size,
                                            "levels": spec.level_count})
        accuracy = card.get("accuracy")
        if not isinstance(accuracy, int | float):
            raise WeightsError(f"{path}: its card states no accuracy")
        version = int(card.get("version", 0))
        estimate = estimate_of(card)
        refining_since = card.get("refining_since")
        # The survey map stays the base every estimate corrects, whichever map is in service.
        base, base_card = load_network(sinr_net, {"kind": "sinr_map",
                                                  "input_size": spec.feature_size,
                                                  "levels": spec.level_count})
        if (warning := foreign_survey_map(base_card, self.scenario)) is not None:
            self.log.warning("%s: %s", sinr_net, warning)
        # On the lockstep clock the mapper runs as in-process: inline, in simulated time, and
        # without a wall-clock budget that a busy machine would cut a refit short by.
        timing = ({"clock": lambda: self.flown_s, "background": False,
                   "retrain": retrain or RetrainConfig(max_seconds=None)} if lockstep
                  else {"retrain": retrain})
        self.mapper = OnlineSinrMapper(self.scenario, self.memory, network, float(accuracy),
                                       base_network=base,
                                       base_accuracy=float(base_card.get("accuracy", accuracy)),
                                       publish=self._on_retrained, **timing, version=version,
                                       estimate=estimate,
                                       refining_since=refining_since
                                       if isinstance(refining_since, int | float) else None,
                                       changed_since=first_change_start(self.maps_dir))
        data = path.read_bytes()
        return SinrMap(version=version, mode="online", sha256=sha256(data), data=data,
                       accuracy=float(accuracy))

    # -- zenoh threads ---------------------------------------------------------------------
    def _serve_value(self, query) -> None:
        query.reply(self.topics.value_weights, encode(self.value))

    def _serve_sinr(self, query) -> None:
        with self._lock:
            current = self.sinr
        query.reply(self.topics.sinr_map, encode(current))

    def _on_upload(self, query) -> None:
        """Checked here, stored and answered by the worker (the query waits for its receipt)."""
        key = self.topics.measurements("*")
        try:
            upload = bus.receive(MeasurementUpload, query.key_expr, query.payload)
            if upload.newest() > time.time() + CLOCK_SKEW_S:
                raise MessageError("upload with measurements from the future")
            if upload.round is not None and self.rounds is None:
                raise MessageError("a round's upload, and the cloud is not on the lockstep "
                                   "clock")
        except MessageError as exc:
            self.dropped.add(key, str(exc))
            bus.refuse(query, str(exc))
            return
        self.tasks.put((upload, query))

    def status(self) -> ProcessStatus:
        with self._lock:
            current = self.sinr
        details = {"map": self.mode, "stored": self.memory.count(),
                   "map_accuracy": current.accuracy, **self.receipts}
        if self.mapper is not None:
            details.update(mapper_details(self.mapper.state()))
        return ProcessStatus(role=ROLE, ident="0", pid=os.getpid(), t=time.time(),
                             value_version=self.value.version, sinr_version=current.version,
                             dropped=self.dropped.as_dict(), details=details)

    # -- worker ----------------------------------------------------------------------------
    def run(self, stop: threading.Event) -> None:
        while not stop.is_set():
            try:
                tasks = [self.tasks.get(timeout=0.2)]
            except queue.Empty:
                self._close_rounds()  # a round that waited its time for an agent
                continue
            while not self.tasks.empty():
                tasks.append(self.tasks.get_nowait())
            self._handle(tasks)
        # Uploads already taken in get their receipt; later ones find no cloud, and wait.
        self.upload_desk.undeclare()
        while not self.tasks.empty():
            self._handle([self.tasks.get_nowait()])
        if self.mapper is not None:
            self.mapper.close()
        else:
            self.memory.close()

    def _handle(self, tasks: list) -> None:
        kept = []  # uploads the memory takes and nothing learns from: stored together
        for task in tasks:
            if isinstance(task, JammerChanged):
                self._follow_jammer(task)
            elif isinstance(task, RoundOpened):
                self.rounds.open(task)
            elif self._learned_from(task[0]):
                self._upload(*task)
            else:
                kept.append(task)
        self._keep(kept)
        self._close_rounds()

    def _learned_from(self, upload: MeasurementUpload) -> bool:
        """Whether an upload goes to the online map. On the lockstep clock, one outside a
        round of this world's (an earlier run's outbox, a round's upload after the round
        closed without it, a round never opened) is kept, not learned from: the mapper takes
        whole rounds only."""
        if self.rounds is None:
            return self.mapper is not None
        return upload.round is not None and not self.rounds.stale(upload.round)

    def _upload(self, upload: MeasurementUpload, query) -> None:
        if self.rounds is None:
            _answer(query, self._ingest(upload.batch()))
        else:
            self.rounds.add(upload, query)

    def _keep(self, uploads: list[tuple[MeasurementUpload, Any]]) -> list[MeasurementBatch]:
        """Store uploads in one transaction and answer each; the rows each one stored."""
        stored = self.memory.store_each([upload.batch() for upload, _ in uploads])
        for (upload, query), (rows, duplicates) in zip(uploads, stored, strict=True):
            _answer(query, self._count((len(rows), duplicates), len(upload.ids)))
        return [rows for rows, _ in stored]

    def _close_rounds(self) -> None:
        """Take every round whose uploads are in: store them in UAV order, have the mapper
        take them as one batch, answer the uploads and the world."""
        if self.rounds is None:
            return
        self._keep(self.rounds.unopened(time.monotonic()))
        while (closing := self.rounds.next_closing(time.monotonic())) is not None:
            opened, uploads = closing
            self.flown_s = opened.flown_s
            before = self.mapper.version
            if stored := self._keep(uploads):
                self.mapper.take(MeasurementBatch.concatenate(stored))
                self._publish_mapper_events()
            self.rounds.published(opened.round, list(range(before + 1,
                                                           self.mapper.version + 1)))
            self.rounds.close(opened.round)
            self.round_pub.put(encode(RoundClosed(round=opened.round,
                                                  serving=self.rounds.serving,
                                                  pending=self.rounds.pending)))

    def _ingest(self, measurements: MeasurementBatch) -> UploadReceipt:
        report = self.mapper.ingest(measurements)
        self._publish_mapper_events()
        return self._count((report.accepted, report.duplicates), len(measurements))

    def _count(self, counts: tuple[int, int], uploaded: int) -> UploadReceipt:
        """The receipt of an upload of ``uploaded`` records, ``counts`` (stored, duplicates)
        of them new and repeated; the rest were refused."""
        stored, duplicates = counts
        receipt = UploadReceipt(stored=stored, duplicates=duplicates,
                                refused=uploaded - stored - duplicates)
        for name, count in receipt:
            self.receipts[f"measurements_{name}"] += count
        return receipt

    def _publish_mapper_events(self) -> None:
        events = self.mapper.events
        for event in events[self._events_seen:]:
            if event["type"] == "change_detected":
                self._publish_event(ChangeDetected(
                    t=event["t"], source=ROLE, version=event["version"],
                    accuracy=event["accuracy"], change_time=event.get("change_time")))
                self.log.info("jammer change detected (map v%d at %.1f%% on the last window)",
                              event["version"], 100 * event["accuracy"])
            elif event["type"] == "estimate_not_converged":
                self.log.info("jammer estimate not converged on %d measurements (%s); trying "
                              "again as more arrive", event["measurements"],
                              describe_count(event["jammers_counted"]))
            elif event["type"] == "estimate_withdrawn":
                self.log.info("jammer estimate withdrawn: %.1f nats against it from the reports "
                              "since t=%.1f; the survey map is in service as v%d",
                              event["evidence_nats"], event["evidence_since"], event["version"])
            elif event["type"] == "jammer_withdrawn":
                self.log.info("jammer at (%.1f, %.1f) m withdrawn alone: %.1f nats against it "
                              "since t=%.1f; %d left", event["x"], event["y"],
                              event["evidence_nats"], event["evidence_since"],
                              event["jammers_left"])
            elif event["type"] == "jammer_tracked":
                self.log.info("jammer tracked at (%.1f, %.1f) m, moving (%.1f, %.1f) +- "
                              "(%.1f, %.1f) m/s", event["x"], event["y"], event["vx"],
                              event["vy"], event["sd_vx_mps"], event["sd_vy_mps"])
            elif event["type"] == "retrain_failed":
                self._publish_event(RetrainFailed(t=event["t"], source=ROLE,
                                                  version=event["version"],
                                                  error=event["error"][:2000]))
        self._events_seen = len(events)

    def _follow_jammer(self, change: JammerChanged) -> None:
        with self._lock:
            version = self.sinr.version + 1
        update = raster_map(self.scenario, self.raster_maps, self.mode, version,
                            tuple(change.jammers))
        with self._lock:
            self.sinr = update
        self.sinr_pub.put(encode(update))
        self.log.info("true map v%d published: %s", version, describe_jammers(change.jammers))

    def _on_retrained(self, weights: PublishedWeights) -> None:
        """Runs on the mapper's retraining thread."""
        path = self.maps_dir / f"sinr_map_v{weights.version}.safetensors"
        path.write_bytes(weights.data)
        path.with_suffix(".json").write_text(json.dumps(
            map_card(weights, time.time(), None if self.rounds is None else self.flown_s),
            indent=2) + "\n", encoding="utf-8")
        update = SinrMap(version=weights.version, mode="online", sha256=weights.sha256,
                         data=weights.data, accuracy=weights.accuracy)
        with self._lock:
            self.sinr = update
        self.sinr_pub.put(encode(update))
        if weights.estimate is not None:
            estimate = estimate_message(weights.estimate, weights.version, time.time())
            self.estimate_pub.put(encode(estimate))
            self._publish_event(JammerEstimated(t=estimate.t, source=ROLE, estimate=estimate))
            self.log.info("jammer estimate with map v%d: %s", weights.version,
                          describe_estimate(estimate))
        self._publish_event(SinrWeightsPublished(
            t=time.time(), source=ROLE, version=weights.version, accuracy=update.accuracy,
            sha256=weights.sha256, path=str(path.resolve()), provisional=weights.provisional,
            jammers_counted=weights.jammers_counted))
        self.log.info("%sSINR map v%d published (held-out accuracy %.1f%%)",
                      "provisional " if weights.provisional else "", weights.version,
                      100 * weights.accuracy)

    def _publish_event(self, event) -> None:
        bus.publish_event(self.session, self.topics, event)


def _answer(query, receipt: UploadReceipt) -> None:
    query.reply(query.key_expr, encode(receipt))
    query.drop()  # a query held on to is not finished: its caller would wait


# -- process shell ------------------------------------------------------------------------------
def estimate_message(estimate, map_version: int, t: float) -> JammerEstimate:
    """The wire form of a ``jammer_estimation.JammerEstimate``: each jammer of its set
    numbered in the set's order."""
    if not estimate.present:
        return JammerEstimate(map_version=map_version, t=t, present=False,
                              measurements=estimate.measurements)
    first, *others = (JammerEstimate(map_version=map_version, t=t, id=index, **{
        key: value for key, value in member._asdict().items()
        if key in JammerEstimate.model_fields and key != "others"})
        for index, member in enumerate(estimate.members))
    return first.model_copy(update={"others": others})


def mapper_details(state: dict) -> dict:
    """The mapper's state as status scalars."""
    estimate = state["estimate"]
    return {"map_phase": state["phase"], "recent_accuracy": state["recent_accuracy"],
            "since_change": state["since_change"], "map_provisional": state["provisional"],
            "jammers_counted": state["jammers_counted"],
            "estimate": None if estimate is None else describe_estimate(
                estimate_message(estimate, state["map_version"], 0.0))}


def build_parser() -> argparse.ArgumentParser:
    parser = ArgumentParser(prog="python -m cloud_service.process", description=__doc__)
    add_bus_arguments(parser)
    parser.add_argument("--scenario", default=None)
    parser.add_argument("--map", choices=("online", "perfect", "outdated"), default="online")
    parser.add_argument("--run-dir", default="runs/cloud", metavar="DIR",
                        help="replay memory and published SINR maps")
    parser.add_argument("--value-net", default=None, metavar="NAME|PATH",
                        help=f"{VALUE_NET_HELP}; the cloud does not know the fleet: unless "
                             "told (`jamnav up` tells it), the one for the scenario's own "
                             "fleet and jammers")
    parser.add_argument("--sinr-map", "--sinr-net", dest="sinr_net", default=None, metavar="PATH",
                        help="the survey's no-jammer SINR map (online; default: the shipped "
                             "one of the scenario's radio world)")
    parser.add_argument("--retrain-samples", type=int, default=None, metavar="N",
                        help="post-change measurements a retraining waits for")
    parser.add_argument("--clock", choices=("realtime", "lockstep"), default="realtime",
                        help="lockstep: the online map takes the world's rounds of uploads, "
                             "in simulated time (the world runs --cloud-clock)")
    parser.add_argument("--cloud-latency", type=float, default=None, metavar="S",
                        help="lockstep: flight seconds from a round to the maps it triggers "
                             "in service (default: the scenario's online_map.cloud_latency_s)")
    jam = parser.add_mutually_exclusive_group()
    jam.add_argument("--jammer", metavar="X,Y,P[,H]", help="initial jammer (map perfect)")
    jam.add_argument("--jammers", metavar="JSON",
                     help="initial jammers (map perfect), as messages carry them")
    jam.add_argument("--no-jammer", action="store_true")
    return parser


def load_training(network: SinrMapNetwork, background: bool) -> None:
    """Torch takes seconds to import, and its first fit longer than the next (BENCHMARKS.md,
    "Distributed runtime"). The cloud serves its weights at once (the agents, and so the first
    step, wait for them) and loads torch meanwhile, and fits ``network`` (the survey map) for
    two throwaway steps, so that its first retraining after a change does not pay the first
    fit's set-up. On the lockstep clock it does so before the first round instead: a fit of a
    round must not draw on torch beside it."""

    def load() -> None:
        import torch

        # The SINR network is tiny: on two cores a second thread only adds hand-offs.
        torch.set_num_threads(1)
        from cloud_service.sinr_training import warm_up

        warm_up(network)

    if background:
        threading.Thread(target=load, name="load-torch", daemon=True).start()
    else:
        load()


def cloud_setup(args: argparse.Namespace) -> bus.ServiceSetup:
    """The cloud the arguments ask for; a ValueError names the first wrong one, and a
    CompiledCoreError a compiled core that cannot run (the radio's, the jammer search's sums,
    the networks' steps and the reports' features, all of which the cloud computes)."""
    radio_core()
    require_modules("_evidence", "_regression", "_measuring")
    scenario = load_scenario(args.scenario)
    if args.cloud_latency is not None:
        scenario = scenario.changed({"online_map.cloud_latency_s": args.cloud_latency})
    if args.clock == "lockstep" and args.map != "online":
        raise ValueError("--clock lockstep is the online map's: --map perfect and outdated "
                         "follow the world's jammer instead")
    jammers = initial_jammers(scenario, args.jammer, args.jammers, args.no_jammer)
    if args.map == "perfect" and any(not jammer.as_jammer(scenario).still for jammer in jammers):
        raise ValueError("--map perfect serves the true map of still jammers; one of these "
                         "moves or switches")
    retrain = None
    if args.retrain_samples is not None:
        if args.retrain_samples < 2:
            raise ValueError("--retrain-samples must be at least 2")
        retrain = RetrainConfig(min_samples=args.retrain_samples)
    sinr_net = None  # resolved here, so that a world without one is refused before connecting
    if args.map == "online":
        sinr_net = Path(args.sinr_net) if args.sinr_net else sinr_map_for(scenario)
    # Chosen for the jammers the run starts with, as jamnav eval chooses.
    value_net = value_net_for(args.value_net, scenario, scenario.missions.uav_count,
                              [jammer.as_jammer(scenario) for jammer in jammers])
    topics = Topics(args.prefix)

    def run(session: zenoh.Session, stop: threading.Event, log: logging.Logger) -> int:
        try:
            cloud = CloudService(session, topics, scenario, args.map, Path(args.run_dir), log,
                                 value_net=value_net,
                                 sinr_net=sinr_net,
                                 jammers=jammers, retrain=retrain,
                                 lockstep=args.clock == "lockstep")
        except (WeightsError, ValueError) as exc:
            return bus.bad_arguments(ROLE, exc)
        if cloud.mapper is not None:
            load_training(cloud.mapper.current_network(), background=cloud.rounds is None)
        cloud.run(stop)
        return 0

    return bus.ServiceSetup(endpoint_from(args.endpoint),
                            access.login_for(args.credentials, access.CLOUD), run)


def main(argv: list[str] | None = None) -> int:
    return bus.run_service(ROLE, build_parser(), cloud_setup, argv)


if __name__ == "__main__":
    sys.exit(main())

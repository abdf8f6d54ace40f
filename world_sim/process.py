"""The world process: owns the truth (one environment of ``VectorWorld``) and steps it.

Each step it sends every active UAV its observation, collects the agents' actions, applies
pending jammer commands, steps the world and publishes the fleet state; at the end of an
episode it publishes the UAV outcomes. Two clocks:

- ``lockstep``: step t waits for the action for t of every live agent (liveliness), up to a
  deadline. Deterministic: the same seed gives the same episodes as ``jamnav eval``.
- ``realtime``: steps at a fixed rate; whatever action arrived for the current step is used.

With ``cloud_clock`` (lockstep, online map) the cloud is part of the clock: after each step the
world hands every UAV's agent its reports (``MeasurementRound``), waits until the cloud has
taken the round (``RoundClosed``), and names the map in service in each observation.
The jammers in force follow the operator's commands (``world_sim.jammer_desk``); with
``swap_every`` one jammer moves to a fresh random setting every K episodes, the ones
``jamnav eval --swap-every K`` flies (``world_sim.jammers``).

Either way a UAV without a fresh action keeps its last velocity, and the miss is counted.
Zenoh callbacks only store what they receive; the main loop does all the work.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import threading
import time
from dataclasses import dataclass

import numpy as np
import zenoh

from shared import access, bus
from shared.events import JammerChanged, RunFinished, UavOutcomes, outcome_labels
from shared.jammer_messages import (
    JammerInfo,
    JammerPlace,
    JammersInForce,
    describe_jammers,
    initial_jammers,
)
from shared.observation import Observation, decision_reach, decision_relevant
from shared.process_status import ProcessStatus
from shared.radio import radio_core
from shared.scenario import MAX_UAVS, Jammer, Scenario, load_scenario
from shared.topics import ArgumentParser, Topics, add_bus_arguments, endpoint_from
from shared.wire import encode
from shared.world_messages import (
    Action,
    AgentObservation,
    Clock,
    JoinReply,
    MeasurementRound,
    RoundClosed,
    RoundOpened,
    WorldState,
)
from world_sim.cloud_rounds import CloudRounds
from world_sim.core import VectorWorld, episode_seed, fleet_observation
from world_sim.jammer_desk import JammerDesk
from world_sim.jammers import swapping_jammers

ROLE = "world"
JOIN_HOLD_S = 10.0  # an id handed out is kept for its agent this long, waiting for its token
OUTCOMES_KEPT = 1000  # episodes whose outcomes a late or reconnected subscriber can fetch
MISSES_NAMED = 10  # steps with missed deadlines an episode's warning names


@dataclass(frozen=True)
class WorldConfig:
    """How a world process runs: its fleet and seed, how long, on which clock, and how
    long it waits for agents and the cloud."""

    uavs: int
    seed: int = 0
    episodes: int | None = None  # None: until stopped (or ``duration``)
    duration: float | None = None  # seconds of wall time
    first_episode: int = 0  # a restarted world carries on where the last one stopped
    clock: Clock = "lockstep"
    rate: float = 10.0  # realtime: steps per second of wall time
    deadline: float = 2.0  # lockstep: seconds to wait for the actions of a step
    start_timeout: float = 60.0  # how long the first episode waits for every agent
    cloud_clock: bool = False  # lockstep with the online map: each step waits for the cloud
    # How long a round waits for the cloud: a refit runs without a wall-clock budget on the
    # lockstep clock and takes seconds on a busy machine.
    cloud_deadline: float = 60.0
    swap_every: int | None = None  # a fresh random jammer every K episodes


class Mailbox:
    """Actions and agent presence, written by zenoh's threads, read by the main loop."""

    def __init__(self, uavs: int):
        self.uavs = uavs
        self._cond = threading.Condition()
        self._actions: dict[int, Action] = {}
        self._live: set[int] = set()
        self._joined: set[int] = set()  # live agents the main loop has not greeted yet
        self._held: dict[int, float] = {}  # ids handed out by ``join``, until when

    def put_action(self, action: Action) -> None:
        with self._cond:
            self._actions[action.uav] = action
            self._cond.notify()

    def on_presence(self, sample: zenoh.Sample) -> None:
        try:
            uav = int(str(sample.key_expr).rsplit("/", 1)[-1])
        except ValueError:
            return
        with self._cond:
            if sample.kind == zenoh.SampleKind.PUT:
                self._live.add(uav)
                self._joined.add(uav)
                self._held.pop(uav, None)
            else:
                self._live.discard(uav)
                self._joined.discard(uav)
            self._cond.notify()

    def live(self) -> set[int]:
        with self._cond:
            return set(self._live)

    def take_joined(self) -> set[int]:
        with self._cond:
            joined, self._joined = self._joined, set()
            return joined

    def hand_out(self) -> int | None:
        """A UAV id no live agent flies and none was promised to recently."""
        now = time.monotonic()
        with self._cond:
            for uav in range(self.uavs):
                if uav not in self._live and self._held.get(uav, 0.0) < now:
                    self._held[uav] = now + JOIN_HOLD_S
                    return uav
        return None

    def wait_all_live(self, until: float, stop: threading.Event) -> bool:
        with self._cond:
            while len(self._live & set(range(self.uavs))) < self.uavs:
                remaining = until - time.monotonic()
                if remaining <= 0 or stop.is_set():
                    return False
                self._cond.wait(min(remaining, 0.2))
            return True

    def collect(self, episode: int, step: int, active: set[int], until: float,
                stop: threading.Event, early: bool) -> dict[int, Action]:
        """Actions for (episode, step) of the ``active`` UAVs that are in by ``until``; with
        ``early``, return as soon as every live active UAV has answered."""
        with self._cond:
            while True:
                fresh = {uav: a for uav, a in self._actions.items()
                         if uav in active and a.episode == episode and a.step == step}
                waiting = (active & self._live) - fresh.keys()
                remaining = until - time.monotonic()
                if (early and not waiting) or remaining <= 0 or stop.is_set():
                    return fresh
                self._cond.wait(min(remaining, 0.1))


def observation_sent(world: VectorWorld) -> tuple[Observation, np.ndarray]:
    """What every UAV of the world's one environment observes now (``fleet_observation``,
    as the in-process evaluation sees it), and which of those others (J, M) its agent is
    sent: only the ones that can change its decision, so that a step's traffic grows with J,
    not J^2."""
    observation = fleet_observation(world)
    return observation, decision_relevant(observation, world.scenario.policy.observed_uavs,
                                          decision_reach(world.scenario, observation.radius))


class WorldService:
    """The world process's work: step the fleet on its clock, hand each agent its
    observation and reports, take their actions, apply jammer commands between steps, and
    publish the fleet state, events and outcomes."""

    def __init__(self, session: zenoh.Session, topics: Topics, scenario: Scenario,
                 config: WorldConfig, jammers: JammersInForce, log: logging.Logger):
        self.session, self.topics, self.config, self.log = session, topics, config, log
        self.scenario = scenario
        self.world = VectorWorld(scenario, 1, config.uavs, record_measurements=True)
        self.world.set_jammers(slice(None), self._world_jammers(jammers))
        self.dropped = bus.Dropped(log)
        self.mailbox = Mailbox(config.uavs)
        self.desk = JammerDesk(scenario, jammers, self.dropped, topics.jammer_control)
        self.jammer_at = swapping_jammers(scenario, self._world_jammers(jammers),
                                          config.swap_every, config.seed)
        self.flown_s = 0.0  # the run's seconds of flight: the reports' clock
        # Round numbers go on from the wall clock's milliseconds: a restarted world's rounds
        # are then never taken for ones the cloud closed before.
        self.round_base = time.time_ns() // 1_000_000
        self.cloud_waits = 0  # rounds the cloud did not close in time
        self.episode = config.first_episode
        self.next_destinations: np.ndarray  # (uavs, 2): drawn at each episode's start
        self.steps = 0
        self.stepping_seconds = 0.0
        self.missed = 0  # live agent, no action in time
        self.missed_at: dict[int, list[int]] = {}  # this episode's misses: step -> UAVs
        self.unattended = 0  # no live agent for an active UAV
        self.finished = False
        self.observation_pubs = [bus.reliable_publisher(session, topics.observation(uav), True)
                                 for uav in range(config.uavs)]
        self.state_pub = session.declare_publisher(topics.state)  # monitoring: may drop
        # The outcomes are the run's record: a supervisor that missed some gets them again.
        self.outcomes_pub = bus.recoverable_publisher(session, topics.event("uav_outcomes"),
                                                      OUTCOMES_KEPT)
        self.rounds = CloudRounds()
        if config.cloud_clock:
            self.round_pubs = [bus.reliable_publisher(session, topics.measurement_round(uav),
                                                      True) for uav in range(config.uavs)]
            self.opened_pub = bus.reliable_publisher(session, topics.round_opened)
        self._declared = [
            bus.subscribe(session, topics.round_closed, RoundClosed, self.rounds.put,
                          self.dropped),
            bus.subscribe(session, topics.action("*"), Action, self._on_action, self.dropped),
            session.liveliness().declare_subscriber(topics.alive("agent"),
                                                    self.mailbox.on_presence, history=True),
            session.declare_queryable(topics.jammer_control, self.desk.handle),
            session.declare_queryable(topics.join, self._on_join),
            bus.serve_status(session, topics, ROLE, 0, self.status),
            bus.declare_alive(session, topics, ROLE, 0),
        ]

    # -- zenoh threads ---------------------------------------------------------------------
    def _on_action(self, action: Action) -> None:
        if action.uav < self.config.uavs:
            self.mailbox.put_action(action)
        else:
            self.dropped.add(self.topics.action("*"), f"uav {action.uav} is not in this world")

    def _on_join(self, query: zenoh.Query) -> None:
        uav = self.mailbox.hand_out()
        if uav is None:
            bus.refuse(query, f"all {self.config.uavs} UAVs have an agent")
        else:
            query.reply(self.topics.join, encode(JoinReply(uav=uav)))

    def status(self) -> ProcessStatus:
        return ProcessStatus(
            role=ROLE, ident="0", pid=os.getpid(), t=time.time(), episode=self.episode,
            step=int(self.world.steps[0]), dropped=self.dropped.as_dict(),
            details={
                "clock": self.config.clock, "uavs": self.config.uavs,
                "live_agents": len(self.mailbox.live()), "steps": self.steps,
                "steps_per_second": self.steps_per_second(), "missed_deadlines": self.missed,
                "unattended_steps": self.unattended, "finished": self.finished,
                "cloud_clock": self.config.cloud_clock, "cloud_waits": self.cloud_waits,
                "jammer": "; ".join(
                    f"{jammer.id}: {jammer.x:g},{jammer.y:g},{jammer.power_w:g},"
                    f"{jammer.height_m:g}{'' if jammer.path is None else ' moving'}"
                    for jammer in self.desk.current()) or "off",
            },
        )

    def steps_per_second(self) -> float:
        return self.steps / self.stepping_seconds if self.stepping_seconds > 0 else 0.0

    # -- main loop -------------------------------------------------------------------------
    def run(self, stop: threading.Event) -> None:
        config = self.config
        if not self.mailbox.wait_all_live(time.monotonic() + config.start_timeout, stop):
            if stop.is_set():
                return
            self.log.warning("starting with %d of %d agents", len(self.mailbox.live()),
                             config.uavs)
        began = time.monotonic()
        last = None if config.episodes is None else config.first_episode + config.episodes
        out_of_time = (lambda: False) if config.duration is None else (
            lambda: time.monotonic() - began >= config.duration)
        while not stop.is_set() and self.episode != last and not out_of_time():
            if self._fly_episode(stop, out_of_time):
                self.episode += 1
        self._log_misses()  # of an episode cut short
        self.finished = True
        self._publish_event(RunFinished(
            t=time.time(), source=ROLE, episodes=self.episode - config.first_episode,
            steps=self.steps, seconds=self.stepping_seconds,
            steps_per_second=self.steps_per_second(), missed_deadlines=self.missed))
        self.log.info("run finished: %d episodes, %.0f steps/s, %d missed deadlines",
                      self.episode - config.first_episode, self.steps_per_second(), self.missed)
        stop.wait()  # stay up (status, control) until told to stop

    def _fly_episode(self, stop: threading.Event, out_of_time) -> bool:
        """One episode; True when it ran to its end."""
        world, config = self.world, self.config
        seed = episode_seed(config.seed, self.episode)
        if config.swap_every is not None and self.episode % config.swap_every == 0:
            self.desk.schedule(self._scheduled_jammers())
            self._apply_jammer()  # before the reset, which reads the jammer's levels
        world.reset([0], [seed])
        # Each UAV's next mission, announced with this one's observations so that its agent
        # prepares the route before it needs it (missions are drawn from the episode's own
        # seed, so drawing them early changes nothing).
        _, self.next_destinations = world.sampler.sample(
            episode_seed(config.seed, self.episode + 1), world.num_uavs)
        period = 1.0 / config.rate
        tick = time.monotonic()  # realtime: when the current step ends
        while True:
            started = time.monotonic()
            self._apply_jammer()
            step = int(world.steps[0])
            self.desk.episode, self.desk.step = self.episode, step
            active = set(np.flatnonzero(world.active[0]).tolist())
            self._publish_step(active)
            if config.clock == "lockstep" or not self.steps:
                # An agent's first decision builds its map's route grid: with many agents on
                # few cores that takes longer than a step, so the run's first step waits, on
                # either clock, as long as its start did.
                wait = config.deadline if self.steps else config.start_timeout
                until, early = started + wait, True
            else:
                tick = max(tick, started) + period  # late: start a new schedule, never rush
                until, early = tick, False
            actions = self.mailbox.collect(self.episode, step, active, until, stop, early)
            if stop.is_set():
                return False
            result = world.step(*self._commands(actions, active))
            self.steps += 1
            self.flown_s += world.dt
            if config.cloud_clock and not self._cloud_round(stop):
                return False
            self.stepping_seconds += time.monotonic() - started
            if result.env_done[0]:
                self._log_misses()
                self._publish_state()
                self.outcomes_pub.put(encode(UavOutcomes(
                    t=time.time(), source=ROLE, episode=self.episode, seed=seed,
                    steps=int(world.steps[0]), outcomes=outcome_labels(world.status[0]))))
                return True
            if out_of_time():
                return False

    def _log_misses(self) -> None:
        """Name the steps of the episode just flown whose actions some live agent did not
        send in time, and those agents' UAVs: when and where a run missed deadlines."""
        if self.missed_at:
            missed = sum(map(len, self.missed_at.values()))
            self.log.warning("episode %d: %d missed deadline%s, at step%s %s", self.episode,
                             missed, "s" * (missed > 1), "s" * (len(self.missed_at) > 1),
                             _misses(self.missed_at))
        self.missed_at = {}

    def _scheduled_jammers(self) -> JammersInForce:
        """The jammers the run's schedule sets for this episode, the first of a period."""
        if self.episode < self.config.swap_every:  # the run's own, until the first swap
            return self.desk.current()
        return tuple(JammerInfo.of(jammer, index)
                     for index, jammer in enumerate(self.jammer_at(self.episode)))

    def _world_jammers(self, jammers: JammersInForce) -> tuple[Jammer, ...]:
        return tuple(jammer.as_jammer(self.scenario) for jammer in jammers)

    def _cloud_round(self, stop: threading.Event) -> bool:
        """Hand each UAV's agent what its receiver reported along the step just flown, and
        wait until the cloud has taken them (False: stopped meanwhile)."""
        w, number = self.world, self.round_base + self.steps
        measured = np.flatnonzero(w.measured[0]).tolist()
        if not measured:
            return True
        for uav in measured:
            reports, reports_db = self._reports(uav)
            self.round_pubs[uav].put(encode(MeasurementRound(
                round=number, episode=self.episode, step=int(w.steps[0]), uav=uav,
                flown_s=self.flown_s, measured=reports, measured_db=reports_db)))
        live = self.mailbox.live()
        self.opened_pub.put(encode(RoundOpened(round=number, flown_s=self.flown_s,
                                               uavs=[uav for uav in measured if uav in live])))
        if not self.rounds.wait(number, time.monotonic() + self.config.cloud_deadline, stop):
            if stop.is_set():
                return False
            self.cloud_waits += 1
            self.log.warning("round %d: the cloud did not close it in %.0f s", number,
                             self.config.cloud_deadline)
        return True

    def _apply_jammer(self) -> None:
        for jammers in self.desk.take():
            self.world.set_jammers(slice(None), self._world_jammers(jammers))
            self._publish_event(JammerChanged(
                t=time.time(), source=ROLE, jammers=list(jammers), episode=self.episode,
                step=int(self.world.steps[0])))
            self.log.info(describe_jammers(jammers))

    def _publish_step(self, active: set[int]) -> None:
        w = self.world
        # A joined agent subscribed before declaring its token; make sure that subscription
        # is known here, or its first observation could be lost.
        joined = sorted(uav for uav in self.mailbox.take_joined() if uav < self.config.uavs)
        matched = bus.wait_matching([self.observation_pubs[uav] for uav in joined], 2.0)
        for uav in (uav for uav, known in zip(joined, matched, strict=True) if not known):
            self.log.warning("agent %d is live but not subscribed", uav)
        observation, relevant = observation_sent(w)
        flown = self.rounds.flown_at(self.round_base + self.steps)
        for uav in sorted(active):
            reports, reports_db = ([], []) if self.config.cloud_clock else self._reports(uav)
            self.observation_pubs[uav].put(encode(AgentObservation.of_row(
                observation, uav, self.episode, uav, reports, reports_db, relevant[uav],
                self.next_destinations[uav], flown)))
        self._publish_state()

    def _reports(self, uav: int) -> tuple[list[tuple[float, float, int]], list[float]]:
        """What UAV ``uav``'s receiver reported along its last step (none at a start): each
        report's place and level, and their SINRs where the receiver reports them."""
        w = self.world
        if not w.measured[0, uav]:
            return [], []
        reports = [(x, y, level) for (x, y), level in zip(
            w.measured_xy[0, uav].tolist(), w.measured_level[0, uav].tolist(), strict=True)]
        reported_db = w.measured_sinr_db[0, uav]
        return reports, ([] if np.isnan(reported_db).all() else reported_db.tolist())

    def _publish_event(self, event) -> None:
        bus.publish_event(self.session, self.topics, event)

    def _publish_state(self) -> None:
        w = self.world
        self.state_pub.put(encode(WorldState.model_construct(
            episode=self.episode, step=int(w.steps[0]), clock=self.config.clock, t=time.time(),
            position=[tuple(p) for p in w.position[0].tolist()],
            velocity=[tuple(v) for v in w.velocity[0].tolist()],
            sinr_db=w.sinr_db[0].tolist(), level=w.level[0].tolist(),
            status=outcome_labels(w.status[0]),
            destination=[tuple(d) for d in w.destination[0].tolist()],
            jammers_in_force=list(self.desk.in_force()), jammer_places=self._jammer_places(),
            jammer_known=True)))

    def _jammer_places(self) -> list[JammerPlace]:
        """Where each jammer in force is now, and whether it transmits (slots as listed)."""
        w = self.world
        return [JammerPlace(id=jammer.id, x=float(w.jammer_x[0, slot]),
                            y=float(w.jammer_y[0, slot]), on=bool(w.jammer_power[0, slot] > 0))
                for slot, jammer in enumerate(self.desk.in_force())]

    def _commands(self, actions: dict[int, Action], active: set[int]
                  ) -> tuple[np.ndarray, np.ndarray]:
        """Commanded speed and heading (1, J): the agents' actions, else the last velocity."""
        w = self.world
        speed = np.hypot(w.velocity[..., 0], w.velocity[..., 1])
        heading = w.heading.copy()
        live = self.mailbox.live()
        for uav in active:
            action = actions.get(uav)
            if action is None:
                if uav in live:
                    self.missed += 1
                    self.missed_at.setdefault(int(w.steps[0]), []).append(uav)
                else:
                    self.unattended += 1
                continue
            speed[0, uav], heading[0, uav] = action.speed, action.heading
        return speed, heading


def _misses(missed_at: dict[int, list[int]]) -> str:
    """The first MISSES_NAMED steps with a miss, and whose: ``3 (UAVs 0, 2); 7 (UAV 1)``."""
    steps = sorted(missed_at)
    named = "; ".join(f"{step} (UAV{'s' if len(missed_at[step]) > 1 else ''} "
                      f"{', '.join(map(str, sorted(missed_at[step])))})"
                      for step in steps[:MISSES_NAMED])
    more = len(steps) - MISSES_NAMED
    return named + (f" and {more} more" if more > 0 else "")


# -- process shell ------------------------------------------------------------------------------
def build_parser() -> argparse.ArgumentParser:
    parser = ArgumentParser(prog="python -m world_sim.process", description=__doc__)
    add_bus_arguments(parser)
    parser.add_argument("--scenario", default=None)
    parser.add_argument("--uavs", type=int, default=None)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--episodes", type=int, default=None)
    parser.add_argument("--duration", type=float, default=None, metavar="SEC")
    parser.add_argument("--first-episode", type=int, default=0)
    parser.add_argument("--clock", choices=("lockstep", "realtime"), default="lockstep")
    parser.add_argument("--rate", type=float, default=10.0, help="realtime steps per second")
    parser.add_argument("--deadline", type=float, default=2.0, help="lockstep seconds")
    parser.add_argument("--start-timeout", type=float, default=60.0)
    parser.add_argument("--cloud-clock", action="store_true",
                        help="lockstep with the online map: each step waits for the cloud to "
                             "take its reports (the cloud runs --clock lockstep)")
    parser.add_argument("--swap-every", type=int, default=None, metavar="K",
                        help="move the jammer to a fresh random setting every K episodes")
    jam = parser.add_mutually_exclusive_group()
    jam.add_argument("--jammer", metavar="X,Y,P[,H]")
    jam.add_argument("--jammers", metavar="JSON",
                     help="the jammers in force, as messages carry them (a restarted world)")
    jam.add_argument("--no-jammer", action="store_true")
    return parser


def world_setup(args: argparse.Namespace) -> bus.ServiceSetup:
    """The world the arguments ask for; a ValueError names the first wrong one, and a
    CompiledCoreError a radio core that cannot run."""
    radio_core()
    scenario = load_scenario(args.scenario)
    uavs = scenario.missions.uav_count if args.uavs is None else args.uavs
    if not 1 <= uavs <= MAX_UAVS:
        raise ValueError(f"--uavs must be between 1 and {MAX_UAVS}")
    if args.cloud_clock and args.clock != "lockstep":
        raise ValueError("--cloud-clock needs --clock lockstep")
    for name in ("episodes", "duration", "rate", "deadline", "swap_every"):
        value = getattr(args, name)
        if value is not None and not value > 0:
            raise ValueError(f"--{name} must be positive")
    jammers = initial_jammers(scenario, args.jammer, args.jammers, args.no_jammer)
    config = WorldConfig(uavs=uavs, seed=args.seed, episodes=args.episodes,
                         duration=args.duration, first_episode=args.first_episode,
                         clock=args.clock, rate=args.rate, deadline=args.deadline,
                         start_timeout=args.start_timeout, cloud_clock=args.cloud_clock,
                         swap_every=args.swap_every)
    topics = Topics(args.prefix)

    def run(session: zenoh.Session, stop: threading.Event, log: logging.Logger) -> int:
        WorldService(session, topics, scenario, config, jammers, log).run(stop)
        return 0

    return bus.ServiceSetup(endpoint_from(args.endpoint),
                            access.login_for(args.credentials, access.WORLD), run)


def main(argv: list[str] | None = None) -> int:
    return bus.run_service(ROLE, build_parser(), world_setup, argv)


if __name__ == "__main__":
    sys.exit(main())

"""The world's traffic of each step: what a UAV observes and the action it sends back, the
reports of a round and the rounds the world opens and the cloud closes (the cloud on the
lockstep clock), the fleet state it publishes, and the UAV it hands an agent that joins."""

from __future__ import annotations

from typing import Any, ClassVar, Literal

import numpy as np
from pydantic import Field, model_validator

from shared.jammer_messages import JammerInfo, JammerPlace, recorded_one_jammer
from shared.observation import Observation
from shared.scenario import MAX_JAMMERS, MAX_UAVS
from shared.wire import (
    XY,
    Coordinate,
    Count,
    Finite,
    Level,
    Message,
    NonNegative,
    Physical,
    Place,
    ReportedDb,
    UavId,
)

MAX_REPORTS = 100  # the scenario's own limit on uav.measurements_per_step
StatusLabel = Literal["active", "success", "disconnection", "collision", "timeout"]
Clock = Literal["lockstep", "realtime"]


class AgentObservation(Message):
    """What UAV ``uav`` observes at a step: its own state and mission, and the others'
    position, velocity and size (never their destinations). One row of ``Observation``."""

    episode: Count
    step: Count
    uav: UavId
    position: Place
    velocity: Place
    heading: Coordinate
    destination: Place
    radius: Physical
    max_speed: Physical
    level: Level
    below_steps: Count
    others_position: list[Place] = Field(max_length=MAX_UAVS - 1)
    others_velocity: list[Place] = Field(max_length=MAX_UAVS - 1)
    others_radius: list[Physical] = Field(max_length=MAX_UAVS - 1)
    others_present: list[bool] = Field(max_length=MAX_UAVS - 1)
    # What the UAV's receiver reported along the step that brought it here, (x, y, level) in
    # the order taken, the last at ``position`` (scenario uav.measurements_per_step points;
    # none at an episode's start). The world simulates the receiver, noise included.
    measured: list[tuple[Coordinate, Coordinate, Level]] = Field(default_factory=list,
                                                                 max_length=MAX_REPORTS)
    # The SINR of each of those reports (dB, in its report steps) where the scenario's
    # receivers report it (uav.report = "db"); empty where they report levels only.
    measured_db: list[ReportedDb] = Field(default_factory=list, max_length=MAX_REPORTS)
    # Where the UAV flies once this mission ends (the next in its mission queue; none when
    # the world has not planned one), so that its agent prepares that route between decisions.
    next_destination: Place | None = None
    # The SINR map version to decide on, when the cloud is on the lockstep clock (RoundClosed):
    # the one in service at this step, not the newest the agent holds. None: the newest.
    sinr_version: Count | None = None

    @model_validator(mode="after")
    def _same_length(self) -> AgentObservation:
        lengths = {len(self.others_position), len(self.others_velocity),
                   len(self.others_radius), len(self.others_present)}
        if len(lengths) != 1:
            raise ValueError("others_* lists differ in length")
        _check_reported_db(self.measured, self.measured_db)
        return self

    @classmethod
    def of_row(cls, observation: Observation, row: int, episode: int, uav: int,
               measured: list[tuple[float, float, int]] = (),
               measured_db: list[float] = (),
               others: np.ndarray | None = None,
               next_destination: np.ndarray | None = None,
               sinr_version: int | None = None) -> AgentObservation:
        """Row ``row`` of ``observation``, with only the others the mask ``others`` (M,)
        keeps (``shared.observation.decision_relevant``), in their order; all without it."""
        o = observation
        keep = slice(None) if others is None else others
        return cls.model_construct(
            episode=episode, step=int(o.step[row]), uav=uav,
            position=tuple(o.position[row].tolist()), velocity=tuple(o.velocity[row].tolist()),
            heading=float(o.heading[row]), destination=tuple(o.destination[row].tolist()),
            radius=float(o.radius[row]), max_speed=float(o.max_speed[row]),
            level=int(o.level[row]), below_steps=int(o.below_steps[row]),
            others_position=[tuple(p) for p in o.others_position[row][keep].tolist()],
            others_velocity=[tuple(v) for v in o.others_velocity[row][keep].tolist()],
            others_radius=o.others_radius[row][keep].tolist(),
            others_present=o.others_present[row][keep].tolist(),
            measured=list(measured), measured_db=list(measured_db),
            next_destination=(None if next_destination is None
                              else tuple(np.asarray(next_destination, dtype=float).tolist())),
            sinr_version=sinr_version,
        )

    def observation(self) -> Observation:
        """The one-row ``Observation`` the policy reads, with the world's dtypes, so that the
        agent computes exactly what an in-process evaluation computes for this UAV."""
        others = len(self.others_present)
        return Observation(
            position=np.array([self.position], dtype=np.float64),
            velocity=np.array([self.velocity], dtype=np.float64),
            heading=np.array([self.heading], dtype=np.float64),
            destination=np.array([self.destination], dtype=np.float64),
            radius=np.array([self.radius], dtype=np.float64),
            max_speed=np.array([self.max_speed], dtype=np.float64),
            level=np.array([self.level], dtype=np.int8),
            below_steps=np.array([self.below_steps], dtype=np.int64),
            step=np.array([self.step], dtype=np.int64),
            others_position=np.array(self.others_position, dtype=np.float64).reshape(1, others, 2),
            others_velocity=np.array(self.others_velocity, dtype=np.float64).reshape(1, others, 2),
            others_radius=np.array(self.others_radius, dtype=np.float64).reshape(1, others),
            others_present=np.array(self.others_present, dtype=bool).reshape(1, others),
        )



# -- the cloud on the lockstep clock ------------------------------------------------------------
# With the online map in lockstep, every world step is a round: the world hands each UAV's
# agent what its receiver reported along the step (MeasurementRound) and tells the cloud whose
# uploads to expect (RoundOpened); the agents upload at once, tagged with the round; the cloud
# takes the round's uploads as one batch, in UAV order, finishes what they trigger and answers
# with the map in service and the rounds from which the ones published fly (RoundClosed). The
# world goes on only then, and names the map in service in each observation: a seed gives the
# maps, steps and outcomes of ``jamnav eval --method proposed``.
class MeasurementRound(Message):
    """What UAV ``uav``'s receiver reported along the world step of ``round`` (one a step,
    numbered on from the world's start time in milliseconds), for its agent to upload at
    once."""

    round: Count
    episode: Count
    step: Count  # the UAV's step in its episode after that flight: the measurements' step
    uav: UavId
    flown_s: Finite  # seconds of flight of the run at the end of that step: the reports' clock
    measured: list[tuple[Coordinate, Coordinate, Level]] = Field(max_length=MAX_REPORTS)
    measured_db: list[ReportedDb] = Field(default_factory=list, max_length=MAX_REPORTS)

    @model_validator(mode="after")
    def _one_sinr_a_report(self) -> MeasurementRound:
        _check_reported_db(self.measured, self.measured_db)
        return self


def _check_reported_db(measured: list, measured_db: list) -> None:
    """Reports carry an SINR each, or none does."""
    if measured_db and len(measured_db) != len(measured):
        raise ValueError(f"measured_db: {len(measured_db)} SINRs for {len(measured)} reports")


class RoundOpened(Message):
    """The world to the cloud: the agents of ``uavs`` upload their reports of ``round``."""

    round: Count
    flown_s: Finite
    uavs: list[UavId] = Field(max_length=MAX_UAVS)


class RoundClosed(Message):
    """The cloud to the world: ``round``'s uploads are stored and what they triggered is done.
    ``serving`` is the map version the decisions after it fly; ``pending`` the versions
    published and not in service yet, each with the round whose decisions first fly it."""

    round: Count
    serving: Count
    pending: list[tuple[Count, Count]] = Field(default_factory=list, max_length=1024)



class Action(Message):
    """A UAV's command for one step (clipped by the world to the kinematic limits)."""

    episode: Count
    step: Count
    uav: UavId
    speed: NonNegative
    heading: Finite


class WorldState(Message):
    """The whole fleet after a step, for monitoring: every list is in UAV order."""

    # At most 81 bytes a UAV in msgpack (three places, an SINR, a level, the longest status):
    # 83 kB for MAX_UAVS = 1,024, past the default cap.
    max_bytes: ClassVar[int] = 4096 + 96 * MAX_UAVS
    episode: Count
    step: Count
    clock: Clock
    t: Finite  # unix seconds
    position: list[XY] = Field(max_length=MAX_UAVS)
    velocity: list[XY] = Field(max_length=MAX_UAVS)
    sinr_db: list[Finite] = Field(max_length=MAX_UAVS)
    level: list[Level] = Field(max_length=MAX_UAVS)
    status: list[StatusLabel] = Field(max_length=MAX_UAVS)
    # Where each UAV is headed this episode (empty from a world that does not say).
    destination: list[XY] = Field(default_factory=list, max_length=MAX_UAVS)
    # The jammers in force after the step, so that a console that joins late, or a replay of
    # a recording begun mid-run, knows them from any state, and where each is then (a jammer
    # on a path moves, a scheduled one switches). ``jammer_known`` is False from a world that
    # does not say (recordings made before it did).
    jammers_in_force: list[JammerInfo] = Field(default_factory=list, max_length=MAX_JAMMERS)
    jammer_places: list[JammerPlace] = Field(default_factory=list, max_length=MAX_JAMMERS)
    jammer_known: bool = False

    @model_validator(mode="before")
    @classmethod
    def _one_jammer_recorded(cls, data: Any) -> Any:
        return recorded_one_jammer(data, "jammer_in_force", "jammers_in_force")


class JoinReply(Message):
    """The world's answer to an agent asking which UAV to fly (agents started as replicas)."""

    uav: UavId

"""Every message on the bus: pydantic models, msgpack on the wire, validated on receipt.

``encode``, ``decode`` and ``decode_event`` are the only way in and out of the wire format.
Decoding refuses, with a one-line ``MessageError``, anything oversized, not msgpack, or outside
the model's rules (unknown fields, non-finite numbers, out-of-range values, inconsistent
lengths, a weights payload whose sha256 does not match). msgpack carries plain data only:
nothing received is ever turned into code or arbitrary objects (no pickle; msgpack extension
types are refused by the models).

The topic each message travels on is in ``shared.topics``; ``docs/topics.md`` lists both.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Iterable
from typing import Annotated, Any, ClassVar, Literal, TypeVar

import msgpack
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, ValidationError, model_validator

from shared.measurements import MAX_REPORTED_DB, MEASUREMENT_FIELDS, Measurement
from shared.observation import Observation
from shared.outcomes import Outcome
from shared.radio import JammerParams
from shared.scenario import (
    MAX_JAMMER_HEIGHT_M,
    MAX_JAMMER_POWER_W,
    MAX_UAVS,
    JammerHeight,
    JammerPower,
)

MAX_WEIGHTS_BYTES = 8 * 2**20
MAX_REPORTS = 100  # the scenario's own limit on uav.measurements_per_step

Finite = Annotated[float, Field(allow_inf_nan=False)]
NonNegative = Annotated[float, Field(ge=0, allow_inf_nan=False)]
Positive = Annotated[float, Field(gt=0, allow_inf_nan=False)]
Count = Annotated[int, Field(ge=0, le=2**62)]
UavId = Annotated[int, Field(ge=0, lt=MAX_UAVS)]
Level = Annotated[int, Field(ge=0, le=127)]
XY = tuple[Finite, Finite]
# What a UAV's own state may hold: far beyond any area and airframe, but small enough that the
# features and the lookahead computed from it stay finite.
Coordinate = Annotated[float, Field(ge=-1e6, le=1e6, allow_inf_nan=False)]
ReportedDb = Annotated[float, Field(ge=-MAX_REPORTED_DB, le=MAX_REPORTED_DB, allow_inf_nan=False)]
Place = tuple[Coordinate, Coordinate]
Physical = Annotated[float, Field(gt=0, le=1e3, allow_inf_nan=False)]
Text = Annotated[str, Field(min_length=1, max_length=200)]
Digest = Annotated[str, Field(pattern=r"^[0-9a-f]{64}$")]
Accuracy = Annotated[float, Field(ge=0, le=1, allow_inf_nan=False)]
StatusLabel = Literal["active", "success", "disconnection", "collision", "timeout"]
OutcomeLabel = Literal["success", "disconnection", "collision", "timeout"]
Role = Literal["world", "cloud", "agent"]  # the processes that answer status queries
Clock = Literal["lockstep", "realtime"]
MapMode = Literal["online", "perfect", "outdated"]


class MessageError(ValueError):
    """A payload that is not a valid message; the text is one line."""


class Message(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)
    max_bytes: ClassVar[int] = 64 * 1024


M = TypeVar("M", bound=Message)


# -- world <-> agents ---------------------------------------------------------------------------
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
    # The jammer in force after the step (None: none), so that a console that joins late, or
    # a replay of a recording begun mid-run, knows it from any state. ``jammer_known`` is
    # False from a world that does not say (recordings made before it did).
    jammer_in_force: JammerInfo | None = None
    jammer_known: bool = False


# -- measurements and weights -------------------------------------------------------------------
MAX_UPLOAD = 256  # measurements per upload


class MeasurementUpload(Message):
    """A batch of one UAV's measurements, sent as a query: the cloud answers once it has
    stored them, and the agent keeps them until then (the cloud screens each record)."""

    max_bytes: ClassVar[int] = 512 * 1024
    uav: UavId
    measurements: list[Measurement] = Field(max_length=MAX_UPLOAD)
    # A round's upload (the cloud on the lockstep clock), which may hold nothing: the cloud
    # waits for one from every agent the round names.
    round: Count | None = None

    @model_validator(mode="after")
    def _something_or_a_round(self) -> MeasurementUpload:
        if not self.measurements and self.round is None:
            raise ValueError("measurements: an upload outside a round holds at least one")
        return self


class UploadReceipt(Message):
    """The cloud's answer to an upload, once it is in the replay memory: records stored now,
    records it already held (a repeat after a lost receipt) and records it refused."""

    stored: Count
    duplicates: Count
    refused: Count


class RasterGrid(Message):
    """Where an int8 level raster lies: node (0, 0) at (x0, y0), rows along y."""

    x0: Finite
    y0: Finite
    spacing: Positive
    rows: int = Field(ge=2, le=4096)
    cols: int = Field(ge=2, le=4096)


class _Weights(Message):
    max_bytes: ClassVar[int] = MAX_WEIGHTS_BYTES + 4096
    version: Count
    sha256: Digest
    data: bytes = Field(min_length=1, max_length=MAX_WEIGHTS_BYTES)

    @model_validator(mode="after")
    def _digest(self):
        if hashlib.sha256(self.data).hexdigest() != self.sha256:
            raise ValueError("sha256 digest does not match the data")
        return self


class ValueWeights(_Weights):
    """The value network as safetensors bytes (architecture in the header metadata)."""


class SinrMap(_Weights):
    """A version of the SINR map: with ``grid`` unset, ``data`` is the SINR-mapping network as
    safetensors (``online``); with ``grid`` set, it is an int8 level raster, row-major
    (the true map for ``perfect``, the no-jammer map for ``outdated``)."""

    mode: MapMode
    accuracy: Accuracy | None = None
    grid: RasterGrid | None = None

    @model_validator(mode="after")
    def _raster_size(self) -> SinrMap:
        if self.grid is not None and len(self.data) != self.grid.rows * self.grid.cols:
            raise ValueError("raster data length differs from rows x cols")
        return self

    def levels(self) -> np.ndarray:
        grid = self.grid
        return np.frombuffer(self.data, dtype=np.int8).reshape(grid.rows, grid.cols)


# -- jammer control -----------------------------------------------------------------------------
# What every jammer a command or message sets must be (JammerPower, JammerHeight).
JAMMER_LIMITS = (f"position, power and height must be finite, power and height >= 0, power at "
                 f"most {MAX_JAMMER_POWER_W:g} W and height at most {MAX_JAMMER_HEIGHT_M:g} m")


class JammerInfo(Message):
    x: Finite
    y: Finite
    power_w: JammerPower
    height_m: JammerHeight

    @classmethod
    def parse(cls, text: str, default_height: float) -> JammerInfo:
        """From "X,Y,P" or "X,Y,P,H" (metres, watts); ValueError with a one-line reason."""
        x, y, power, height = jammer_numbers(text)
        try:
            return cls(x=x, y=y, power_w=power,
                       height_m=default_height if height is None else height)
        except ValidationError:
            raise ValueError(f"jammer {text!r}: {JAMMER_LIMITS}") from None

    @staticmethod
    def params(jammer: JammerInfo | None) -> JammerParams | None:
        """The radio model's jammer (None: no jammer)."""
        if jammer is None:
            return None
        return JammerParams(jammer.x, jammer.y, jammer.power_w, jammer.height_m)


def jammer_numbers(text: str) -> tuple[float, float, float, float | None]:
    """"X,Y,P" or "X,Y,P,H" as numbers (H None when left out): the one jammer syntax of every
    command. ValueError with a one-line reason."""
    parts = text.split(",")
    if len(parts) not in (3, 4):
        raise ValueError(f"jammer {text!r}: expected X,Y,P or X,Y,P,H")
    try:
        values = [float(part) for part in parts]
    except ValueError:
        raise ValueError(f"jammer {text!r}: expected numbers, e.g. -25,15,1") from None
    return values[0], values[1], values[2], (values[3] if len(values) == 4 else None)


class JammerCommand(Message):
    """Payload of a query on the control key; no payload means ``show``."""

    action: Literal["set", "off", "show"]
    x: Finite | None = None
    y: Finite | None = None
    power_w: JammerPower | None = None
    height_m: JammerHeight | None = None

    @model_validator(mode="after")
    def _complete(self) -> JammerCommand:
        given = [v is not None for v in (self.x, self.y, self.power_w, self.height_m)]
        if self.action == "set" and not all(given[:3]):
            raise ValueError("set needs x, y and power_w")
        if self.action != "set" and any(given):
            raise ValueError(f"{self.action} takes no position or power")
        return self


class JoinReply(Message):
    """The world's answer to an agent asking which UAV to fly (agents started as replicas)."""

    uav: UavId


class JammerReply(Message):
    accepted: bool
    reason: str | None = Field(default=None, max_length=500)
    jammer: JammerInfo | None  # in force from the next step (None: no jammer)
    episode: Count
    step: Count


# -- cloud -> everyone ---------------------------------------------------------------------------
class JammerEstimate(Message):
    """The cloud's estimate of the jammer after a detected change, from the uploads alone.

    ``map_version`` is the SINR map corrected with it (published at the same time). With
    ``present`` false the uploads are best explained by no jammer at all, and the position and
    power fields are None. Standard deviations come from the fit's likelihood.
    """

    map_version: Count
    t: Finite  # unix seconds (simulated seconds in-process)
    present: bool
    x: Finite | None = None
    y: Finite | None = None
    power_w: NonNegative | None = None  # nominal, as `jamnav jammer set` takes it
    effective_power_dbm: Finite | None = None  # what reaches the receiver in band
    sd_x_m: NonNegative | None = None
    sd_y_m: NonNegative | None = None
    sd_power_db: NonNegative | None = None
    measurements: Count  # post-change uploads it was fitted to
    change_time: Finite | None = None  # the detector's estimate of when the change happened

    @model_validator(mode="after")
    def _located(self) -> JammerEstimate:
        located = (self.x, self.y, self.power_w)
        if self.present and None in located:
            raise ValueError("a present jammer needs x, y and power_w")
        if not self.present and any(v is not None for v in located):
            raise ValueError("an absent jammer has no x, y or power_w")
        return self


# -- events -------------------------------------------------------------------------------------
class _Event(Message):
    t: Finite  # unix seconds
    source: Text


class JammerChanged(_Event):
    type: Literal["jammer_changed"] = "jammer_changed"
    jammer: JammerInfo | None
    episode: Count
    step: Count


class ChangeDetected(_Event):
    type: Literal["change_detected"] = "change_detected"
    version: Count  # the map version found outdated
    accuracy: Accuracy  # of that map on the window that fired
    change_time: Finite | None = None  # the detector's estimate of when the change happened


class SinrWeightsPublished(_Event):
    type: Literal["sinr_weights_published"] = "sinr_weights_published"
    version: Count
    accuracy: Accuracy | None
    sha256: Digest
    path: str = Field(max_length=4096)  # the safetensors file of this version (cloud's disk)
    # Corrected by where the jammer may be while its estimate has not converged yet.
    provisional: bool = False


class JammerEstimated(_Event):
    type: Literal["jammer_estimated"] = "jammer_estimated"
    estimate: JammerEstimate


class RetrainFailed(_Event):
    type: Literal["retrain_failed"] = "retrain_failed"
    version: Count
    error: str = Field(max_length=2000)


class WeightsRefused(_Event):
    """An agent refused a weights payload and flies on with its previous version."""

    type: Literal["weights_refused"] = "weights_refused"
    uav: UavId
    weights: Literal["value", "sinr_map"]
    version: Count | None  # None: the payload was not even a readable message
    reason: str = Field(max_length=500)
    flying_on: Count | None  # the version still in use


class UavOutcomes(_Event):
    type: Literal["uav_outcomes"] = "uav_outcomes"
    episode: Count
    seed: Count
    steps: Count
    outcomes: list[OutcomeLabel] = Field(min_length=1, max_length=MAX_UAVS)


class RunFinished(_Event):
    type: Literal["run_finished"] = "run_finished"
    episodes: Count
    steps: Count
    seconds: NonNegative
    steps_per_second: NonNegative
    missed_deadlines: Count


Event = Annotated[
    JammerChanged | ChangeDetected | JammerEstimated | SinrWeightsPublished | RetrainFailed
    | WeightsRefused
    | UavOutcomes | RunFinished,
    Field(discriminator="type"),
]
_EVENTS: TypeAdapter[Event] = TypeAdapter(Event)


# -- status -------------------------------------------------------------------------------------
Scalar = int | float | str | bool | None


class ProcessStatus(Message):
    """A process's answer to a status query."""

    role: Role
    ident: Text
    pid: int = Field(ge=0)
    t: Finite
    episode: Count | None = None
    step: Count | None = None
    value_version: Count | None = None
    sinr_version: Count | None = None
    dropped: dict[str, Count] = Field(default_factory=dict, max_length=64)
    details: dict[str, Scalar] = Field(default_factory=dict, max_length=64)


def describe_estimate(estimate: JammerEstimate) -> str:
    """One line for people: where the jammer is thought to be, and how sure the fit is."""
    if not estimate.present:
        return f"no jammer ({estimate.measurements} measurements)"
    return (f"({estimate.x:.1f} +- {estimate.sd_x_m:.1f}, {estimate.y:.1f} +- "
            f"{estimate.sd_y_m:.1f}) m, {estimate.power_w:.2f} W +- {estimate.sd_power_db:.1f} dB "
            f"({estimate.measurements} measurements)")


def mapper_summary(cloud: ProcessStatus | None) -> str:
    """The online mapper's state from the cloud's status: map version, accuracy on recent
    uploads, and what it does about a change (with the measurements gathered since)."""
    if cloud is None or "map_phase" not in cloud.details:
        return "map ?"
    d = cloud.details
    recent = d.get("recent_accuracy")
    text = f"map v{cloud.sinr_version}" + (
        " (provisional)" if d.get("map_provisional") else "") + (
        f" {recent:.0%} on recent" if isinstance(recent, float) else "")
    if d["map_phase"] != "watching":
        text += f", {d['map_phase']} ({d.get('since_change')} since change)"
    return text


# -- the wire -----------------------------------------------------------------------------------
def encode(message: Message) -> bytes:
    return msgpack.packb(message.model_dump(mode="python"), use_bin_type=True)


def encode_upload(uav: int, records: Iterable[tuple], round: int | None = None) -> bytes:
    """``encode`` of a ``MeasurementUpload`` of ``records``, each a tuple of a ``Measurement``'s
    field values in ``MEASUREMENT_FIELDS`` order, without a model per record: an agent uploads
    the records it made itself, and the cloud validates each one on receipt."""
    measurements = [dict(zip(MEASUREMENT_FIELDS, record, strict=True)) for record in records]
    return msgpack.packb({"uav": uav, "measurements": measurements, "round": round},
                         use_bin_type=True)


def _unpack(payload: bytes, max_bytes: int) -> Any:
    if len(payload) > max_bytes:
        raise MessageError(f"payload of {len(payload)} bytes exceeds {max_bytes}")
    try:
        return msgpack.unpackb(payload, raw=False, strict_map_key=True)
    except (ValueError, TypeError, msgpack.ExtraData, msgpack.FormatError,
            msgpack.StackError) as exc:
        raise MessageError(f"not msgpack ({type(exc).__name__}: {exc})") from None


def _one_line(exc: ValidationError) -> str:
    first = exc.errors()[0]
    where = ".".join(str(part) for part in first["loc"]) or "(message)"
    more = f" (and {exc.error_count() - 1} more)" if exc.error_count() > 1 else ""
    return f"{where}: {first['msg']}{more}"


def decode(kind: type[M], payload: bytes) -> M:
    """The message of type ``kind`` in ``payload``, validated; MessageError otherwise."""
    data = _unpack(bytes(payload), kind.max_bytes)
    if not isinstance(data, dict):
        raise MessageError(f"{kind.__name__}: expected a map, got {type(data).__name__}")
    try:
        return kind.model_validate(data)
    except ValidationError as exc:
        raise MessageError(f"{kind.__name__}: {_one_line(exc)}") from None


def decode_event(payload: bytes) -> Event:
    data = _unpack(bytes(payload), Message.max_bytes)
    try:
        return _EVENTS.validate_python(data)
    except ValidationError as exc:
        raise MessageError(f"event: {_one_line(exc)}") from None


def outcome_labels(codes) -> list[str]:
    return [Outcome(int(code)).label for code in codes]


# -- zenoh-cli codec (entry points in pyproject.toml) ------------------------------------------
def _printable(value: Any) -> Any:
    if isinstance(value, bytes):
        return f"<{len(value)} bytes>"
    if isinstance(value, dict):
        return {str(k): _printable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_printable(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    return value


def zenoh_cli_decoder(key: str, payload: bytes) -> str:
    """msgpack payload -> one JSON line (binary fields shown as their length)."""
    return json.dumps(_printable(_unpack(payload, MAX_WEIGHTS_BYTES + 4096)))


def zenoh_cli_encoder(key: str, value: str) -> bytes:
    """JSON text -> msgpack, e.g. a jammer command typed on the command line."""
    return msgpack.packb(json.loads(value), use_bin_type=True)

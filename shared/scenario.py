"""Scenario: every number of the simulated world, loaded from a TOML file.

The paper fixes some values (GBS power, heights, antenna tilt, noise, SINR threshold); the rest
are choices documented next to each value in ``scenarios/icc2021.toml``. Nothing in the code
hard-codes a number that a scenario file can set.
"""

from __future__ import annotations

import math
import sys
from functools import cached_property
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from shared.shadowing import MAX_GRID_SIDE, field_grid
from shared.shipped import shipped_dir

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - exercised only on Python 3.10
    import tomli as tomllib

SCENARIO_DIR = shipped_dir("scenarios")
DEFAULT_SCENARIO = "icc2021"
# The most UAVs one episode flies: what the world, the lookahead and the bus messages are sized
# for (the city scenario at 1,024 UAVs is benchmarks/bench_scale.py's largest case).
MAX_UAVS = 1024
# Negative seeds fail deep in numpy; torch refuses seeds past 64 bits, and training adds
# offsets to its seed, so stay well clear at 32 bits (numpy's legacy seed range).
SEED_MAX = 2**32 - 1
# The strongest and highest jammer a scenario or a live command may set: a thousand times the
# GBSs' 1 W and twenty times the UAVs' altitude are far past anything the maps are made for;
# beyond them a typing slip (1e30 W) would turn the whole area off without a word.
MAX_JAMMER_POWER_W = 1000.0
MAX_JAMMER_HEIGHT_M = 1000.0
MAX_JAMMERS = 4  # the most a scenario or the live commands may set at once
JammerPower = Annotated[float, Field(ge=0, le=MAX_JAMMER_POWER_W, allow_inf_nan=False)]
JammerHeight = Annotated[float, Field(ge=0, le=MAX_JAMMER_HEIGHT_M, allow_inf_nan=False)]

Positive = Annotated[float, Field(gt=0, allow_inf_nan=False)]
NonNegative = Annotated[float, Field(ge=0, allow_inf_nan=False)]
Finite = Annotated[float, Field(allow_inf_nan=False)]


class ScenarioError(ValueError):
    """A scenario file that cannot be used; the message is one line naming file and field."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Area(_Strict):
    x_min: Finite
    x_max: Finite
    y_min: Finite
    y_max: Finite

    @model_validator(mode="after")
    def _ordered(self) -> Area:
        if self.x_min >= self.x_max or self.y_min >= self.y_max:
            raise ValueError("area needs x_min < x_max and y_min < y_max")
        return self

    def contains(self, x: float, y: float) -> bool:
        return self.x_min <= x <= self.x_max and self.y_min <= y <= self.y_max

    def outside(self, xy: np.ndarray) -> np.ndarray:
        """Which points (..., 2) lie outside the area (a NaN point does not)."""
        x, y = xy[..., 0], xy[..., 1]
        return (x < self.x_min) | (x > self.x_max) | (y < self.y_min) | (y > self.y_max)

    @property
    def square_metres(self) -> float:
        return (self.x_max - self.x_min) * (self.y_max - self.y_min)


def _read_only(array: np.ndarray) -> np.ndarray:
    array.flags.writeable = False
    return array


class Gbs(_Strict):
    positions: list[tuple[Finite, Finite]] = Field(min_length=1)
    height_m: Positive
    power_w: Positive
    tilt_deg: Finite
    beamwidth_3db_deg: Positive
    max_attenuation_db: NonNegative
    # The frequency channel of each GBS, in the order of ``positions``: a GBS interferes only
    # with receivers served on its own channel (frequency reuse). None: all share one channel,
    # as in the paper.
    channels: list[Annotated[int, Field(ge=0, le=1023)]] | None = None

    @cached_property
    def xy(self) -> np.ndarray:
        """``positions`` as a read-only (K, 2) array, built once: an agent's every step reads
        them, and the city's 192 cost more to convert than its features to compute."""
        return _read_only(np.asarray(self.positions, dtype=np.float64))

    @cached_property
    def channel_of(self) -> np.ndarray | None:
        """``channels`` as a read-only array (None where all share one), built once."""
        return None if self.channels is None else _read_only(np.asarray(self.channels))

    @model_validator(mode="after")
    def _one_channel_per_gbs(self) -> Gbs:
        if self.channels is not None and len(self.channels) != len(self.positions):
            raise ValueError(f"channels names {len(self.channels)} GBSs, positions "
                             f"{len(self.positions)}")
        return self


class Uav(_Strict):
    altitude_m: Positive
    radius_m: Positive
    max_speed_mps: Positive
    turn_rate_deg_s: Positive
    speed_choices: int = Field(ge=1, le=32)
    heading_choices: int = Field(ge=1, le=63)
    arrival_tolerance_m: Positive
    measurements_per_step: int = Field(ge=1, le=100)
    # Std (dB) of the error on the SINR a UAV's receiver reports; 0 = exact reports.
    measurement_noise_db: NonNegative = 0.0
    # What the receiver reports of each measurement: "level", its quantized level (the paper's
    # setting), or "db", the measured SINR in steps of report_step_db, its level beside it.
    report: Literal["level", "db"] = "level"
    report_step_db: Positive = 0.5
    # A UAV keeps a new measurement only this far from its last kept one, or at a new level:
    # a hovering UAV would otherwise report one spot over and over.
    measurement_spacing_m: NonNegative = 0.25


class Shadowing(_Strict):
    """Log-normal shadowing of the world: one spatially correlated field per transmitter.

    Absent from a scenario, the world is the paper's idealized Eq. (1)-(5). Correlation over
    distance d follows Gudmundson's exponential model, R(d) = exp(-d / decorrelation_m).
    """

    gbs_sigma_db: NonNegative  # std of the shadowing on every GBS link
    jammer_sigma_db: NonNegative  # std of the shadowing on the jammer link
    decorrelation_m: Positive  # distance at which the correlation falls to 1/e
    seed: int = Field(ge=0)  # which realisation of the fields the world is
    field_spacing_m: Positive  # grid spacing of the sampled fields


class Timing(_Strict):
    step_s: Positive
    disconnection_limit_s: Positive
    episode_limit_s: Positive

    @cached_property
    def disconnection_limit_steps(self) -> int:
        """n_t = T_t / dt, rounded to whole steps."""
        return max(1, round(self.disconnection_limit_s / self.step_s))

    @cached_property
    def episode_limit_steps(self) -> int:
        return max(1, math.ceil(self.episode_limit_s / self.step_s))


class Channel(_Strict):
    path_loss_exponent: Positive
    noise_w: Positive
    sinr_threshold_db: Finite
    level_edges_db: list[Finite] = Field(min_length=1)

    @model_validator(mode="after")
    def _edges(self) -> Channel:
        edges = self.level_edges_db
        if any(b <= a for a, b in zip(edges, edges[1:], strict=False)):
            raise ValueError("level_edges_db must be strictly increasing")
        if not math.isclose(edges[0], self.sinr_threshold_db):
            raise ValueError("level_edges_db[0] must equal sinr_threshold_db (level 0 = below T_s)")
        return self

    @property
    def level_count(self) -> int:
        return len(self.level_edges_db) + 1


class JammerPath(_Strict):
    """A jammer on a vehicle: from its position through ``waypoints`` at a steady speed. The
    drive starts afresh with each episode, so that every mission meets the same convoy."""

    waypoints: list[tuple[Finite, Finite]] = Field(min_length=1)
    speed_mps: Positive
    # After the last waypoint: back to the start and round again (True), or stop there.
    loop: bool = False


class DutyCycle(_Strict):
    """On for ``on_s``, then off for ``off_s``, over and over from ``offset_s`` into the cycle
    at each episode's start."""

    kind: Literal["duty"]
    on_s: Positive
    off_s: NonNegative
    offset_s: NonNegative = 0.0


class Reactive(_Strict):
    """On while any flying UAV is within ``radius_m`` (horizontally) of the jammer: every UAV
    in flight transmits, its uploads if nothing else."""

    kind: Literal["reactive"]
    radius_m: Positive


OnOffSchedule = Annotated[DutyCycle | Reactive, Field(discriminator="kind")]


class Jammer(_Strict):
    """A jammer as configured; ``power_w`` is its nominal (label) power, ``x, y`` where it
    stands or, with a path, where its drive starts. Without a schedule it is always on."""

    enabled: bool = True
    x: Finite
    y: Finite
    power_w: JammerPower
    height_m: JammerHeight
    efficiency_db: Annotated[float, Field(le=0, allow_inf_nan=False)]
    path: JammerPath | None = None
    schedule: OnOffSchedule | None = None

    @property
    def still(self) -> bool:
        """Where it stands and whether it transmits never change within an episode."""
        return self.path is None and self.schedule is None

    @property
    def flies(self) -> bool:
        """Whether a world with it has it: on, and with some power."""
        return self.enabled and self.power_w > 0


class Rewards(_Strict):
    disconnected: Finite
    marginal: Finite
    collision: Finite
    discomfort_distance_m: NonNegative
    arrival: Finite
    step: Finite
    connectivity_check_every_steps: int | None = Field(default=None, ge=1)


class Missions(_Strict):
    uav_count: int = Field(ge=1, le=MAX_UAVS)
    mode: Literal["uniform"] = "uniform"
    margin_m: NonNegative
    min_trip_m: NonNegative
    # The longest start-to-destination distance drawn; None: any the area holds.
    max_trip_m: Positive | None = None
    min_separation_m: NonNegative

    @model_validator(mode="after")
    def _trips_possible(self) -> Missions:
        if self.max_trip_m is not None and self.max_trip_m < self.min_trip_m:
            raise ValueError("missions.max_trip_m is below missions.min_trip_m")
        return self

    def room(self, area: Area) -> tuple[float, float]:
        """Width and height of the part of ``area`` where starts and destinations are drawn."""
        return (area.x_max - area.x_min - 2 * self.margin_m,
                area.y_max - area.y_min - 2 * self.margin_m)


class Policy(_Strict):
    gamma: Annotated[float, Field(gt=0, le=1)]
    observed_uavs: int = Field(ge=0, le=16)
    nearby_gbs: int = Field(ge=1)
    # Whether a measurement's features end with the nearest GBS's own position (its cell
    # identity, which a receiver decodes): on a layout that repeats itself, the offsets alone
    # do not tell the cloud where a measurement was taken (shared/measurements.py).
    nearest_gbs_position: bool = False
    value_scale: Positive
    orca_time_horizon_s: Positive
    route_cell_m: Positive
    route_uncovered_cost: Annotated[float, Field(ge=1, allow_inf_nan=False)]
    # Steps the lookahead searches for a UAV at risk of disconnection (planning/reference.py): each
    # step multiplies its cost by the action count, so more than 3 is out of reach.
    lookahead_depth: int = Field(default=1, ge=1, le=3)
    # How the lookahead predicts the others' next move (planning/reference.py): at their observed
    # velocity, or each taking its half of the avoidance as ORCA's reciprocal agents do.
    others_model: Literal["constant_velocity", "reciprocal"] = "constant_velocity"


class Training(_Strict):
    jammer_change_every_episodes: int = Field(ge=1)
    jammer_power_range_w: tuple[NonNegative, NonNegative]
    jammer_absent_probability: Annotated[float, Field(ge=0, le=1)]
    # A period with jammers has from 1 to this many, each anywhere at a power in the range.
    jammer_count_max: int = Field(default=1, ge=1, le=MAX_JAMMERS)
    # The share of training's jammers on a vehicle: each drives to a random point of the area
    # and back, over and over, at a speed uniform over the range.
    moving_jammer_share: Annotated[float, Field(ge=0, le=1)] = 0.0
    moving_jammer_speed_range_mps: tuple[Positive, Positive] = (1.0, 5.0)
    # The map training's lookahead reads shows a moving jammer where it was at the last
    # multiple of this many seconds into the episode: each new place costs a raster and the
    # UAVs' route fields on it, where every step's place would multiply training's time.
    moving_map_every_s: Positive = 5.0

    @model_validator(mode="after")
    def _ranges_ordered(self) -> Training:
        for name in ("jammer_power_range_w", "moving_jammer_speed_range_mps"):
            low, high = getattr(self, name)
            if low > high:
                raise ValueError(f"training.{name}: {low} > {high}")
        return self


class OnlineMap(_Strict):
    """The cloud's change detector (``cloud_service.change_detection.ChangeDetector``)."""

    change_threshold: Positive  # nats of evidence one UAV's reports must pile up
    # Nats of evidence the fleet's reports must pile up against the jammer a map was
    # corrected for before that map is withdrawn (``jammer_withdrawal.WithdrawalTest``).
    withdrawal_threshold: Positive
    # Nats of evidence for that jammer the reports taken after its detection must give
    # before the first map corrected for it is published (``WithdrawalTest.confirms``).
    confirmation_threshold: Positive
    probability_floor: Annotated[float, Field(gt=0, lt=1, allow_inf_nan=False)]
    # Points the survey map (corrected by the jammer's estimate) labels for each refit: the
    # prior that tells the network what the uploads have not reached.
    prior_points: Annotated[int, Field(ge=1, le=1_000_000)]
    # Flight seconds from the cloud having an upload to a map it triggers flying on the UAVs:
    # in-process runs put a map published at step t in service at t + ceil(latency / dt).
    cloud_latency_s: Annotated[float, Field(ge=0, le=3600, allow_inf_nan=False)]
    # Where receivers report the SINR (uav.report = "db"): the side of the cells in which the
    # cloud averages the no-jammer reports (cloud_service.sinr_reference), the flight a report
    # waits before it enters, and the loss the detector tests those reports for.
    reference_cell_m: Annotated[float, Field(gt=0, le=100, allow_inf_nan=False)] = 1.0
    reference_delay_s: NonNegative = 10.0
    detection_shift_db: Positive = 1.0
    # While it handles a change, the cloud follows the jammer through windows of this many
    # seconds of uploads, each estimated alone (cloud_service.jammer_tracking).
    tracking_window_s: Positive = 5.0
    # While a change's estimate is of one still jammer or none, the cloud tries it as a
    # driving one (cloud_service.driving_jammer) once its uploads span driving_fit_after_s,
    # then every driving_fit_every_s, at most driving_fits times, and fits one that drives
    # again every driving_fit_every_s: the latest driving_fit_window_s of uploads read at
    # once in the frame of each velocity the training's vehicles may have.
    driving_fit_after_s: NonNegative = 10.0
    driving_fit_every_s: Positive = 3.0
    driving_fits: Annotated[int, Field(ge=0, le=1000)] = 0  # the paper's still jammers
    driving_fit_window_s: Positive = 30.0


class Scenario(_Strict):
    """A whole scenario file, validated: the area, stations, UAVs, radio channel, jammer,
    rewards, missions, policy, training and online map every process of a run reads."""

    name: str
    area: Area
    gbs: Gbs
    uav: Uav
    timing: Timing
    channel: Channel
    # A scenario file's ``[jammer]`` section is the one-entry list of ``[[jammers]]``.
    jammers: tuple[Jammer, ...] = Field(min_length=1, max_length=MAX_JAMMERS)
    rewards: Rewards
    missions: Missions
    policy: Policy
    training: Training
    online_map: OnlineMap
    shadowing: Shadowing | None = None

    @model_validator(mode="before")
    @classmethod
    def _jammer_as_list(cls, data: Any) -> Any:
        if isinstance(data, dict) and "jammer" in data:
            if "jammers" in data:
                raise ValueError("give [jammer] or [[jammers]], not both")
            data = {**data, "jammers": [data["jammer"]]}
            del data["jammer"]
        return data

    @property
    def flown_jammers(self) -> tuple[Jammer, ...]:
        """The jammers the scenario flies: those it lists that are on and have power."""
        return tuple(jammer for jammer in self.jammers if jammer.flies)

    @property
    def jammer(self) -> Jammer:
        """The first jammer: the one a single-jammer command or table sets, and whose height
        and efficiency are every command's defaults."""
        return self.jammers[0]

    @model_validator(mode="after")
    def _consistent(self) -> Scenario:
        for x, y in self.gbs.positions:
            if not self.area.contains(x, y):
                raise ValueError(f"gbs.positions: ({x}, {y}) lies outside the area")
        self._jammers_inside()
        width, height = self.missions.room(self.area)
        if width <= 0 or height <= 0:
            raise ValueError("missions.margin_m leaves no room inside the area")
        if self.missions.min_trip_m > math.hypot(width, height):
            raise ValueError(f"missions.min_trip_m ({self.missions.min_trip_m:g} m) is longer "
                             f"than any trip inside the margin ({math.hypot(width, height):.1f} "
                             "m at most)")
        if self.policy.nearby_gbs > len(self.gbs.positions):
            raise ValueError("policy.nearby_gbs exceeds the number of GBSs")
        if self.uav.altitude_m == self.gbs.height_m:
            raise ValueError("uav.altitude_m must differ from gbs.height_m (Eq. 3 divides by it)")
        if self.shadowing is not None:
            grid = field_grid(self.shadowing, self.area)
            side = max(grid.period_x, grid.period_y)
            if side > MAX_GRID_SIDE:
                raise ValueError(f"shadowing: the fields need a grid of {side} points per side "
                                 f"(at most {MAX_GRID_SIDE}): raise field_spacing_m")
        return self

    def _jammers_inside(self) -> None:
        for index, jammer in enumerate(self.jammers):
            where = f"jammers.{index}" if len(self.jammers) > 1 else "jammer"
            if not self.area.contains(jammer.x, jammer.y):
                raise ValueError(f"{where}: position lies outside the area")
            for x, y in [] if jammer.path is None else jammer.path.waypoints:
                if not self.area.contains(x, y):
                    raise ValueError(f"{where}.path: waypoint ({x:g}, {y:g}) lies outside the "
                                     "area")
            # Eq. (5) scales every jammer's power by one efficiency: the radio model's.
            if jammer.efficiency_db != self.jammer.efficiency_db:
                raise ValueError(f"{where}.efficiency_db: every jammer has the first one's "
                                 f"({self.jammer.efficiency_db:g} dB)")

    def survey_world(self) -> dict[str, Any]:
        """What a no-jammer SINR map learned from a survey depends on: where the survey flies,
        the radio world it measures (layout, channel, shadowing, the receivers' noise) and the
        features the map reads. Two scenarios that agree on it can share a survey map;
        missions, rewards, the policy's planning values and the jammer cannot change one."""
        return {"area": self.area.model_dump(), "gbs": self.gbs.model_dump(),
                "altitude_m": self.uav.altitude_m,
                "measurement_noise_db": self.uav.measurement_noise_db,
                "channel": self.channel.model_dump(),
                "shadowing": None if self.shadowing is None else self.shadowing.model_dump(),
                "nearby_gbs": self.policy.nearby_gbs,
                "nearest_gbs_position": self.policy.nearest_gbs_position}

    @property
    def connectivity_check_steps(self) -> int:
        return self.rewards.connectivity_check_every_steps or self.timing.disconnection_limit_steps

    def changed(self, changes: dict[str, Any], name: str | None = None) -> Scenario:
        """The same scenario with each ``"section.key"`` of ``changes`` set (and renamed
        ``name``), validated as a scenario file would be."""
        data = self.model_dump()
        data["jammer"] = data["jammers"][0]  # what a single-jammer change names
        for dotted, value in changes.items():
            section, _, key = dotted.partition(".")
            values = data.get(section)
            if not isinstance(values, dict) or key not in values:
                raise ScenarioError(f"{dotted}: no such scenario value")
            values[key] = value
        if name is not None:
            data["name"] = name
        data["jammers"] = [data.pop("jammer"), *data["jammers"][1:]]
        return Scenario.model_validate(data)

    def with_jammer(self, x: float, y: float, power_w: float,
                    height_m: float | None = None) -> Scenario:
        """The same scenario with one jammer standing still at (x, y), always on, in place of
        all it had (the first one's efficiency kept, and its height unless given)."""
        still = self.jammer.model_copy(update={
            "enabled": True, "x": x, "y": y, "power_w": power_w, "path": None, "schedule": None,
            **({} if height_m is None else {"height_m": height_m})})
        return Scenario.model_validate({**self.model_dump(), "jammers": [still.model_dump()]})

    def without_jammer(self) -> Scenario:
        """The same scenario with no jammer at all."""
        off = self.jammer.model_copy(update={"enabled": False, "path": None, "schedule": None})
        return Scenario.model_validate({**self.model_dump(), "jammers": [off.model_dump()]})


def resolve_scenario_path(name_or_path: str | Path | None) -> Path:
    """A bare name looks in ``scenarios/``; anything with a suffix or separator is a path."""
    if name_or_path is None:
        name_or_path = DEFAULT_SCENARIO
    candidate = Path(name_or_path)
    if candidate.suffix == "" and len(candidate.parts) == 1:
        candidate = SCENARIO_DIR / f"{candidate.name}.toml"
    if candidate.is_dir():
        raise ScenarioError(f"scenario {name_or_path!s}: a directory, not a TOML file")
    if not candidate.is_file():
        known = ", ".join(sorted(p.stem for p in SCENARIO_DIR.glob("*.toml")))
        raise ScenarioError(f"scenario {name_or_path!s}: no such file (known names: {known})")
    return candidate


def load_scenario(name_or_path: str | Path | None = None) -> Scenario:
    """Load and validate a scenario; raise ScenarioError with a one-line message on any problem."""
    path = resolve_scenario_path(name_or_path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ScenarioError(f"{path}: not valid TOML: {exc}") from None
    data.setdefault("name", path.stem)
    try:
        return Scenario.model_validate(data)
    except ValidationError as exc:
        first = exc.errors()[0]
        location = first["loc"]
        if "jammer" in data and location[:2] == ("jammers", 0):
            location = ("jammer", *location[2:])  # as the file names it
        field = ".".join(str(part) for part in location) or "(top level)"
        problems = exc.error_count()
        more = f" (and {problems - 1} more)" if problems > 1 else ""
        raise ScenarioError(f"{path}: field {field}: {first['msg']}{more}") from None

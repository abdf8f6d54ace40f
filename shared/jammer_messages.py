"""The jammers: each as messages carry it (``JammerInfo``, and the one syntax every command
gives its place), where each is at a step (``JammerPlace``), the operator's commands on the
control key and the world's replies, and the cloud's estimate."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Annotated, Any, Literal

from pydantic import Field, TypeAdapter, ValidationError, model_validator

from shared.radio import JammerParams
from shared.scenario import (
    MAX_JAMMER_HEIGHT_M,
    MAX_JAMMER_POWER_W,
    MAX_JAMMERS,
    Jammer,
    JammerHeight,
    JammerPath,
    JammerPower,
    OnOffSchedule,
    Scenario,
)
from shared.wire import Count, Finite, Message, NonNegative

# What every jammer a command or message sets must be (JammerPower, JammerHeight).
JAMMER_LIMITS = (f"position, power and height must be finite, power and height >= 0, power at "
                 f"most {MAX_JAMMER_POWER_W:g} W and height at most {MAX_JAMMER_HEIGHT_M:g} m")


# A running world's jammers are numbered 0-3: a new one takes the lowest number free.
JammerId = Annotated[int, Field(ge=0, lt=MAX_JAMMERS)]


class JammerInfo(Message):
    """A jammer as messages carry it (position in metres, nominal power, antenna height, and
    the path it drives and its on/off schedule, if any): what a command sets and the world
    reports in force; ``params`` is the radio model's."""

    id: JammerId = 0
    x: Finite
    y: Finite
    power_w: JammerPower
    height_m: JammerHeight
    path: JammerPath | None = None
    schedule: OnOffSchedule | None = None

    @classmethod
    def of(cls, jammer: Jammer, id: int) -> JammerInfo:
        """A scenario's jammer as messages carry it."""
        return cls(id=id, x=jammer.x, y=jammer.y, power_w=jammer.power_w,
                   height_m=jammer.height_m, path=jammer.path, schedule=jammer.schedule)

    def as_jammer(self, scenario: Scenario) -> Jammer:
        """The scenario's jammer it stands for (the radio model's one efficiency)."""
        return Jammer(x=self.x, y=self.y, power_w=self.power_w, height_m=self.height_m,
                      efficiency_db=scenario.jammer.efficiency_db, path=self.path,
                      schedule=self.schedule)

    @staticmethod
    def of_scenario(scenario: Scenario) -> tuple[JammerInfo, ...]:
        """The scenario's jammers that are on, numbered in the file's order."""
        return tuple(JammerInfo.of(jammer, index)
                     for index, jammer in enumerate(scenario.flown_jammers))

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
    def params(jammers: Sequence[JammerInfo]) -> tuple[JammerParams, ...]:
        """The radio model's jammers, each where it stands or starts its drive."""
        return tuple(JammerParams(jammer.x, jammer.y, jammer.power_w, jammer.height_m)
                     for jammer in jammers)


def recorded_one_jammer(data: Any, one_key: str, list_key: str) -> Any:
    """A message recorded when a world had one jammer (``one_key``: it, or None) read as the
    list (``list_key``) that messages carry now, so that older recordings still replay."""
    if isinstance(data, dict) and one_key in data:
        one = data[one_key]
        data = {key: value for key, value in data.items() if key != one_key}
        data[list_key] = [] if one is None else [one]
    return data


JammersInForce = tuple[JammerInfo, ...]
_JAMMER_LIST = TypeAdapter(list[JammerInfo])


class JammerPlace(Message):
    """Where jammer ``id`` is at a step, and whether it transmits then."""

    id: JammerId
    x: Finite
    y: Finite
    on: bool


def initial_jammers(scenario: Scenario, text: str | None, listed: str | None,
                    off: bool) -> JammersInForce:
    """The jammers a run starts with: ``--jammer X,Y,P[,H]`` (one), ``--jammers JSON`` (the
    list a restarted world carries on with), ``--no-jammer`` (none) or the scenario's.
    ValueError with a one-line reason."""
    if off:
        return ()
    if listed is not None:
        try:
            jammers = tuple(_JAMMER_LIST.validate_json(listed))
        except ValidationError as exc:
            raise ValueError(f"--jammers: {exc.errors()[0]['msg']}") from None
        if len(jammers) > MAX_JAMMERS or len({jammer.id for jammer in jammers}) < len(jammers):
            raise ValueError(f"--jammers: at most {MAX_JAMMERS}, each with its own id")
    elif text is not None:
        jammers = (JammerInfo.parse(text, scenario.jammer.height_m),)
    else:
        return JammerInfo.of_scenario(scenario)
    for jammer in jammers:
        check_inside(scenario, jammer.x, jammer.y)
    return tuple(jammer for jammer in jammers if jammer.power_w > 0)


def check_inside(scenario: Scenario, x: float, y: float) -> None:
    area = scenario.area
    if not area.contains(x, y):
        raise ValueError(f"position ({x:g}, {y:g}) outside the area [{area.x_min:g}, "
                         f"{area.x_max:g}] x [{area.y_min:g}, {area.y_max:g}]")


def jammer_arguments(jammers: JammersInForce) -> list[str]:
    """The command-line options that start a process with ``jammers`` in force."""
    if not jammers:
        return ["--no-jammer"]
    return ["--jammers", _JAMMER_LIST.dump_json(list(jammers)).decode()]


def jammer_numbers(text: str, placed_only: bool = False
                   ) -> tuple[float, float, float | None, float | None]:
    """"X,Y,P" or "X,Y,P,H" as numbers (H None when left out): the one jammer syntax of every
    command; with ``placed_only`` (a move) also "X,Y" (P None). ValueError with a one-line
    reason."""
    parts = text.split(",")
    if len(parts) not in ((2, 3, 4) if placed_only else (3, 4)):
        raise ValueError(f"jammer {text!r}: expected "
                         + ("X,Y[,P[,H]]" if placed_only else "X,Y,P or X,Y,P,H"))
    try:
        values = [float(part) for part in parts] + [None] * (4 - len(parts))
    except ValueError:
        raise ValueError(f"jammer {text!r}: expected numbers, e.g. -25,15,1") from None
    return values[0], values[1], values[2], values[3]


class JammerCommand(Message):
    """Payload of a query on the control key; no payload means ``show``. ``set`` puts one
    jammer in place of all; ``add`` one more (a new id); ``move`` jammer ``id`` (standing
    still there; power and height kept unless given); ``remove`` jammer ``id``; ``off`` every
    jammer, or jammer ``id`` alone."""

    action: Literal["set", "add", "move", "remove", "off", "show"]
    id: JammerId | None = None
    x: Finite | None = None
    y: Finite | None = None
    power_w: JammerPower | None = None
    height_m: JammerHeight | None = None

    @model_validator(mode="after")
    def _complete(self) -> JammerCommand:
        placed = self.x is not None and self.y is not None
        numbers = any(v is not None for v in (self.x, self.y, self.power_w, self.height_m))
        if self.action in ("set", "add") and not (placed and self.power_w is not None):
            raise ValueError(f"{self.action} needs x, y and power_w")
        if self.action == "move" and not placed:
            raise ValueError("move needs x and y")
        if self.action in ("move", "remove") and self.id is None:
            raise ValueError(f"{self.action} needs the jammer's id")
        if self.action in ("set", "add", "show") and self.id is not None:
            raise ValueError(f"{self.action} takes no id")
        if self.action in ("remove", "off", "show") and numbers:
            raise ValueError(f"{self.action} takes no position or power")
        return self



class JammerReply(Message):
    """The world's answer to a jammer command: accepted or why not, and the jammers in force
    with the step they apply from."""

    accepted: bool
    reason: str | None = Field(default=None, max_length=500)
    jammers: list[JammerInfo] = Field(max_length=MAX_JAMMERS)  # in force from the next step
    episode: Count
    step: Count



class JammerEstimate(Message):
    """The cloud's estimate of the jammers after a detected change, from the uploads alone:
    the first jammer in its own fields and any estimated beside it in ``others``, each a
    present estimate with its own ``id`` and no others of its own.

    ``map_version`` is the SINR map corrected with them (published at the same time). With
    ``present`` false the uploads are best explained by no jammer at all, and the position and
    power fields are None. Standard deviations come from the fit's likelihood.
    """

    map_version: Count
    t: Finite  # unix seconds (simulated seconds in-process)
    present: bool
    id: JammerId = 0  # the estimate's own numbering, not the world's (it cannot know those)
    x: Finite | None = None
    y: Finite | None = None
    power_w: NonNegative | None = None  # nominal, as `jamnav jammer set` takes it
    effective_power_dbm: Finite | None = None  # what reaches the receiver in band
    sd_x_m: NonNegative | None = None
    sd_y_m: NonNegative | None = None
    sd_power_db: NonNegative | None = None
    # Where the cloud follows the jammer over time: its velocity (m/s) and their sds.
    vx_mps: Finite | None = None
    vy_mps: Finite | None = None
    sd_vx_mps: NonNegative | None = None
    sd_vy_mps: NonNegative | None = None
    measurements: Count  # post-change uploads it was fitted to
    change_time: Finite | None = None  # the detector's estimate of when the change happened
    others: list[JammerEstimate] = Field(default_factory=list, max_length=MAX_JAMMERS - 1)

    @model_validator(mode="after")
    def _located(self) -> JammerEstimate:
        located = (self.x, self.y, self.power_w)
        if self.present and None in located:
            raise ValueError("a present jammer needs x, y and power_w")
        if not self.present and any(v is not None for v in located):
            raise ValueError("an absent jammer has no x, y or power_w")
        if self.others and not self.present:
            raise ValueError("an absent jammer has no others beside it")
        if any(not other.present or other.others for other in self.others):
            raise ValueError("each other jammer is present, with no others of its own")
        if len({estimate.id for estimate in self.members}) != len(self.members):
            raise ValueError("each estimated jammer needs its own id")
        return self

    @property
    def members(self) -> list[JammerEstimate]:
        """Each estimated jammer, this one first; none when ``present`` is false."""
        return [self, *self.others] if self.present else []


def describe_jammers(jammers: Sequence[JammerInfo]) -> str:
    """The jammers a change put in force, for people: one still jammer as where it moved."""
    if not jammers:
        return "jammer switched off"
    places = [f"({jammer.x:g}, {jammer.y:g}), {jammer.power_w:g} W"
              + ("" if jammer.path is None else " on a path") for jammer in jammers]
    if len(jammers) == 1:
        return f"jammer moved to {places[0]}"
    return "jammers now " + "; ".join(f"{jammer.id}: {place}"
                                     for jammer, place in zip(jammers, places, strict=True))


def describe_estimate(estimate: JammerEstimate) -> str:
    """One line for people: where each jammer is thought to be, and how sure the fit is."""
    if not estimate.present:
        return f"no jammer ({estimate.measurements} measurements)"
    places = [f"({member.x:.1f} +- {member.sd_x_m:.1f}, {member.y:.1f} +- "
              f"{member.sd_y_m:.1f}) m, {member.power_w:.2f} W +- {member.sd_power_db:.1f} dB"
              + _velocity(member) for member in estimate.members]
    if len(places) > 1:
        places = [f"{len(places)} jammers:"] + [f"{member.id}: {place};" for member, place
                                                in zip(estimate.members, places, strict=True)]
        places[-1] = places[-1].rstrip(";")
    return " ".join(places) + f" ({estimate.measurements} measurements)"


def describe_count(jammers_counted: int | None) -> str:
    """How many jammers the cloud counted, for people."""
    if jammers_counted is None:
        return "no count yet"
    return f"{jammers_counted} jammer{'' if jammers_counted == 1 else 's'} counted"


def _velocity(estimate: JammerEstimate) -> str:
    if estimate.vx_mps is None or estimate.vy_mps is None:
        return ""
    return (f", moving ({estimate.vx_mps:.1f} +- {estimate.sd_vx_mps or 0.0:.1f}, "
            f"{estimate.vy_mps:.1f} +- {estimate.sd_vy_mps or 0.0:.1f}) m/s")

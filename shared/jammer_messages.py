"""The jammer: where one is (``JammerInfo``, and the one syntax every command gives it), the
operator's commands on the control key and the world's replies, and the cloud's estimate of
it."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, ValidationError, model_validator

from shared.radio import JammerParams
from shared.scenario import (
    MAX_JAMMER_HEIGHT_M,
    MAX_JAMMER_POWER_W,
    JammerHeight,
    JammerPower,
)
from shared.wire import Count, Finite, Message, NonNegative

# What every jammer a command or message sets must be (JammerPower, JammerHeight).
JAMMER_LIMITS = (f"position, power and height must be finite, power and height >= 0, power at "
                 f"most {MAX_JAMMER_POWER_W:g} W and height at most {MAX_JAMMER_HEIGHT_M:g} m")


class JammerInfo(Message):
    """A jammer as messages carry it (position in metres, nominal power, antenna height):
    what a command sets and the world reports in force; ``params`` is the radio model's."""

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



class JammerReply(Message):
    """The world's answer to a jammer command: accepted or why not, and the jammer in force
    with the step it applies from."""

    accepted: bool
    reason: str | None = Field(default=None, max_length=500)
    jammer: JammerInfo | None  # in force from the next step (None: no jammer)
    episode: Count
    step: Count



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


def describe_estimate(estimate: JammerEstimate) -> str:
    """One line for people: where the jammer is thought to be, and how sure the fit is."""
    if not estimate.present:
        return f"no jammer ({estimate.measurements} measurements)"
    return (f"({estimate.x:.1f} +- {estimate.sd_x_m:.1f}, {estimate.y:.1f} +- "
            f"{estimate.sd_y_m:.1f}) m, {estimate.power_w:.2f} W +- {estimate.sd_power_db:.1f} dB "
            f"({estimate.measurements} measurements)")

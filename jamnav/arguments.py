"""Command-line arguments shared by the ``jamnav`` commands: the options several commands take
(``--scenario``, ``--jammer``) and how they are read, and the checks of counts, ranges, output
paths and model files. A bad value is refused with one line before any work starts, never
found deep inside as a traceback."""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path

from shared.jammer_messages import JAMMER_LIMITS, JammerCommand, JammerInfo
from shared.scenario import MAX_JAMMERS, Scenario, load_scenario, resolve_scenario_path


class UsageError(Exception):
    """A problem with the user's input, reported as one line (exit 2)."""


# -- --scenario and --jammer --------------------------------------------------------------------
def add_scenario(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--scenario", default=None, metavar="NAME|PATH",
        help="scenario name under scenarios/ or a TOML file (default: icc2021)",
    )


def add_jammer(parser: argparse.ArgumentParser) -> None:
    group = parser.add_mutually_exclusive_group()
    group.add_argument(
        "--jammer", metavar="X,Y,P[,H]",
        help="jammer position (m), nominal power (W) and height (m, default: the scenario's)",
    )
    group.add_argument("--no-jammer", action="store_true", help="no jammer at all")


def scenario_argument(args: argparse.Namespace) -> Scenario:
    """load_scenario, with a file that exists but cannot be read as one line too."""
    try:
        return load_scenario(args.scenario)
    except OSError as exc:
        raise UsageError(f"{resolve_scenario_path(args.scenario)}: {exc.strerror}") from None


def scenario_with_jammer(args: argparse.Namespace) -> Scenario:
    """The scenario named by --scenario with --jammer/--no-jammer applied and validated."""
    scenario = scenario_argument(args)
    if getattr(args, "no_jammer", False):
        return scenario.without_jammer()
    if getattr(args, "jammer", None) is not None:
        try:
            jammer = JammerInfo.parse(args.jammer, scenario.jammer.height_m)
        except ValueError as exc:
            raise UsageError(f"--{exc}") from None
        if not scenario.area.contains(jammer.x, jammer.y):
            area = scenario.area
            raise UsageError(
                f"--jammer {args.jammer!r}: position outside the area "
                f"[{area.x_min:g}, {area.x_max:g}] x [{area.y_min:g}, {area.y_max:g}]"
            )
        return scenario.with_jammer(jammer.x, jammer.y, jammer.power_w, jammer.height_m)
    return scenario


# -- checks -------------------------------------------------------------------------------------
def comma_numbers(text: str, count: int, what: str) -> list[float]:
    """The ``count`` finite numbers of one comma-separated argument, which ``what`` names in
    the error."""
    parts = text.split(",")
    try:
        values = [float(part) for part in parts]
    except ValueError:
        raise UsageError(f"{what} {text!r}: expected {count} comma-separated numbers") from None
    if len(values) != count or not all(math.isfinite(v) for v in values):
        raise UsageError(f"{what} {text!r}: expected {count} finite comma-separated numbers")
    return values


def check_range(
    option: str, value: float | None, low: float, high: float | None = None,
    *, above: bool = False,
) -> None:
    """Refuse a count, rate or seed out of range before any work starts (deep inside, it
    would fail as a traceback or run forever). NaN and infinities are never in range;
    ``above`` excludes ``low`` itself."""
    if value is None:  # an optional value left to its default
        return
    if math.isfinite(value) and (value > low if above else value >= low) and (
        high is None or value <= high
    ):
        return
    if above:
        raise UsageError(f"{option} must be a finite number above {low:g}")
    if high is None:
        raise UsageError(f"{option} must be at least {low}")
    raise UsageError(f"{option} must be between {low} and {high}")


def output_path(
    option: str, text: str, *, directory: bool = False, beside: Sequence[str] = ()
) -> Path:
    """``text`` as where a command writes (a directory, or a file plus the files named by
    ``beside`` suffixes), refused now if it cannot be written: the writing comes last, after
    the work, which a late failure would throw away."""
    path = Path(text)
    if not directory:
        for target in (path, *(path.with_suffix(suffix) for suffix in beside)):
            if target.is_dir():
                raise UsageError(f"{option} {text}: {target} is a directory")
            if target.is_symlink() and not target.exists():
                raise UsageError(f"{option} {text}: {target} is a link to nothing")
    existing = path if directory else path.parent
    while not existing.exists() and not existing.is_symlink():  # a dangling link stops too
        existing = existing.parent
    if not existing.is_dir():
        raise UsageError(f"{option} {text}: {existing} is not a directory")
    # Tried, not asked (os.access): root passes every permission check, yet cannot write
    # into /proc or /sys or a read-only mount.
    try:
        tempfile.TemporaryFile(dir=existing).close()
    except OSError as exc:
        raise UsageError(f"{option} {text}: cannot write in {existing} "
                         f"({exc.strerror or exc})") from None
    return path


def new_recording(option: str, text: str) -> Path:
    """``output_path`` for a recording, which is never written over: a file there (or a link
    to one) is refused now."""
    path = output_path(option, text)
    if path.exists():
        link = " (a link)" if path.is_symlink() else ""
        raise UsageError(f"{option} {text}: exists{link}; choose another name or remove it")
    return path


# Episodes whose missions a fleet check places: placement draws at random and gives up after
# a bounded number of draws, so a fleet near what the area holds fails on some episodes only.
FLEET_CHECK_EPISODES = 8


def check_fleet(option: str, uavs: int, scenario, seed: int = 0) -> None:
    """Refuse a fleet whose missions the scenario's area cannot hold (placed for the run's
    first episodes as the world will place them), instead of failing at the first reset."""
    from world_sim.core import MissionSampler, episode_seed

    sampler = MissionSampler(scenario)
    for episode in range(FLEET_CHECK_EPISODES):
        try:
            sampler.sample(episode_seed(seed, episode), uavs)
        except ValueError as exc:
            raise UsageError(f"{option} {uavs}: {exc} (scenario {scenario.name})") from None


def sinr_map_argument(option: str, path: str, scenario):
    """(network, card) of a SINR map given on the command line for ``scenario``: refused in
    one line unless it is a SINR-mapping network of the scenario's features and levels."""
    from planning.networks import WeightsError, load_network
    from shared.measurements import MeasurementSpec

    spec = MeasurementSpec.of(scenario)
    try:
        return load_network(Path(path), {"kind": "sinr_map", "input_size": spec.feature_size,
                                         "levels": spec.level_count})
    except WeightsError as exc:
        raise UsageError(f"{option}: {exc}") from None


def survey_map_argument(option: str, path: str, scenario) -> Path:
    """``sinr_map_argument`` for a survey map, with a one-line warning on stderr when its card
    says it was learned in another radio world than ``scenario``'s."""
    from shared.survey_maps import foreign_survey_map

    _, card = sinr_map_argument(option, path, scenario)
    if (warning := foreign_survey_map(card, scenario)) is not None:
        print(f"jamnav: warning: {option}: {warning}", file=sys.stderr)
    return Path(path)


def jammer_command(action: str, numbers: tuple | None = None, what: str = "",
                   jammer_id: int | None = None) -> JammerCommand:
    """The world's ``JammerCommand``: ``set``, ``add`` or ``move`` (jammer ``jammer_id``) to
    ``numbers`` (x, y, power_w or None for a move, height_m or None), ``remove`` or ``off``
    (jammer ``jammer_id``, or every one), or ``show``. What it would refuse is a UsageError
    with one line that quotes ``what`` the user gave (the command line's X,Y,P[,H], the
    console's JSON)."""
    if jammer_id is not None and not 0 <= jammer_id < MAX_JAMMERS:
        raise UsageError(f"jammer {action} {jammer_id}: a jammer's id is 0 to {MAX_JAMMERS - 1}")
    if numbers is None:
        return JammerCommand(action=action, id=jammer_id)
    x, y, power, height = numbers
    try:
        return JammerCommand(action=action, id=jammer_id, x=x, y=y, power_w=power,
                             height_m=height)
    except ValueError:
        raise UsageError(f"jammer {action} {what}: {JAMMER_LIMITS}") from None

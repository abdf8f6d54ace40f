"""Where the shipped files live: the scenario files and the default weights (``models/``,
trained by the project's commands)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from shared.scenario import Jammer, Scenario


def shipped_dir(name: str) -> Path:
    """The repository's top-level ``name/`` (``scenarios``, ``models``): in an installed copy
    the package data inside ``shared`` (pyproject.toml puts it there), else the checkout's own
    directory (an editable install, or a checkout that shadows an installed copy)."""
    installed = Path(__file__).resolve().parent / name
    return installed if installed.is_dir() else installed.parent.parent / name


MODELS_DIR = shipped_dir("models")
VALUE_NET = MODELS_DIR / "value_net.safetensors"  # the paper's method
EXTENDED_VALUE_NET = MODELS_DIR / "value_net_extended.safetensors"
# The paper's method trained in scenarios/icc2021-tt6.toml, where it flies as the paper reports.
PAPER_TT6_VALUE_NET = MODELS_DIR / "value_net_paper_tt6.safetensors"
SINR_MAP_NO_JAMMER = MODELS_DIR / "sinr_map_no_jammer.safetensors"
SINR_MAP_NO_JAMMER_SHADOWED = MODELS_DIR / "sinr_map_no_jammer_shadowed.safetensors"
SINR_MAP_NO_JAMMER_CITY = MODELS_DIR / "sinr_map_no_jammer_city.safetensors"
EXTENDED_CROWD_VALUE_NET = MODELS_DIR / "value_net_extended_crowd.safetensors"
# The extended method trained in scenarios/icc2021-many-jammers.toml: up to three jammers in a
# training period, a quarter of them driving.
EXTENDED_MANY_VALUE_NET = MODELS_DIR / "value_net_extended_many.safetensors"

# The shipped value networks by name; every command that takes one defaults to the best.
VALUE_NETS = {"extended": EXTENDED_VALUE_NET, "extended-crowd": EXTENDED_CROWD_VALUE_NET,
              "extended-many": EXTENDED_MANY_VALUE_NET, "paper": VALUE_NET,
              "paper-tt6": PAPER_TT6_VALUE_NET}
DEFAULT_VALUE_NET = "extended"
VALUE_NET_HELP = ("value network: a shipped one by name (extended, the best for the paper's "
                  "4 UAVs per hectare and one still jammer; extended-many, trained with up to "
                  "three jammers, some driving; extended-crowd, trained with 16 UAVs per "
                  "hectare; the default is the one of the three for the fleet's density and the "
                  "scenario's jammers; paper, the paper's method; paper-tt6, the paper's method "
                  "trained for --scenario icc2021-tt6) or a safetensors path")
# What makes a fleet a crowd is how many UAVs meet, and the features are local: so density, not
# count (the city's 64 UAVs on 16 ha fly as icc2021's 4 on 1 ha). At 16 per hectare the crowd's
# network flies better, at 8 the two tie (BENCHMARKS.md, "Planning").
CROWD_UAVS_PER_HECTARE = 8.0


def best_value_net(scenario: Scenario, uavs: int,
                   jammers: Sequence[Jammer] | None = None) -> Path:
    """The shipped value network that flies ``uavs`` UAVs in ``scenario``'s world best: the
    crowd's where they are dense, else the one trained on several and driving jammers where
    the jammers flown (default: the scenario's) are several or one drives (BENCHMARKS.md, "A
    network trained on several and driving jammers, shipped")."""
    if uavs / (scenario.area.square_metres / 10_000.0) >= CROWD_UAVS_PER_HECTARE:
        return VALUE_NETS["extended-crowd"]
    flown = [jammer for jammer in (scenario.jammers if jammers is None else jammers)
             if jammer.flies]
    varied = len(flown) > 1 or any(jammer.path is not None for jammer in flown)
    return VALUE_NETS["extended-many" if varied else DEFAULT_VALUE_NET]


def value_net_path(name_or_path: str | Path) -> Path:
    """A shipped value network by name, or the path given."""
    return VALUE_NETS.get(str(name_or_path), Path(name_or_path))


def value_net_for(name_or_path: str | Path | None, scenario: Scenario, uavs: int,
                  jammers: Sequence[Jammer] | None = None) -> Path:
    """The value network asked for (a shipped name or a path), or else the best shipped one
    for ``uavs`` UAVs in ``scenario``'s world under ``jammers`` (default: the scenario's)."""
    if name_or_path:
        return value_net_path(name_or_path)
    return best_value_net(scenario, uavs, jammers)


def value_net_name(path: Path | None) -> str:
    """How people know a value network: a shipped one by its name, another by its path
    (None: the default)."""
    if path is None:
        return DEFAULT_VALUE_NET
    resolved = Path(path).resolve()
    return next((name for name, shipped in VALUE_NETS.items() if shipped.resolve() == resolved),
                str(path))

"""Where the shipped files live: the scenario files and the default weights (``models/``,
trained by the project's commands)."""

from __future__ import annotations

from pathlib import Path


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

# The survey map (no jammer) learned in each scenario's world; other scenarios share icc2021's.
_SURVEY_MAPS = {"icc2021-shadowed": SINR_MAP_NO_JAMMER_SHADOWED,
                "city": SINR_MAP_NO_JAMMER_CITY}


def sinr_map_for(scenario_name: str) -> Path:
    """The shipped no-jammer SINR map learned from measurements in the named scenario."""
    return _SURVEY_MAPS.get(scenario_name, SINR_MAP_NO_JAMMER)


# The shipped value networks by name; every command that takes one defaults to the best.
VALUE_NETS = {"extended": EXTENDED_VALUE_NET, "paper": VALUE_NET, "paper-tt6": PAPER_TT6_VALUE_NET}
DEFAULT_VALUE_NET = "extended"
DEFAULT_VALUE_NET_PATH = VALUE_NETS[DEFAULT_VALUE_NET]
VALUE_NET_HELP = ("value network: a shipped one by name (extended, the default and the best; "
                  "paper, the paper's method; paper-tt6, the paper's method trained for "
                  "--scenario icc2021-tt6) or a safetensors path")


def value_net_path(name_or_path: str | Path) -> Path:
    """A shipped value network by name, or the path given."""
    return VALUE_NETS.get(str(name_or_path), Path(name_or_path))


def value_net_name(path: Path | None) -> str:
    """How people know a value network: a shipped one by its name, another by its path
    (None: the default)."""
    if path is None:
        return DEFAULT_VALUE_NET
    resolved = Path(path).resolve()
    return next((name for name, shipped in VALUE_NETS.items() if shipped.resolve() == resolved),
                str(path))

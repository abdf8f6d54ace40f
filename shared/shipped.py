"""Where the shipped default weights live (``models/``, trained by the project's commands)."""

from __future__ import annotations

from pathlib import Path

MODELS_DIR = Path(__file__).resolve().parent.parent / "models"
VALUE_NET = MODELS_DIR / "value_net.safetensors"  # the paper's method
EXTENDED_VALUE_NET = MODELS_DIR / "value_net_extended.safetensors"
SINR_MAP_NO_JAMMER = MODELS_DIR / "sinr_map_no_jammer.safetensors"

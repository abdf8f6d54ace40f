"""zenoh-cli's msgpack codec (entry points in pyproject.toml): ``zenoh subscribe ... --decoder
msgpack`` prints each message as a JSON line (docs/topics.md)."""

from __future__ import annotations

import json
import math
from typing import Any

import msgpack

from shared.cloud_messages import ValueWeights
from shared.wire import unpack


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
    return json.dumps(_printable(unpack(payload, ValueWeights.max_bytes)))  # the largest


def zenoh_cli_encoder(key: str, value: str) -> bytes:
    """JSON text -> msgpack, e.g. a jammer command typed on the command line."""
    return msgpack.packb(json.loads(value), use_bin_type=True)

"""What a message is on the bus: the pydantic base of every message, the field types they are
validated by, and msgpack on the wire.

``encode`` and ``decode`` (with ``shared.events.decode_event``) are the only way in and out of
the wire format. Decoding refuses, with a one-line ``MessageError``, anything oversized, not
msgpack, or outside the model's rules (unknown fields, non-finite numbers, out-of-range
values, inconsistent lengths, a weights payload whose sha256 does not match). msgpack carries
plain data only: nothing received is ever turned into code or arbitrary objects (no pickle;
msgpack extension types are refused by the models).

The messages are defined by topic family: ``shared.world_messages`` (the world's step),
``shared.cloud_messages`` (uploads and networks), ``shared.jammer_messages``,
``shared.events`` and ``shared.process_status``. The topic each travels on is in
``shared.topics``; ``docs/topics.md`` lists both.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Annotated, Any, ClassVar, TypeVar

import msgpack
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from shared.measurements import MAX_REPORTED_DB
from shared.scenario import MAX_UAVS

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


class MessageError(ValueError):
    """A payload that is not a valid message; the text is one line."""


class Message(BaseModel):
    """The base of every message: frozen, unknown fields refused, and a cap on the payload
    it is decoded from (``max_bytes``: 64 KiB unless the message needs more)."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    max_bytes: ClassVar[int] = 64 * 1024


M = TypeVar("M", bound=Message)


def encode(message: Message) -> bytes:
    return msgpack.packb(message.model_dump(mode="python"), use_bin_type=True)


def unpack(payload: bytes, max_bytes: int) -> Any:
    """The plain data in a msgpack ``payload`` of at most ``max_bytes``; MessageError
    otherwise."""
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


def validated(validate: Callable[[Any], M], data: Any, what: str) -> M:
    """``validate(data)``, a ValidationError turned into a one-line MessageError about
    ``what``."""
    try:
        return validate(data)
    except ValidationError as exc:
        raise MessageError(f"{what}: {_one_line(exc)}") from None


def decode(kind: type[M], payload: bytes) -> M:
    """The message of type ``kind`` in ``payload``, validated; MessageError otherwise."""
    data = unpack(bytes(payload), kind.max_bytes)
    if not isinstance(data, dict):
        raise MessageError(f"{kind.__name__}: expected a map, got {type(data).__name__}")
    return validated(kind.model_validate, data, kind.__name__)

"""Where the system is on the bus: the router's endpoint and every key expression, under one
prefix (default ``jamnav``).

The layout groups what concerns one UAV under ``<prefix>/uav/<id>/`` so that one UAV's traffic
can be watched with a single wildcard. ``docs/topics.md`` lists each key with its message.
"""

from __future__ import annotations

import argparse
import os
import re
from dataclasses import dataclass

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
ENDPOINT_ENV = "JAMNAV_ENDPOINT"
DEFAULT_PREFIX = "jamnav"
_PREFIX = re.compile(r"^[A-Za-z0-9_-]+(/[A-Za-z0-9_-]+)*$")
_PROTOCOLS = ("tcp", "udp", "tls", "quic")
_ENDPOINT = re.compile(rf"^(?:{'|'.join(_PROTOCOLS)})/(?:\[[0-9A-Fa-f:.]+\]|[^/:\[\]]+)"
                       r":(?P<port>[0-9]{1,5})$")
_UAV_KEY = re.compile(r"/uav/([^/]+)/")


def endpoint_from(given: str | None = None) -> str:
    """--endpoint if given, else $JAMNAV_ENDPOINT, else the default loopback router; a
    malformed one is refused here (zenoh would only say later that it cannot connect)."""
    endpoint = given or os.environ.get(ENDPOINT_ENV) or DEFAULT_ENDPOINT
    found = _ENDPOINT.match(endpoint)
    if not found or not 1 <= int(found.group("port")) <= 65535:
        raise ValueError(f"endpoint {endpoint!r}: expected PROTOCOL/HOST:PORT with PROTOCOL "
                         f"one of {', '.join(_PROTOCOLS)}, e.g. {DEFAULT_ENDPOINT}")
    return endpoint


class ArgumentParser(argparse.ArgumentParser):
    """Reads "-12.5,-33" as a value, not an option: coordinates are often negative, and the
    supervisor hands them on to its children as they were given."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._negative_number_matcher = re.compile(r"^-\.?\d[\d.,eE+-]*$")


def add_bus_arguments(parser: argparse.ArgumentParser) -> None:
    """--endpoint, --prefix and --credentials: how every command and process finds its
    system and, on a secure one, logs in."""
    parser.add_argument("--endpoint", default=None,
                        help=f"router (default ${ENDPOINT_ENV} or {DEFAULT_ENDPOINT})")
    parser.add_argument("--prefix", default=DEFAULT_PREFIX, help="key prefix of the system")
    parser.add_argument("--credentials", default=None, metavar="PATH",
                        help="a secure system's credentials file (`jamnav up --secure` writes "
                             "one): log in as this command's role (a router enforces them)")


def uav_in_key(key: str) -> str | None:
    """The UAV id of a ``.../uav/<id>/...`` key, as written (None for other keys)."""
    found = _UAV_KEY.search(str(key))
    return found.group(1) if found else None


@dataclass(frozen=True)
class Topics:
    """Every key expression of one system, under its prefix: what each process publishes,
    subscribes to, queries and serves (docs/topics.md lists them with their messages)."""

    prefix: str = DEFAULT_PREFIX

    def __post_init__(self) -> None:
        if not _PREFIX.match(self.prefix):
            raise ValueError(f"bus prefix {self.prefix!r}: use letters, digits, _ and -, "
                             "chunks separated by /")

    # -- world ------------------------------------------------------------------------------
    @property
    def state(self) -> str:
        """Whole-fleet state per step (monitoring: positions, velocities, SINR of every UAV)."""
        return f"{self.prefix}/world/state"

    @property
    def join(self) -> str:
        """Queryable of the world that hands a free UAV id to an agent started without one."""
        return f"{self.prefix}/world/join"

    def observation(self, uav: int | str) -> str:
        """What one UAV observes at a step: its own state and the observable others."""
        return f"{self.prefix}/uav/{uav}/observation"

    def action(self, uav: int | str) -> str:
        return f"{self.prefix}/uav/{uav}/action"

    def measurement_round(self, uav: int | str) -> str:
        """The cloud on the lockstep clock: one UAV's reports of a round, for its agent."""
        return f"{self.prefix}/uav/{uav}/measurement_round"

    @property
    def round_opened(self) -> str:
        """The cloud on the lockstep clock: whose uploads a round brings (world to cloud)."""
        return f"{self.prefix}/world/round"

    def measurements(self, uav: int | str) -> str:
        return f"{self.prefix}/uav/{uav}/measurements"

    # -- cloud ------------------------------------------------------------------------------
    @property
    def value_weights(self) -> str:
        return f"{self.prefix}/cloud/weights/value"

    @property
    def sinr_map(self) -> str:
        return f"{self.prefix}/cloud/weights/sinr_map"

    @property
    def round_closed(self) -> str:
        """The cloud on the lockstep clock: a round done, its maps' service (cloud to world)."""
        return f"{self.prefix}/cloud/round"

    @property
    def jammer_estimate(self) -> str:
        """The cloud's estimate of the jammer, put with each map corrected by one."""
        return f"{self.prefix}/cloud/jammer_estimate"

    # -- control, events, presence ----------------------------------------------------------
    @property
    def jammer_control(self) -> str:
        return f"{self.prefix}/control/jammer"

    def event(self, kind: str = "*") -> str:
        return f"{self.prefix}/event/{kind}"

    def alive(self, role: str = "*", ident: int | str = "*") -> str:
        """Liveliness token of a process (``alive()`` matches every process)."""
        return f"{self.prefix}/alive/{role}/{ident}"

    def status(self, role: str = "*", ident: int | str = "*") -> str:
        """Queryable through which a process reports its state (``status()``: all of them)."""
        return f"{self.prefix}/status/{role}/{ident}"

    @property
    def everything(self) -> str:
        return f"{self.prefix}/**"

    def last_chunk(self, key: str) -> str:
        return str(key).rsplit("/", 1)[-1]

    def role_and_id(self, key: str) -> tuple[str, str]:
        """(role, id) from an ``alive`` or ``status`` key."""
        role, ident = str(key).rsplit("/", 2)[-2:]
        return role, ident

"""The routers of a ``jamnav up`` system: one, or two linked over mutual TLS (the world and the
cloud on the first, the agents on the second). Where they listen unless told, whether a port is
free for one, the command line each is started with, and the certificates of their link."""

from __future__ import annotations

import socket
from pathlib import Path
from typing import TYPE_CHECKING

from shared import access, tls

if TYPE_CHECKING:  # the supervisor starts the routers with this module
    from jamnav.supervisor import UpConfig

# Whose logins each router of a two-router system accepts (``jamnav router --roles``).
ROUTER_ROLES = (f"{access.OPERATOR},{access.WORLD},{access.CLOUD}", "agent-*")
LINK_DIR = "tls"  # in the run directory: the routers' certificates and TLS settings


def next_endpoint(endpoint: str, step: int, protocol: str | None = None) -> str:
    """``endpoint`` ``step`` ports up (with another ``protocol``): where the second router and
    the link between the routers listen unless told."""
    proto, _, address = endpoint.partition("/")
    host, _, port = address.rpartition(":")
    return f"{protocol or proto}/{host}:{int(port) + step}"


def check_endpoint_free(endpoint: str, option: str = "--endpoint") -> None:
    """Refuse to start a router on a port in use (another ``jamnav up``?)."""
    proto, _, address = endpoint.partition("/")
    host, _, port = address.rpartition(":")
    if proto not in ("tcp", "tls") or not port.isdigit():
        return
    with socket.socket(socket.AF_INET6 if ":" in host.strip("[]") else socket.AF_INET) as probe:
        # As a listener binds: connections of a previous run in TIME_WAIT do not count.
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind((host.strip("[]"), int(port)))
        except OSError as exc:
            raise ValueError(f"{endpoint} is in use ({exc.strerror}): is another system "
                             f"running? choose {option}") from None


def credentials_argv(credentials: Path | None) -> list[str]:
    """How a child of a secure system is told where its login is; nothing on an open one."""
    return [] if credentials is None else ["--credentials", str(credentials)]


def router_argv(config: UpConfig, ident: int, credentials: Path | None,
                link_files: dict[str, tls.RouterCertificate]) -> list[str]:
    """``jamnav router``'s arguments for router ``ident``. With two routers, router 0 serves
    the supervisor, the world and the cloud and awaits router 1 on the TLS link; router 1
    serves the agents and links to router 0."""
    c = config
    argv = ["--prefix", c.prefix, "--id", str(ident)]
    if c.routers == 1:
        argv += ["--endpoint", c.endpoint]
    else:
        link = ["--listen" if ident == 0 else "--connect", c.link_endpoint]
        argv += ["--endpoint", c.endpoint if ident == 0 else c.agent_endpoint, *link,
                 "--zenoh-config", str(link_files[str(ident)].zenoh_config)]
    argv += credentials_argv(credentials)
    if credentials is not None and c.routers > 1:
        # The recorder logs in beside the supervisor.
        recorder = f",{access.RECORDER}" if ident == 0 and c.record is not None else ""
        argv += ["--roles", ROUTER_ROLES[ident] + recorder]
    return argv


def make_link_certificates(config: UpConfig) -> dict[str, tls.RouterCertificate]:
    """Two routers: a fresh authority and a certificate for each, valid for the link's host,
    with the routers' TLS settings, in the run directory's ``LINK_DIR``."""
    host = config.link_endpoint.partition("/")[2].rpartition(":")[0].strip("[]")
    return tls.make_router_certificates(config.run_dir / LINK_DIR, ["0", "1"],
                                        tuple(dict.fromkeys([*tls.LOOPBACK_NAMES, host])))

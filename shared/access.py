"""Who may do what on the bus: the logins of a secure system and the access rules its router
enforces (zenoh's user/password authentication and access control).

Every process logs in as its role (``operator``, ``world``, ``cloud``, ``agent-<uav>``,
``recorder``); the router accepts only the logins of the credentials file and, for each role,
exactly the traffic that role needs: only the operator moves the jammer, an agent publishes
only its own action and uploads only its own measurements, only the world publishes state and
observations, only the cloud publishes weights; the recorder only listens, to everything.
Denied traffic is dropped silently by the router.

A system of linked routers (one per host) spreads its roles over them: each router accepts the
logins of the roles that connect to it and enforces their rules, and trusts what a linked
router forwards. A linked router is known by its certificate (``LINKED_ROUTER``, signed by the
system's own authority: ``shared.tls``), and logs in as ``router`` to the router it connects to.
"""

from __future__ import annotations

import json
import os
import re
import secrets
import stat
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from fnmatch import fnmatchcase
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, RootModel, ValidationError, model_validator

from shared.events import (
    ChangeDetected,
    JammerChanged,
    JammerEstimated,
    RetrainFailed,
    RunFinished,
    SinrWeightsPublished,
    UavOutcomes,
    WeightsRefused,
)
from shared.topics import Topics

CREDENTIALS_FILE = "credentials.json"
OPERATOR, WORLD, CLOUD, ROUTER = "operator", "world", "cloud", "router"
RECORDER = "recorder"  # its liveliness token: <prefix>/alive/recorder/<pid>
# The common name of every router certificate of a system; only its authority signs one.
LINKED_ROUTER = "jamnav-router"
_ROLE = re.compile(r"^(operator|world|cloud|router|recorder|agent-(0|[1-9][0-9]*))$")
_AGENT = re.compile(r"^agent-([0-9]+)$")


class AccessError(ValueError):
    """Credentials that cannot be used; the text is one line."""


def agent_role(uav: int) -> str:
    return f"agent-{uav}"


def roles(uavs: int, linked: bool = False, recorder: bool = False) -> list[str]:
    """Every role of a system of ``uavs`` UAVs, with the routers' login if they are
    ``linked`` and the recorder's if it has one."""
    return [OPERATOR, WORLD, CLOUD, *(agent_role(uav) for uav in range(uavs)),
            *([ROUTER] if linked else []), *([RECORDER] if recorder else [])]


class Login(BaseModel):
    """A user and password that a client session presents to a secure system's router."""

    # The router reads logins as ``user:password`` lines: neither may hold a line break, and
    # the user no colon.
    model_config = ConfigDict(extra="forbid", frozen=True)
    user: str = Field(pattern=r"^[^\s:]+$", max_length=128)
    password: str = Field(pattern=r"^\S+$", min_length=16, max_length=256)

    def zenoh_settings(self) -> dict[str, Any]:
        """What a client session presents to its router."""
        return {"transport/auth/usrpwd/user": self.user,
                "transport/auth/usrpwd/password": self.password}


class Credentials(RootModel[dict[str, Login]]):
    """Role -> login."""

    model_config = ConfigDict(frozen=True)

    @model_validator(mode="after")
    def _known_roles_distinct_users(self) -> Credentials:
        for role in self.root:
            if not _ROLE.match(role):
                raise ValueError(f"unknown role {role!r}")
        users = [login.user for login in self.root.values()]
        if len(set(users)) != len(users):
            raise ValueError("two roles share a user")
        return self

    def login(self, role: str) -> Login:
        try:
            return self.root[role]
        except KeyError:
            raise AccessError(f"credentials: no login for role {role!r}") from None

    def only(self, patterns: list[str]) -> Credentials:
        """The logins of the roles that match one of the shell-style ``patterns``
        (``agent-*``); a pattern that matches no role is a mistake."""
        for pattern in patterns:
            if not any(fnmatchcase(role, pattern) for role in self.root):
                raise AccessError(f"credentials: no role matches {pattern!r}")
        return Credentials({role: login for role, login in self.root.items()
                            if any(fnmatchcase(role, pattern) for pattern in patterns)})


def generate(uavs: int, linked: bool = False) -> Credentials:
    """Fresh credentials for every role of a system of ``uavs`` UAVs (its ``linked`` routers
    and a recorder included); each user is its role."""
    return Credentials({role: Login(user=role, password=secrets.token_urlsafe(24))
                        for role in roles(uavs, linked, recorder=True)})


def write_private(path: Path, text: str) -> None:
    """Write ``path`` readable by its owner only, from its creation on: a temporary file made
    with mode 0600 then renamed over the target (a file already there keeps no other mode)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    descriptor, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    try:
        with os.fdopen(descriptor, "w", encoding="utf-8") as file:
            file.write(text)
        os.replace(temporary, path)
    except BaseException:
        os.unlink(temporary)
        raise


def save(credentials: Credentials, path: Path) -> None:
    write_private(path, json.dumps(credentials.model_dump(), indent=2) + "\n")


def load(path: str | Path, required: list[str] | tuple[str, ...] = ()) -> Credentials:
    """Read a credentials file that holds a login for every ``required`` role. Like ssh with a
    private key, a file that others may read is refused."""
    path = Path(path)
    try:
        mode = path.stat().st_mode
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise AccessError(f"credentials {path}: no such file") from None
    except OSError as exc:
        raise AccessError(f"credentials {path}: {exc.strerror}") from None
    except UnicodeDecodeError:
        raise AccessError(f"credentials {path}: not a credentials file (not UTF-8 text)") from None
    if mode & 0o077:
        raise AccessError(f"credentials {path}: open to group or others (mode "
                          f"{stat.S_IMODE(mode):04o}); chmod 600 it")
    try:
        credentials = Credentials.model_validate_json(text)
    except ValidationError as exc:
        error = exc.errors()[0]
        where = ".".join(str(part) for part in error["loc"])
        raise AccessError(f"credentials {path}: not a credentials file ("
                          f"{where + ': ' if where else ''}{error['msg']})") from None
    for role in required:
        if role not in credentials.root:
            raise AccessError(f"credentials {path}: no login for role {role!r}")
    return credentials


def login_for(path: str | Path | None, role: str) -> Login | None:
    """The login of ``role`` in the credentials file at ``path`` (None: no file, no login)."""
    return None if path is None else load(path, (role,)).login(role)


# -- the router's rules -------------------------------------------------------------------------
# What a session does, as the messages the router checks: at ingress for the sender, at egress
# for each receiver. A rule applies to a message only if its key expression includes the whole
# message key (wildcards included), and anything no rule allows is denied.
_CAPABILITIES: dict[str, tuple[tuple[str, tuple[str, ...]], ...]] = {
    "publish": (("ingress", ("put",)),),
    # A declared publisher sends nothing until it sees a matching subscription, and it sees
    # one only if its key expression (a wildcard too) is granted here.
    "see_subscribers": (("egress", ("declare_subscriber",)),),
    "subscribe": (("ingress", ("declare_subscriber",)), ("egress", ("put",))),
    "serve": (("ingress", ("declare_queryable", "reply")),),
    "be_asked": (("egress", ("query",)),),
    "ask": (("ingress", ("query",)), ("egress", ("reply",))),
    "announce": (("ingress", ("liveliness_token",)),),
    "watch": (("ingress", ("declare_liveliness_subscriber", "liveliness_query")),
              ("egress", ("liveliness_token",))),
}


def _events(topics: Topics, *kinds) -> list[str]:
    return [topics.event(kind.model_fields["type"].default) for kind in kinds]


def grants(topics: Topics, role: str) -> dict[str, list[str]]:
    """Capability -> key expressions, for one role. Publishers and queryables must also be
    reached by the wildcards the others use (the world's ``uav/*/action``, the operator's
    ``status/*/*``)."""
    weights = [topics.value_weights, topics.sinr_map]
    every_status = f"{topics.prefix}/status/**"
    if role == OPERATOR:  # the SINR map too: the console draws the map in service
        return {"ask": [topics.jammer_control, topics.sinr_map, every_status],
                "subscribe": [f"{topics.prefix}/event/**", topics.state,
                              topics.jammer_estimate, topics.sinr_map],
                "watch": [f"{topics.prefix}/alive/**"]}
    if role == RECORDER:  # what it hears is what a replay puts back: all of it
        return {"subscribe": [topics.everything], "announce": [topics.alive(RECORDER)]}
    if role == WORLD:
        rounds = [topics.measurement_round("*"), topics.round_opened]
        return {"publish": [topics.observation("*"), topics.state, *rounds,
                            *_events(topics, JammerChanged, UavOutcomes, RunFinished)],
                # The outcomes go out through a declared publisher (the world keeps them for
                # a supervisor that missed some): it must see the operator's subscription.
                "see_subscribers": [topics.observation("*"), topics.state, *rounds,
                                    f"{topics.prefix}/event/**"],
                "subscribe": [topics.action("*"), topics.round_closed],
                "serve": [topics.jammer_control, topics.status(WORLD, 0)],
                "be_asked": [topics.jammer_control, every_status],
                "announce": [topics.alive(WORLD, 0)],
                "watch": [f"{topics.prefix}/alive/agent/**"]}
    if role == CLOUD:
        desks = [*weights, topics.measurements("*")]
        return {"publish": [*weights, topics.jammer_estimate, topics.round_closed,
                            *_events(topics, ChangeDetected, JammerEstimated,
                                     SinrWeightsPublished, RetrainFailed)],
                "see_subscribers": [*weights, topics.jammer_estimate, topics.round_closed],
                "subscribe": [topics.round_opened, *_events(topics, JammerChanged)],
                "serve": [*desks, topics.status(CLOUD, 0)],
                "be_asked": [*desks, every_status],
                "announce": [topics.alive(CLOUD, 0)]}
    uav = _AGENT.match(role).group(1)
    return {"publish": [topics.action(uav), *_events(topics, WeightsRefused)],
            "see_subscribers": [topics.action("*")],
            "subscribe": [topics.observation(uav), topics.measurement_round(uav), *weights],
            "ask": [*weights, topics.measurements(uav)],
            "serve": [topics.status("agent", uav)],
            "be_asked": [every_status],
            "announce": [topics.alive("agent", uav)]}


def access_control(prefix: str, credentials: Credentials, linked: bool = False
                   ) -> dict[str, Any]:
    """The router's ``access_control`` section: deny by default, and one policy per role of
    ``credentials`` with the rules of its ``grants``. A ``linked`` router lets a router that
    presents a ``LINKED_ROUTER`` certificate pass anything under the prefix both ways: that
    router checked its own clients, and this one checks its own. The ``router`` login alone
    grants nothing."""
    topics = Topics(prefix)
    rules, subjects, policies = [], [], []
    for role, login in credentials.root.items():
        if role == ROUTER:
            continue
        ids = []
        for capability, keys in grants(topics, role).items():
            for flow, messages in _CAPABILITIES[capability]:
                ids.append(f"{role}_{capability}_{flow}")
                rules.append({"id": ids[-1], "messages": list(messages), "flows": [flow],
                              "permission": "allow", "key_exprs": keys})
        subjects.append({"id": role, "usernames": [login.user]})
        policies.append({"id": f"{role}_policy", "subjects": [role], "rules": ids})
    if linked:
        every_message = sorted({message for flows in _CAPABILITIES.values()
                                for _, messages in flows for message in messages})
        rules.append({"id": "linked_router_relay", "messages": every_message,
                      "flows": ["ingress", "egress"], "permission": "allow",
                      "key_exprs": [topics.everything]})
        subjects.append({"id": "linked_router", "cert_common_names": [LINKED_ROUTER]})
        policies.append({"id": "linked_router_policy", "subjects": ["linked_router"],
                         "rules": ["linked_router_relay"]})
    return {"enabled": True, "default_permission": "deny", "rules": rules,
            "subjects": subjects, "policies": policies}


@dataclass(frozen=True)
class Guard:
    """What a router enforces: the logins of ``credentials`` and the rules of ``prefix``,
    relaying for the routers it is ``linked`` with."""

    credentials: Credentials
    prefix: str
    linked: bool = False

    @contextmanager
    def zenoh_settings(self) -> Iterator[dict[str, Any]]:
        """The router's settings while it opens. Zenoh reads the logins from a file, once, as
        the router opens: the file lives in a private directory that is gone afterwards."""
        with tempfile.TemporaryDirectory(prefix="jamnav-logins-") as private:
            logins = Path(private) / "logins"
            write_private(logins, "".join(f"{login.user}:{login.password}\n"
                                          for login in self.credentials.root.values()))
            yield {"transport/auth/usrpwd/dictionary_file": str(logins),
                   "access_control": access_control(self.prefix, self.credentials,
                                                    self.linked)}

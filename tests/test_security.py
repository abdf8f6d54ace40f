"""Secure mode: the credentials file, the logins the router accepts, the access rules it
enforces (every role in this process, one session each), and ``jamnav up --secure`` for real."""

from __future__ import annotations

import json
import os
import signal
import stat
import threading
import time

import pytest
import zenoh

from jamnav.cli import main as jamnav
from shared import access, bus
from shared.topics import Topics
from tests.support import free_endpoint, gone, wait_until
from uav_agent.process import main as agent_main

# How long a denied message gets to show up after a later allowed one has arrived: the router
# forwards in order, so this only guards against a reordering we do not expect.
GRACE_S = 0.5


def run_cli(capsys, *argv: str):
    code = jamnav(list(argv))
    captured = capsys.readouterr()
    return code, captured.out, captured.err


# -- the credentials file -----------------------------------------------------------------------
def test_credentials_are_private_hold_every_role_and_bad_files_are_refused(tmp_path):
    path = tmp_path / "run" / access.CREDENTIALS_FILE
    access.save(access.generate(3), path)
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    credentials = access.load(path, access.roles(3))
    assert sorted(credentials.root) == ["agent-0", "agent-1", "agent-2", "cloud", "operator",
                                        "recorder", "world"]
    assert all(login.user == role for role, login in credentials.root.items())
    assert len({login.password for login in credentials.root.values()}) == 7

    def refused(path, roles=()) -> str:
        with pytest.raises(access.AccessError) as caught:
            access.load(path, roles)
        assert "\n" not in str(caught.value)
        return str(caught.value)

    assert "no such file" in refused(tmp_path / "absent.json")
    assert "no login for role 'agent-3'" in refused(path, access.roles(4))
    not_json = tmp_path / "not.json"
    not_json.write_text("{")
    not_json.chmod(0o600)
    assert "not a credentials file" in refused(not_json)
    path.chmod(0o640)
    assert "chmod 600" in refused(path)


def test_commands_refuse_unusable_credentials_with_one_line(tmp_path, capsys):
    path = tmp_path / access.CREDENTIALS_FILE
    access.save(access.generate(1), path)
    assert agent_main(["--credentials", str(path)]) == 2
    assert "needs --uav" in capsys.readouterr().err
    code, _, err = run_cli(capsys, "router", "--credentials", str(path), "--connect",
                           free_endpoint(), "--endpoint", free_endpoint())
    assert code == 2 and "no login for role 'router'" in err and err.count("\n") == 1
    path.chmod(0o644)
    code, _, err = run_cli(capsys, "status", "--credentials", str(path), "--endpoint",
                           free_endpoint())
    assert code == 2 and "chmod 600" in err and err.count("\n") == 1


# -- logins and access rules, every role in this process ---------------------------------------
class Inbox:
    """Keys (and payloads) received on a subscription, in order."""

    def __init__(self):
        self.items: list[tuple[str, bytes]] = []
        self._lock = threading.Lock()

    def __call__(self, sample) -> None:
        with self._lock:
            self.items.append((str(sample.key_expr), sample.payload.to_bytes()))

    def keys(self) -> list[str]:
        with self._lock:
            return [key for key, _ in self.items]

    def payloads(self) -> list[bytes]:
        with self._lock:
            return [payload for _, payload in self.items]


@pytest.fixture(scope="module")
def secure_bus():
    """A router enforcing the rules of 2 UAVs under ``jamnav``, and a session per role."""
    credentials, endpoint = access.generate(2), free_endpoint()
    router = bus.open_session("router", endpoint, guard=access.Guard(credentials, "jamnav"))
    sessions = {role: bus.open_session("client", endpoint, 2000,
                                       login=credentials.login(role))
                for role in access.roles(2)}
    yield endpoint, credentials, sessions
    for session in sessions.values():
        session.close()
    router.close()


def test_a_session_without_the_right_login_cannot_connect(secure_bus):
    endpoint, credentials, _ = secure_bus
    with pytest.raises(bus.BusError, match="a secure system needs --credentials"):
        bus.open_session("client", endpoint, 300)
    wrong = access.Login(user="operator", password="not-the-operator-password")
    with pytest.raises(bus.BusError, match="refused the login of 'operator'"):
        bus.open_session("client", endpoint, 300, login=wrong)
    unknown = access.Login(user="intruder", password=credentials.login("operator").password)
    with pytest.raises(bus.BusError, match="refused the login of 'intruder'"):
        bus.open_session("client", endpoint, 300, login=unknown)
    with pytest.raises(bus.BusError, match="cannot reach a router"):  # nobody listens there
        bus.open_session("client", free_endpoint(), 300, login=wrong)


def delivered(send, inbox: Inbox, payload: bytes) -> None:
    """Send ``payload`` until it arrives. Zenoh 1.10 may lose a put sent just as the publisher
    sees the subscription (with or without access control); denied messages sent after this
    went through would have arrived like it."""

    def arrived() -> bool:
        if payload in inbox.payloads():
            return True
        send(payload)
        return False

    wait_until(arrived, 5, f"{payload!r} delivered", every=0.05)


def test_an_agent_publishes_only_its_own_action(secure_bus):
    _, _, s = secure_bus
    topics = Topics()
    actions = Inbox()
    s["world"].declare_subscriber(topics.action("*"), actions)
    # Declared publishers, as an agent's: they see the world's wildcard subscription.
    own = bus.reliable_publisher(s["agent-1"], topics.action(1))
    other = bus.reliable_publisher(s["agent-1"], topics.action(0))
    delivered(own.put, actions, b"before")
    other.put(b"forged")
    s["agent-1"].put(topics.action(0), b"forged")
    delivered(own.put, actions, b"after")
    time.sleep(GRACE_S)
    assert set(actions.keys()) == {topics.action(1)} and b"forged" not in actions.payloads()


def test_only_the_world_publishes_state_and_only_the_cloud_weights(secure_bus):
    _, _, s = secure_bus
    topics = Topics()
    state, weights = Inbox(), Inbox()
    s["operator"].declare_subscriber(topics.state, state)
    s["agent-0"].declare_subscriber(topics.value_weights, weights)
    world_pub = s["world"].declare_publisher(topics.state)
    cloud_pub = bus.reliable_publisher(s["cloud"], topics.value_weights)
    delivered(world_pub.put, state, b"state")
    delivered(cloud_pub.put, weights, b"weights")
    s["agent-1"].put(topics.state, b"forged")
    s["agent-1"].put(topics.value_weights, b"forged")
    delivered(world_pub.put, state, b"later state")
    delivered(cloud_pub.put, weights, b"later weights")
    time.sleep(GRACE_S)
    assert b"forged" not in state.payloads() and b"forged" not in weights.payloads()


def test_only_the_cloud_publishes_the_jammer_estimate_and_the_operator_sees_it(secure_bus):
    _, _, s = secure_bus
    topics = Topics()
    estimates = Inbox()
    s["operator"].declare_subscriber(topics.jammer_estimate, estimates)
    cloud_pub = bus.reliable_publisher(s["cloud"], topics.jammer_estimate)
    delivered(cloud_pub.put, estimates, b"estimate")
    for role in ("world", "agent-0"):
        s[role].put(topics.jammer_estimate, b"forged")
    delivered(cloud_pub.put, estimates, b"later estimate")
    time.sleep(GRACE_S)
    assert b"forged" not in estimates.payloads()


def test_only_the_operator_controls_the_jammer_and_it_sees_every_status(secure_bus):
    _, _, s = secure_bus
    topics = Topics()
    asked = []

    def jammer_desk(query) -> None:
        asked.append(str(query.key_expr))
        query.reply(topics.jammer_control, b"jammer")

    s["world"].declare_queryable(topics.jammer_control, jammer_desk)
    statuses = {"world": topics.status("world", 0), "cloud": topics.status("cloud", 0),
                "agent-1": topics.status("agent", 1)}
    for role, key in statuses.items():
        s[role].declare_queryable(key, lambda query, key=key: query.reply(key, key.encode()))
    # An agent's queryable on the cloud's key is never declared to the others.
    forged = topics.status("cloud", 0)
    s["agent-0"].declare_queryable(forged, lambda query: query.reply(forged, b"forged"))

    def operator_asks(key: str) -> list[tuple[str, bytes]]:
        # Every reply, even two on one key (zenoh would otherwise keep one of them).
        replies = s["operator"].get(key, timeout=1.0, consolidation=zenoh.ConsolidationMode.NONE)
        return sorted((str(r.ok.key_expr), r.ok.payload.to_bytes())
                      for r in replies if r.ok is not None)

    def every_status() -> list | None:
        replies = operator_asks(topics.status())
        return replies if len(replies) >= len(statuses) else None

    replies = wait_until(every_status, 5, "every status")
    time.sleep(GRACE_S)
    assert operator_asks(topics.status()) == replies == sorted(
        (key, key.encode()) for key in statuses.values())

    wait_until(lambda: operator_asks(topics.jammer_control), 5, "the jammer desk")
    answered = len(asked)
    assert [r.ok for r in s["agent-1"].get(topics.jammer_control, timeout=1.0)] == []
    assert len(asked) == answered
    assert operator_asks(topics.jammer_control) == [(topics.jammer_control, b"jammer")]
    assert len(asked) == answered + 1


# -- jamnav up --secure ------------------------------------------------------------------------
def test_up_secure_flies_like_eval_and_needs_the_credentials(supervisor, capsys, tmp_path):
    endpoint, run_dir = free_endpoint(), tmp_path / "run"
    process = supervisor("--secure", "--uavs", "2", "--lockstep", "--map", "perfect",
                         "--jammer", "0,0,1", "--no-figures", "--endpoint", endpoint,
                         "--run-dir", str(run_dir))
    credentials = str(run_dir / access.CREDENTIALS_FILE)

    def status() -> list[dict]:
        code, out, _ = run_cli(capsys, "status", "--json", "--credentials", credentials,
                               "--endpoint", endpoint)
        return json.loads(out) if code == 0 else []

    def all_live() -> list[dict] | None:
        found = status()
        return found if len(found) == 5 else None

    live = wait_until(all_live, 90, "router, world, cloud and two agents live")
    assert sorted(p["role"] for p in live) == ["agent", "agent", "cloud", "router", "world"]
    assert stat.S_IMODE(os.stat(credentials).st_mode) == 0o600
    code, out, _ = run_cli(capsys, "jammer", "show", "--credentials", credentials,
                           "--endpoint", endpoint)
    assert code == 0 and [jammer["x"] for jammer in json.loads(out)["jammers"]] == [0.0]
    # A jammer a micrometre higher than the one in force (30 m) is a change, which goes the
    # whole way: world -> event -> cloud -> new true map -> every agent; but no level can
    # tell it apart (the SINR moves by under 1e-6 dB), so no outcome changes. Setting the
    # jammer in force itself would change nothing, and say nothing.
    code, out, _ = run_cli(capsys, "jammer", "set", "0,0,1,30.000001",
                           "--credentials", credentials, "--endpoint", endpoint)
    assert code == 0 and json.loads(out)["accepted"]
    wait_until(lambda: [p.get("sinr_version") for p in status()
                        if p["role"] in ("cloud", "agent")] == [2, 2, 2], 30,
               "the new map at the cloud and both agents")
    code, _, err = run_cli(capsys, "status", "--endpoint", endpoint)
    assert code == 1 and err.count("\n") == 1
    wait_until(lambda: any(p["role"] == "world" and p["episode"] >= 2 for p in status()), 60,
               "two episodes flown")

    process.send_signal(signal.SIGINT)
    out, err = process.communicate(timeout=60)
    assert process.returncode == 0, err[-2000:]
    assert f"credentials: {credentials}" in out
    report = json.loads((run_dir / "report.json").read_text())
    assert report["secure"] is True and report["dropped_messages"] == {}
    assert report["missed_deadlines"] == 0
    assert report["restarts"] == {"router": 0, "world": 0, "cloud": 0, "agent": 0}
    assert all(gone(p["pid"]) for p in report["processes"])
    episodes = report["episodes"]
    assert episodes >= 2
    code, out, _ = run_cli(capsys, "eval", "--method", "perfect", "--episodes", str(episodes),
                           "--uavs", "2", "--seed", "0", "--jammer", "0,0,1", "--per-episode",
                           "--json")
    assert code == 0 and report["outcomes"] == json.loads(out)["outcomes"]

"""Two routers linked over TLS with certificates both ways (mTLS): the certificates, the access
rules across the link, and ``jamnav up --routers 2`` for real, plain and ``--secure``."""

from __future__ import annotations

import json
import signal
import stat
import threading

import pytest
from cryptography import x509
from cryptography.exceptions import InvalidSignature
from cryptography.x509.oid import NameOID

from jamnav.cli import main as jamnav
from jamnav.routers import LINK_DIR
from shared import access, bus, tls
from shared.topics import Topics
from tests.support import free_endpoint, gone, wait_until

# How long a router gets to link before we conclude it cannot: a good one links in ~0.2 s.
LINK_WAIT_S = 2.0


def run_cli(capsys, *argv: str):
    code = jamnav(list(argv))
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def free_tls_endpoint() -> str:
    return "tls/" + free_endpoint().partition("/")[2]


def linked_router(endpoint: str, link: str, files: tls.RouterCertificate,
                  login: access.Login | None = None):
    """A router of its own that links to ``link`` with ``files``' certificate."""
    return bus.open_session("router", endpoint, routers=(link,), login=login,
                            base_file=str(files.zenoh_config))


def sees_the_world(router) -> bool:
    """Whether the world's token reaches ``router`` over its link within ``LINK_WAIT_S``."""

    def seen() -> bool:
        replies = router.liveliness().get(Topics().alive("world", 0), timeout=0.5)
        return any(reply.ok is not None for reply in replies)

    try:
        return wait_until(seen, LINK_WAIT_S, "the world's token")
    except AssertionError:
        return False


# -- certificates -------------------------------------------------------------------------------
def test_router_certificates_chain_to_a_fresh_authority_and_keys_are_private(tmp_path):
    files = tls.make_router_certificates(tmp_path / "a", ["0", "1"])
    other = tls.make_router_certificates(tmp_path / "b", ["0"])
    authority = x509.load_pem_x509_certificate(files["0"].authority.read_bytes())
    assert authority.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    for router in files.values():
        certificate = x509.load_pem_x509_certificate(router.certificate.read_bytes())
        certificate.verify_directly_issued_by(authority)
        assert certificate.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value == (
            access.LINKED_ROUTER)
        names = certificate.extensions.get_extension_for_class(x509.SubjectAlternativeName)
        assert "localhost" in names.value.get_values_for_type(x509.DNSName)
        assert stat.S_IMODE(router.private_key.stat().st_mode) == 0o600
        assert json.loads(router.zenoh_config.read_text())["transport"]["link"]["tls"][
            "enable_mtls"] is True
    stranger = x509.load_pem_x509_certificate(other["0"].certificate.read_bytes())
    with pytest.raises(InvalidSignature):
        stranger.verify_directly_issued_by(authority)


# -- access rules across the link ---------------------------------------------------------------
class Received:
    def __init__(self):
        self.payloads: list[bytes] = []
        self._lock = threading.Lock()

    def __call__(self, sample) -> None:
        with self._lock:
            self.payloads.append(sample.payload.to_bytes())

    def __contains__(self, payload: bytes) -> bool:
        with self._lock:
            return payload in self.payloads


def test_each_router_enforces_its_own_clients_rules_across_the_link(tmp_path):
    """The world and the cloud's router and the agents' router, each with the logins of its
    own clients: an agent's forged action and an agent's subscription to another UAV's
    observations are refused by the agents' router, while the allowed traffic crosses."""
    credentials, topics = access.generate(2, linked=True), Topics()
    files = tls.make_router_certificates(tmp_path, ["0", "1"])
    hub, spoke, link = free_endpoint(), free_endpoint(), free_tls_endpoint()
    hub_guard = access.Guard(credentials.only(["world", "router"]), "jamnav", linked=True)
    spoke_guard = access.Guard(credentials.only(["agent-*"]), "jamnav", linked=True)
    sessions = [bus.open_session("router", hub, listeners=(link,), guard=hub_guard,
                                 base_file=str(files["0"].zenoh_config))]
    try:
        sessions.append(bus.open_session("router", spoke, routers=(link,), guard=spoke_guard,
                                         login=credentials.login(access.ROUTER),
                                         base_file=str(files["1"].zenoh_config)))
        with pytest.raises(bus.BusError, match="refused the login of 'world'"):
            bus.open_session("client", spoke, 300, login=credentials.login("world"))
        world, agent0, agent1 = (bus.open_session("client", endpoint, 2000,
                                                  login=credentials.login(role))
                                 for endpoint, role in ((hub, "world"), (spoke, "agent-0"),
                                                        (spoke, "agent-1")))
        sessions += [world, agent0, agent1]
        actions, seen_by_0, seen_by_1 = Received(), Received(), Received()
        world.declare_subscriber(topics.action("*"), actions)
        agent0.declare_subscriber(topics.observation(0), seen_by_0)
        agent1.declare_subscriber(topics.observation(0), seen_by_1)
        own, forged = agent1.declare_publisher(topics.action(1)), agent1.declare_publisher(
            topics.action(0))
        observation = world.declare_publisher(topics.observation(0))

        def crossed() -> bool:
            forged.put(b"forged")
            own.put(b"own")
            observation.put(b"observation")
            return b"own" in actions and b"observation" in seen_by_0

        wait_until(crossed, 5, "an action and an observation across the link", every=0.05)
        assert b"forged" not in actions and b"observation" not in seen_by_1
    finally:
        for session in reversed(sessions):
            session.close()


# -- jamnav up --routers 2 ----------------------------------------------------------------------
def up_report(supervisor, tmp_path, name: str, *argv: str) -> dict:
    run_dir = tmp_path / name
    process = supervisor("--lockstep", "--episodes", "3", "--uavs", "3", "--seed", "4",
                         "--map", "perfect", "--jammer", "0,0,1", "--no-figures",
                         "--endpoint", free_endpoint(), "--run-dir", str(run_dir), *argv)
    _, err = process.communicate(timeout=120)
    assert process.returncode == 0, err[-2000:]
    return json.loads((run_dir / "report.json").read_text())


def test_two_routers_fly_the_episodes_of_one(supervisor, tmp_path):
    one = up_report(supervisor, tmp_path, "one")
    two = up_report(supervisor, tmp_path, "two", "--routers", "2", "--agent-endpoint",
                    free_endpoint(), "--link-endpoint", free_tls_endpoint())
    assert one["routers"] == 1 and two["routers"] == 2
    assert sorted(p["role"] for p in two["processes"]).count("router") == 2
    assert all(gone(p["pid"]) for p in two["processes"])

    def flights(report: dict) -> list[tuple]:
        return [(e["episode"], e["seed"], e["steps"], e["outcomes"])
                for e in report["events"] if e["type"] == "uav_outcomes"]

    assert len(flights(one)) == 3 and flights(two) == flights(one)
    assert two["outcomes"] == one["outcomes"]
    assert two["measurements"]["taken"] == one["measurements"]["taken"] > 0
    assert two["dropped_messages"] == {} and two["missed_deadlines"] == 0
    for router in ("router-0", "router-1"):
        key = tmp_path / "two" / LINK_DIR / f"{router}.key"
        assert stat.S_IMODE(key.stat().st_mode) == 0o600


def test_secure_two_routers_refuse_wrong_logins_and_strange_routers_and_fly(
        supervisor, capsys, tmp_path):
    endpoint, agents, link = free_endpoint(), free_endpoint(), free_tls_endpoint()
    run_dir = tmp_path / "run"
    process = supervisor("--secure", "--routers", "2", "--uavs", "2", "--lockstep", "--map",
                         "perfect", "--jammer", "0,0,1", "--no-figures", "--endpoint", endpoint,
                         "--agent-endpoint", agents, "--link-endpoint", link,
                         "--run-dir", str(run_dir))
    credentials_path = run_dir / access.CREDENTIALS_FILE

    def live() -> list[dict] | None:
        code, out, _ = run_cli(capsys, "status", "--json", "--credentials",
                               str(credentials_path), "--endpoint", endpoint)
        found = json.loads(out) if code == 0 else []
        return found if len(found) == 6 else None

    found = wait_until(live, 90, "two routers, world, cloud and two agents live")
    assert sorted(f"{p['role']}-{p['id']}" for p in found) == [
        "agent-0", "agent-1", "cloud-0", "router-0", "router-1", "world-0"]
    credentials = access.load(credentials_path)
    for at in (endpoint, agents):
        wrong = access.Login(user="operator", password="not-the-operator-password")
        with pytest.raises(bus.BusError, match="refused the login"):
            bus.open_session("client", at, 300, login=wrong)
    # Each router holds only the logins of its own clients.
    with pytest.raises(bus.BusError, match="refused the login of 'agent-0'"):
        bus.open_session("client", endpoint, 300, login=credentials.login("agent-0"))
    with pytest.raises(bus.BusError, match="refused the login of 'world'"):
        bus.open_session("client", agents, 300, login=credentials.login("world"))

    # With the routers' login, a router links only with a certificate of the run's authority.
    router_login = credentials.login(access.ROUTER)
    strange = tls.make_router_certificates(tmp_path / "strange", ["0"])["0"]
    with linked_router(free_endpoint(), link, strange, router_login) as router:
        assert not sees_the_world(router)
    ours = tls.RouterCertificate(*(run_dir / LINK_DIR / name for name in (
        "router-1.pem", "router-1.key", tls.CA_FILE, "router-1.json5")))
    with linked_router(free_endpoint(), link, ours, router_login) as router:
        assert sees_the_world(router)

    wait_until(lambda: any(p["role"] == "world" and p["episode"] >= 2 for p in live() or []),
               60, "two episodes flown")
    process.send_signal(signal.SIGINT)
    _, err = process.communicate(timeout=60)
    assert process.returncode == 0, err[-2000:]
    report = json.loads((run_dir / "report.json").read_text())
    assert report["secure"] is True and report["routers"] == 2
    assert report["restarts"] == {"router": 0, "world": 0, "cloud": 0, "agent": 0}
    assert report["dropped_messages"] == {} and report["missed_deadlines"] == 0
    assert all(gone(p["pid"]) for p in report["processes"])
    code, out, _ = run_cli(capsys, "eval", "--method", "perfect", "--episodes",
                           str(report["episodes"]), "--uavs", "2", "--seed", "0", "--jammer",
                           "0,0,1", "--per-episode", "--json")
    assert report["episodes"] >= 2 and code == 0
    assert report["outcomes"] == json.loads(out)["outcomes"]


# -- bad input ----------------------------------------------------------------------------------
@pytest.mark.parametrize("argv, message", [
    (("up", "--agent-endpoint", "tcp/127.0.0.1:7600"), "add --routers 2"),
    (("up", "--routers", "2", "--link-endpoint", "tcp/127.0.0.1:7600"), "link over TLS"),
    (("up", "--routers", "2", "--endpoint", "tcp/127.0.0.1:7600", "--agent-endpoint",
      "tcp/127.0.0.1:7600"), "three different ports"),
    (("router", "--roles", "agent-*"), "give both"),
])
def test_two_router_options_refuse_mistakes_with_one_line(capsys, argv, message):
    code, _, err = run_cli(capsys, *argv)
    assert code == 2 and message in err and err.count("\n") == 1


def test_a_router_refuses_roles_it_has_no_login_for_and_a_busy_agent_port(capsys, tmp_path):
    path = tmp_path / access.CREDENTIALS_FILE
    access.save(access.generate(1, linked=True), path)
    code, _, err = run_cli(capsys, "router", "--credentials", str(path), "--roles", "agnet-*",
                           "--endpoint", free_endpoint())
    assert code == 2 and "no role matches 'agnet-*'" in err and err.count("\n") == 1
    endpoint = free_endpoint()
    with bus.open_session("router", endpoint):
        code, _, err = run_cli(capsys, "up", "--routers", "2", "--endpoint", free_endpoint(),
                               "--agent-endpoint", endpoint, "--run-dir", str(tmp_path / "run"))
    assert code == 2 and "choose --agent-endpoint" in err and err.count("\n") == 1

"""The console without a browser or a bus: what it folds from the messages into the state its
API returns, the jammer commands it makes of a request body, the maps it draws, and where it
listens (a taken port, the token file)."""

from __future__ import annotations

import base64
import json
import socket
import stat

import numpy as np
import pytest

from jamnav.cli import main as jamnav
from jamnav.console import listen
from jamnav.console.maps import CoverageMaps
from jamnav.console.state import TIMELINE_IN_FRAME, ConsoleState, jammer_request
from planning.networks import sha256
from shared.cloud_messages import RasterGrid, SinrMap
from shared.events import (
    ChangeDetected,
    JammerChanged,
    RunFinished,
    SinrWeightsPublished,
    UavOutcomes,
)
from shared.jammer_messages import JammerEstimate, JammerInfo, JammerPlace
from shared.radio import JammerParams, RadioModel
from shared.shipped import SINR_MAP_NO_JAMMER
from shared.wire import decode, encode
from shared.world_messages import WorldState

T = 1_700_000_000.0


def world_state(episode: int, step: int, positions, statuses=None, destinations=()):
    return WorldState(episode=episode, step=step, clock="realtime", t=T + step,
                      position=positions, velocity=[(0.0, 0.0)] * len(positions),
                      sinr_db=[0.0] * len(positions), level=[1] * len(positions),
                      status=statuses or ["active"] * len(positions),
                      destination=list(destinations))


def online_map(version: int) -> SinrMap:
    data = SINR_MAP_NO_JAMMER.read_bytes()
    return SinrMap(version=version, sha256=sha256(data), data=data, mode="online", accuracy=0.9)


def test_the_state_follows_the_fleet_with_trails_that_restart_each_episode():
    state = ConsoleState()
    assert state.snapshot()["uavs"] == [] and state.snapshot()["episode"] is None
    state.on_world_state(world_state(3, 0, [(0.0, 0.0), (10.0, -5.0)],
                                     destinations=[(40.0, 40.0), (-40.0, 0.0)]))
    state.on_world_state(world_state(3, 1, [(1.0, 0.5), (10.0, -5.0)],
                                     statuses=["active", "success"]))
    view = state.snapshot(trails=True)
    assert (view["episode"], view["step"], view["clock"]) == (3, 1, "realtime")
    assert view["uavs"] == [
        {"id": 0, "x": 1.0, "y": 0.5, "status": "active", "destination": None},
        {"id": 1, "x": 10.0, "y": -5.0, "status": "success", "destination": None}]
    # A UAV that stayed put adds nothing to its trail.
    assert view["trails"] == [[[0.0, 0.0], [1.0, 0.5]], [[10.0, -5.0]]]
    state.on_world_state(world_state(4, 0, [(-20.0, 3.0), (5.0, 5.0)],
                                     destinations=[(1.0, 2.0), (3.0, 4.0)]))
    view = state.snapshot(trails=True)
    assert view["trails"] == [[[-20.0, 3.0]], [[5.0, 5.0]]]
    assert [u["destination"] for u in view["uavs"]] == [[1.0, 2.0], [3.0, 4.0]]
    assert "trails" not in state.snapshot()


def test_events_count_outcomes_once_follow_the_jammer_and_fill_the_timeline():
    state = ConsoleState()
    state.on_event(UavOutcomes(t=T, source="world", episode=0, seed=1, steps=20,
                               outcomes=["success", "disconnection", "success"]))
    # The world sends an episode's outcomes again after a router restart: counted once.
    state.on_event(UavOutcomes(t=T, source="world", episode=0, seed=1, steps=20,
                               outcomes=["success", "disconnection", "success"]))
    state.on_event(UavOutcomes(t=T, source="world", episode=1, seed=2, steps=60,
                               outcomes=["timeout", "collision", "collision"]))
    assert not state.jammer_known
    state.on_event(JammerChanged(t=T + 1, source="world", episode=2, step=7,
                                 jammers=[JammerInfo(x=25, y=-10, power_w=1, height_m=30)]))
    state.on_event(ChangeDetected(t=T + 2, source="cloud", version=3, accuracy=0.8))
    state.on_event(RunFinished(t=T + 3, source="world", episodes=2, steps=80, seconds=4,
                               steps_per_second=20, missed_deadlines=0))
    view = state.snapshot()
    assert view["counters"] == {"episodes": 2, "success": 2, "disconnection": 1,
                                "collision": 2, "timeout": 1}
    assert view["jammers"] == [{"id": 0, "x": 25.0, "y": -10.0, "power_w": 1.0, "on": True,
                                "path": None}]
    assert view["finished"] is True
    assert [(e["seq"], e["kind"], e["t"], e["text"]) for e in view["timeline"]] == [
        (1, "jammer_changed", T + 1, "jammer moved to (25, -10), 1 W (episode 2, step 7)"),
        (2, "change_detected", T + 2, "change detected: map v3 right on 80% of recent uploads")]
    state.on_event(JammerChanged(t=T + 4, source="world", episode=3, step=0, jammers=[]))
    assert state.snapshot()["jammers"] == [] and state.jammer_known


def test_a_provisional_map_carries_the_jammers_counted_before_they_are_placed():
    state = ConsoleState()
    assert (state.snapshot()["map_provisional"], state.snapshot()["jammers_counted"]) == (
        False, None)

    def published(version: int, provisional: bool, counted: int | None) -> SinrWeightsPublished:
        return SinrWeightsPublished(t=T + version, source="cloud", version=version,
                                    accuracy=0.9, sha256="0" * 64, path="m.safetensors",
                                    provisional=provisional, jammers_counted=counted)

    state.on_event(published(4, True, 2))
    view = state.snapshot()
    assert (view["map_provisional"], view["jammers_counted"]) == (True, 2)
    assert view["timeline"][-1]["text"] == ("provisional SINR map v4 published, 2 jammers "
                                            "counted, not placed yet (held-out accuracy 90.0%)")
    state.on_event(published(5, False, 2))  # the estimate's map: the count placed
    assert state.snapshot()["map_provisional"] is False


def test_the_world_state_says_which_jammers_are_in_force_and_an_older_one_says_nothing():
    state = ConsoleState()
    state.on_world_state(world_state(0, 1, [(0.0, 0.0)]))  # a recording from before it said
    assert not state.jammer_known
    still = JammerInfo(x=25, y=-10, power_w=1, height_m=30)
    convoy = JammerInfo(id=2, x=-40, y=0, power_w=0.5, height_m=20,
                        path={"waypoints": [(40.0, 0.0)], "speed_mps": 3.0})
    said = world_state(0, 2, [(0.0, 0.0)]).model_copy(update={
        "jammers_in_force": [still, convoy], "jammer_known": True,
        "jammer_places": [JammerPlace(id=0, x=25, y=-10, on=False),
                          JammerPlace(id=2, x=-34, y=0, on=True)]})
    state.on_world_state(decode(WorldState, encode(said)))  # as it comes over the wire
    # The true map is drawn under the jammers transmitting, where they are now.
    assert state.current_jammers() == (True, (JammerParams(-34.0, 0.0, 0.5, 20.0),))
    assert state.snapshot()["jammers"][1] == {"id": 2, "x": -34.0, "y": 0.0, "power_w": 0.5,
                                              "on": True, "path": [[-40.0, 0.0], [40.0, 0.0]]}
    state.on_world_state(world_state(0, 3, [(0.0, 0.0)]).model_copy(
        update={"jammer_known": True}))
    assert state.current_jammers() == (True, ())


def test_a_state_recorded_with_one_jammer_replays_as_a_list():
    recorded = world_state(0, 2, [(0.0, 0.0)]).model_dump(mode="json", exclude={
        "jammers_in_force", "jammer_places"})
    one = {"x": 25.0, "y": -10.0, "power_w": 1.0, "height_m": 30.0}
    state = WorldState.model_validate({**recorded, "jammer_in_force": one, "jammer_known": True})
    assert [jammer.model_dump(include=set(one)) for jammer in state.jammers_in_force] == [one]
    assert WorldState.model_validate({**recorded, "jammer_in_force": None}).jammers_in_force == []


def test_the_frame_keeps_the_newest_timeline_entries_and_is_encoded_once_per_change():
    state = ConsoleState()
    for n in range(TIMELINE_IN_FRAME + 5):
        state.on_presence(f"agent-{n}", False, T + n)
    state.on_presence("agent-3", True, T + 99)
    state.on_presence("agent-99", True, T + 99)  # first seen: not a restart
    timeline = state.snapshot()["timeline"]
    assert len(timeline) == TIMELINE_IN_FRAME
    assert timeline[-1]["text"] == "agent-3 is back (restarted)"
    assert timeline[-2]["text"] == f"agent-{TIMELINE_IN_FRAME + 4} went away"
    revision, frame = state.encoded_frame()
    assert state.encoded_frame()[1] is frame
    assert json.loads(frame) == state.snapshot()
    state.on_estimate(JammerEstimate(map_version=4, t=T, present=True, x=1.0, y=2.0,
                                     power_w=0.5, sd_x_m=1.5, sd_y_m=2.5, sd_power_db=1.0,
                                     measurements=300))
    later, frame = state.encoded_frame()
    assert later > revision
    assert json.loads(frame)["estimate"] == {
        "present": True, "id": 0, "x": 1.0, "y": 2.0, "power_w": 0.5, "sd_x_m": 1.5,
        "sd_y_m": 2.5, "sd_power_db": 1.0, "vx_mps": None, "vy_mps": None, "map_version": 4,
        "measurements": 300, "others": []}


def test_a_map_no_newer_than_the_one_in_service_is_ignored():
    state = ConsoleState()
    assert state.on_map(online_map(2))
    assert not state.on_map(online_map(2)) and not state.on_map(online_map(1))
    assert state.snapshot()["map_version"] == 2
    assert state.on_map(online_map(5)) and state.snapshot()["map_version"] == 5
    assert state.snapshot()["maps"] == {}
    state.set_map("served", {"version": 5})
    state.set_map("served", {"version": 6})
    assert state.snapshot()["maps"] == {"served": 2}
    assert state.map_payload("served") == {"version": 6, "serial": 2}
    assert state.map_payload("true") is None


def command(action, id=None, x=None, y=None, power_w=None) -> dict:
    return {"action": action, "id": id, "x": x, "y": y, "power_w": power_w, "height_m": None}


@pytest.mark.parametrize(("body", "expected"), [
    ({"x": -25, "y": 15.5, "power_w": 1}, command("set", x=-25.0, y=15.5, power_w=1.0)),
    ({"x": -25, "y": 15.5, "power_w": 1, "add": True},
     command("add", x=-25.0, y=15.5, power_w=1.0)),
    ({"id": 2, "x": 3, "y": -4}, command("move", id=2, x=3.0, y=-4.0)),
    ({"remove": 1}, command("remove", id=1)),
    ({"off": True}, command("off")),
])
def test_a_request_body_becomes_the_worlds_command(body, expected):
    assert jammer_request(body).model_dump() == expected


@pytest.mark.parametrize(("body", "reason"), [
    ([1, 2, 3], "expected a JSON object"),
    ({"off": False}, "expected one of"),
    ({"off": True, "x": 1}, "expected one of"),
    ({"x": 1, "y": 2}, "expected one of"),
    ({"x": 1, "y": 2, "power_w": 1, "height_m": 5}, "expected one of"),
    ({"x": 1, "y": 2, "power_w": 1, "add": False}, '"add" is true or left out'),
    ({"x": "1", "y": 2, "power_w": 1}, "must be numbers"),
    ({"x": True, "y": 2, "power_w": 1}, "must be numbers"),
    ({"x": 1, "y": 2, "power_w": -1}, "power and height >= 0"),
    ({"x": 1, "y": 2, "power_w": 1001}, "power at most 1000 W"),
    ({"x": float("inf"), "y": 2, "power_w": 1}, "must be finite"),
    ({"remove": "1"}, "a jammer's id is a whole number"),
    ({"remove": 7}, "a jammer's id is 0 to 3"),
    ({"id": True, "x": 1, "y": 2}, "a jammer's id is a whole number"),
])
def test_a_bad_request_body_is_refused_with_one_line(body, reason):
    with pytest.raises(ValueError, match=reason) as refused:
        jammer_request(body)
    assert "\n" not in str(refused.value)


def test_the_maps_are_the_worlds_truth_and_what_the_cloud_serves(scenario):
    maps = CoverageMaps(scenario)
    area = scenario.area
    x, y = maps.points[..., 0], maps.points[..., 1]
    assert maps.points.shape == (100, 100, 2) and maps.spacing == 1.0
    assert x.min() == area.x_min + 0.5 and y.max() == area.y_max - 0.5
    radio = RadioModel(scenario)
    nearest_station = radio.evaluate(np.array(scenario.gbs.positions)).level
    assert (nearest_station > 0).all()
    free = maps.true(())
    jammed = maps.true((JammerParams(0.0, 0.0, 20.0, 30.0),))
    centre = (np.abs(x) < 5) & (np.abs(y) < 5)
    assert (jammed <= free).all() and (jammed[centre] == 0).all()
    assert (free > 0).mean() > 0.8
    # The shipped no-jammer network agrees with the no-jammer truth (README: 99 %).
    assert (maps.served(online_map(1)) == free).mean() > 0.95
    # A raster map (perfect, outdated) is read at its nearest nodes: level 1 east of x = 0.
    grid = RasterGrid(x0=-60, y0=-60, spacing=2, rows=61, cols=61)
    raster = np.where(np.arange(61) * 2 - 60 > 0, 1, 0).astype(np.int8)[None, :].repeat(61, 0)
    data = raster.tobytes()
    served = maps.served(SinrMap(version=1, sha256=sha256(data), data=data, mode="perfect",
                                 grid=grid))
    assert (served == (x > 1).astype(int)).all()
    payload = maps.payload(served, version=1)
    levels = np.frombuffer(base64.b64decode(payload["levels"]), dtype=np.int8)
    assert payload["version"] == 1 and (payload["rows"], payload["cols"]) == (100, 100)
    assert (levels.reshape(100, 100) == served).all()


def held_port() -> socket.socket:
    holder = socket.socket()
    holder.bind(("127.0.0.1", 0))
    holder.listen()
    return holder


def test_a_taken_default_port_gives_way_and_a_taken_chosen_one_is_an_error(monkeypatch):
    with held_port() as holder:
        port = holder.getsockname()[1]
        with pytest.raises(ValueError, match=f"127.0.0.1:{port} cannot be used") as refused:
            listen.open_listener(f"127.0.0.1:{port}")
        assert "\n" not in str(refused.value)
        # As if this port were the default (8470 may come and go with other systems here).
        monkeypatch.setattr(listen, "DEFAULT_WEB", f"127.0.0.1:{port}")
        listener, address = listen.open_listener(None)
        with listener:
            assert address.port not in (port, 0) and address.taken_default == port
            assert listener.getsockname()[1] == address.port
    for bad in ("8470", "127.0.0.1:", "127.0.0.1:70000", ":8470"):
        with pytest.raises(ValueError, match="expected HOST:PORT"):
            listen.parse_web(bad)
    assert listen.parse_web("[::1]:9000").url("abc") == "http://[::1]:9000/?token=abc"


def test_a_console_takes_the_listening_socket_it_is_handed():
    """`jamnav up` holds its console's socket from its checks on and hands it down: a console
    serves on it, and what is no listening TCP socket is refused."""
    with held_port() as holder:
        inherited = listen.inherited_listener(holder.dup().detach())
        with inherited, socket.create_connection(holder.getsockname(), timeout=5):
            accepted, _ = inherited.accept()
            accepted.close()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as datagram:
        with pytest.raises(ValueError, match="not a listening TCP socket"):
            listen.inherited_listener(datagram.dup().detach())


def test_the_commands_refuse_a_taken_port_with_one_line(capsys, tmp_path):
    with held_port() as holder:
        web = f"127.0.0.1:{holder.getsockname()[1]}"
        for argv in (["up", "--web", web, "--run-dir", str(tmp_path / "run")],
                     ["console", "--web", web]):
            assert jamnav(argv) == 2
            err = capsys.readouterr().err
            assert f"--web {web} cannot be used" in err and err.count("\n") == 1
    assert not (tmp_path / "run").exists()


def test_the_token_file_is_private_and_one_open_to_others_is_refused(tmp_path):
    path = tmp_path / "run" / listen.TOKEN_FILE
    token = listen.token_for(path)
    assert stat.S_IMODE(path.stat().st_mode) == 0o600 and len(token) >= 32
    assert listen.token_for(path) == token == listen.read_token(path)
    assert listen.new_token(path) != token
    path.chmod(0o644)
    with pytest.raises(ValueError, match="chmod 600"):
        listen.read_token(path)


@pytest.mark.parametrize(("argv", "reason"), [
    (["--web", "nowhere"], "expected HOST:PORT"),
    (["--web", "127.0.0.1:0"], "expected HOST:PORT"),
    (["--token-file", "{tmp}/token"], "only a secure system's console"),
    (["--credentials", "{tmp}/absent.json"], "no such file"),
    (["--scenario", "no-such-world"], "no-such-world"),
    (["--prefix", "bad prefix"], "bus prefix"),
])
def test_the_console_refuses_bad_arguments_with_one_line(argv, reason, capsys, tmp_path):
    argv = [arg.replace("{tmp}", str(tmp_path)) for arg in argv]
    assert jamnav(["console", *argv]) == 2
    err = capsys.readouterr().err
    assert reason in err and err.count("\n") == 1

"""Messages on the wire: round trips, refusal of anything invalid, topics, the zenoh-cli codec."""

from __future__ import annotations

import hashlib
import json
import pickle

import msgpack
import numpy as np
import pytest

from shared.cloud_messages import MeasurementUpload, RasterGrid, SinrMap, ValueWeights
from shared.events import UavOutcomes, decode_event
from shared.jammer_messages import JammerCommand, JammerEstimate, JammerInfo
from shared.measurements import Measurement
from shared.observation import Observation
from shared.topics import Topics
from shared.wire import MessageError, decode, encode
from shared.world_messages import Action, AgentObservation, MeasurementRound
from shared.zenoh_cli_codec import zenoh_cli_decoder, zenoh_cli_encoder
from tests.support import upload_of
from world_sim.core import VectorWorld, episode_seed


def test_an_observation_row_survives_the_wire_bit_for_bit(scenario):
    world = VectorWorld(scenario, 1, 5)
    world.reset([0], [episode_seed(0, 3)])
    world.step(np.full((1, 5), 2.0), world.heading + 0.3)
    fleet = Observation.of_fleet(world.position, world.velocity, world.heading,
                                 world.destination, world.radius, world.max_speed, world.level,
                                 world.below_steps, world.active, world.steps)
    for uav in range(5):
        message = decode(AgentObservation, encode(AgentObservation.of_row(fleet, uav, 7, uav)))
        got, want = message.observation(), fleet.select(np.array([uav]))
        for name, value in vars(want).items():
            received = getattr(got, name)
            assert received.dtype == value.dtype and received.shape == value.shape, name
            np.testing.assert_array_equal(received, value, err_msg=name)
        assert (message.episode, message.uav) == (7, uav)


@pytest.mark.parametrize("payload, fragment", [
    (b"\xc1", "not msgpack"),
    (msgpack.packb([1, 2]), "expected a map"),
    (msgpack.packb({"episode": 0, "step": 0, "uav": 0, "speed": float("nan"), "heading": 0}),
     "finite"),
    (msgpack.packb({"episode": 0, "step": 0, "uav": 0, "speed": -1.0, "heading": 0}),
     "speed"),
    (msgpack.packb({"episode": 0, "step": 0, "uav": 1024, "speed": 1.0, "heading": 0}), "uav"),
    (msgpack.packb({"episode": 0, "step": 0, "uav": 0, "speed": 1.0, "heading": 0, "x": 1}),
     "x"),
    (msgpack.packb({"episode": 0, "step": 0, "uav": 0, "speed": 1.0,
                    "heading": msgpack.ExtType(1, b"x")}), "heading"),
    (pickle.dumps({"episode": 0}), ""),
    (b"\x80" * 70_000, "exceeds"),
])
def test_invalid_payloads_are_one_line_errors(payload, fragment):
    with pytest.raises(MessageError) as caught:
        decode(Action, payload)
    assert fragment in str(caught.value) and "\n" not in str(caught.value)


def test_weights_must_match_their_digest_and_rasters_their_grid():
    data = b"weights"
    good = ValueWeights(version=2, sha256=hashlib.sha256(data).hexdigest(), data=data)
    assert decode(ValueWeights, encode(good)) == good
    forged = msgpack.packb({**good.model_dump(), "data": b"weightz"})
    with pytest.raises(MessageError, match="digest"):
        decode(ValueWeights, forged)
    levels = np.zeros((3, 4), dtype=np.int8).tobytes()
    grid = RasterGrid(x0=-1.0, y0=-1.0, spacing=0.5, rows=3, cols=4)
    raster = SinrMap(version=1, mode="perfect", sha256=hashlib.sha256(levels).hexdigest(),
                     data=levels, grid=grid)
    assert decode(SinrMap, encode(raster)).levels().shape == (3, 4)
    short = msgpack.packb({**raster.model_dump(), "data": levels[:-1],
                           "sha256": hashlib.sha256(levels[:-1]).hexdigest()})
    with pytest.raises(MessageError, match="rows x cols"):
        decode(SinrMap, short)


def test_uploads_and_jammer_commands_have_limits():
    record = Measurement(id="a", source="uav-0", step=0, time=1.0, features=[0.0] * 20, level=1)
    reported = record.model_copy(update={"id": "b", "sinr_db": -2.5})
    upload = upload_of(0, [record, reported])
    assert upload.batch().records() == [record, reported]
    assert upload.sinr_db == [None, -2.5]
    columns = msgpack.unpackb(encode(upload))
    with pytest.raises(MessageError, match="ids"):
        decode(MeasurementUpload, msgpack.packb({**columns, "ids": [], "steps": [], "times": [],
                                                 "features": b"", "levels": [], "sinr_db": []}))
    with pytest.raises(MessageError, match="one value per id"):
        decode(MeasurementUpload, msgpack.packb({**columns, "levels": [1]}))
    for features in (columns["features"][:-1], columns["features"][:-4], b""):
        with pytest.raises(MessageError, match="features"):
            decode(MeasurementUpload, msgpack.packb({**columns, "features": features}))
    for bad in (float("nan"), 1e9, "loud"):
        with pytest.raises(MessageError, match="sinr_db"):
            decode(MeasurementUpload, msgpack.packb({**columns, "sinr_db": [None, bad]}))
    round_ = {"round": 1, "episode": 0, "step": 1, "uav": 0, "flown_s": 1.0,
              "measured": [(0.0, 0.0, 1), (1.0, 0.0, 2)]}
    assert decode(MeasurementRound, msgpack.packb({**round_, "measured_db": [-2.5, 0.0]}))
    with pytest.raises(MessageError, match="2 reports"):
        decode(MeasurementRound, msgpack.packb({**round_, "measured_db": [-2.5]}))
    with pytest.raises(ValueError, match="set needs"):
        JammerCommand(action="set", x=1.0)
    with pytest.raises(ValueError, match="takes no"):
        JammerCommand(action="off", power_w=1.0)
    assert JammerInfo.parse("1,2,0.5", 30.0) == JammerInfo(x=1, y=2, power_w=0.5, height_m=30)
    for bad in ("1,2", "1,2,nan", "1,2,-1", "a,b,c"):
        with pytest.raises(ValueError, match="jammer"):
            JammerInfo.parse(bad, 30.0)


def test_events_decode_by_type():
    event = UavOutcomes(t=1.0, source="world", episode=3, seed=9, steps=20,
                        outcomes=["success", "timeout"])
    assert decode_event(encode(event)) == event
    with pytest.raises(MessageError, match="event"):
        decode_event(msgpack.packb({"type": "unknown", "t": 1.0, "source": "x"}))


def test_topics_live_under_one_prefix():
    topics = Topics()
    assert topics.jammer_control == "jamnav/control/jammer"
    assert topics.action(3) == "jamnav/uav/3/action"
    assert topics.event("jammer_changed") == "jamnav/event/jammer_changed"
    assert Topics("lab/one").state == "lab/one/world/state"
    with pytest.raises(ValueError, match="prefix"):
        Topics("bad prefix/**")


def test_the_zenoh_cli_codec_prints_json_and_encodes_commands():
    data = b"\x00" * 10
    weights = ValueWeights(version=1, sha256=hashlib.sha256(data).hexdigest(), data=data)
    printed = json.loads(zenoh_cli_decoder("k", encode(weights)))
    assert printed["data"] == "<10 bytes>" and printed["version"] == 1
    command = zenoh_cli_encoder("k", '{"action": "set", "x": 1, "y": 2, "power_w": 0.5}')
    assert decode(JammerCommand, command).power_w == 0.5


def test_an_estimate_of_several_jammers_numbers_each_on_the_wire():
    """The cloud's set goes out as the first jammer with the others beside it, numbered in
    the set's order; a set that breaks the message's rules is refused in one line."""
    from cloud_service.estimated_jammer import JammerEstimate as Estimated
    from cloud_service.estimated_jammer import estimated_set
    from cloud_service.process import estimate_message

    first = Estimated(True, 3.0, -7.0, 0.8, 9.0, 4.0, 2.0, 1.5, 500, 30.0, 3.0)
    second = Estimated(True, -20.0, 12.0, 0.5, 7.0, 1.0, 3.0, 0.5, 500, 20.0, 0.0)
    message = estimate_message(estimated_set([first, second]), 4, 10.0)
    decoded = decode(JammerEstimate, encode(message))
    assert [(m.id, m.x, m.y, m.power_w) for m in decoded.members] == [
        (0, 3.0, -7.0, 0.8), (1, -20.0, 12.0, 0.5)]
    assert decoded.map_version == decoded.others[0].map_version == 4
    assert estimate_message(first, 4, 10.0).others == []
    assert estimate_message(Estimated(False, None, None, None, None, None, None, None, 9, 0.0),
                            4, 10.0).members == []
    fields = message.model_dump()
    for broken, fragment in (({**fields, "present": False, "x": None, "y": None,
                               "power_w": None}, "no others"),
                             ({**fields, "others": [{**fields["others"][0], "id": 0}]},
                              "its own id")):
        with pytest.raises(MessageError, match=fragment):
            decode(JammerEstimate, msgpack.packb(broken))


def test_an_empty_rounds_upload_is_an_empty_batch():
    upload = upload_of(2, [], round_number=7)
    assert (upload.round, len(upload.batch()), upload.newest()) == (7, 0, 0.0)

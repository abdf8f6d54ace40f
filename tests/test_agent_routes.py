"""An agent's route fields stay few however long it flies one map."""

from __future__ import annotations

import logging

import numpy as np

from planning.networks import sha256
from shared.cloud_messages import SinrMap, ValueWeights
from shared.shipped import EXTENDED_VALUE_NET
from shared.survey_maps import sinr_map_for
from shared.world_messages import AgentObservation
from uav_agent.process import ROUTE_FIELDS_KEPT, Models


def test_an_agent_keeps_a_few_route_fields_however_many_missions_it_flies(scenario):
    """Every mission's destination gets its field; an agent keeps only the last few, where an
    in-process flight keeps thousands (a fleet's destinations). Twelve missions on one map:
    without the bound, twelve fields."""
    models = Models(scenario, logging.getLogger("agent"))
    value, sinr = EXTENDED_VALUE_NET.read_bytes(), sinr_map_for(scenario).read_bytes()
    models.accept(ValueWeights(version=1, sha256=sha256(value), data=value))
    models.accept(SinrMap(version=1, sha256=sha256(sinr), data=sinr, mode="online"))
    rng = np.random.default_rng(2)
    for destination in rng.uniform(-45, 45, size=(12, 2)).tolist():
        seen = AgentObservation(
            episode=0, step=1, uav=0, position=(0.0, 0.0), velocity=(0.0, 0.0), heading=0.0,
            destination=tuple(destination), radius=1.0, max_speed=5.0, level=2,
            below_steps=0, others_position=[], others_velocity=[], others_radius=[],
            others_present=[])
        models.policy.decide(seen.observation(), models.radio_map)
    routes = models.radio_map.first.routes(scenario)
    assert len(routes.cache) == ROUTE_FIELDS_KEPT
    assert len(routes.store) <= ROUTE_FIELDS_KEPT


def test_on_the_lockstep_clock_an_agent_flies_the_version_the_world_names(scenario):
    """Without the clock the newest map flies and only it is kept. Once a round pins the
    agent, newer maps are held (not due yet) until the world names one; a version that can
    never come (older than all held) is stood in for by the oldest held, and one that may
    still come is waited for."""
    class Built:  # what a map is flown with; the agent only keeps and hands it over
        pass

    def commit(models: Models, version: int) -> Built:
        built = Built()
        models.commit(_Version(version), built)
        return built

    free = Models(scenario, logging.getLogger("test"))
    commit(free, 0)
    newest = commit(free, 1)
    assert free.radio_map is newest and free.sinr_version == 1 and set(free.maps) == {1}

    clocked = Models(scenario, logging.getLogger("test"))
    first = commit(clocked, 0)
    clocked.pin()
    held = [commit(clocked, v) for v in (1, 2, 3)]
    assert clocked.radio_map is first and set(clocked.maps) == {0, 1, 2, 3}
    assert clocked.fly_version(2) and clocked.radio_map is held[1]
    assert set(clocked.maps) == {2, 3}  # the versions before the one named never fly again
    assert clocked.fly_version(1) and clocked.sinr_version == 2
    assert not clocked.fly_version(4) and clocked.sinr_version == 2


class _Version:
    """A SINR map update as ``Models.commit`` reads it: its version."""

    def __init__(self, version: int):
        self.version = version

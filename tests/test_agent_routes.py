"""An agent's route fields stay few however long it flies one map."""

from __future__ import annotations

import logging

import numpy as np

from shared.messages import AgentObservation, SinrMap, ValueWeights
from shared.networks import sha256
from shared.shipped import EXTENDED_VALUE_NET, sinr_map_for
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

"""The PettingZoo wrapper of the world: API conformance, seeding, episodes, errors."""

from __future__ import annotations

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test

from shared.outcomes import OUTCOME_LABELS
from shared.scenario import MAX_JAMMERS, SCENARIO_DIR, ScenarioError, load_scenario
from world_sim import parallel_env

FINAL = {"success", "disconnection", "collision", "timeout"}


def toward_destination(env) -> dict[str, int]:
    """For every live agent, the action whose next position is nearest its destination."""
    world, actions = env.world, {}
    for agent in env.agents:
        j = env.possible_agents.index(agent)
        speed, heading = env.action_set.candidates(world.heading[0, j])
        speed, heading = env.action_set.clip(speed, heading, world.heading[0, j])
        step = np.stack([speed * np.cos(heading), speed * np.sin(heading)], axis=-1) * world.dt
        miss = np.hypot(*(world.position[0, j] + step - world.destination[0, j]).T)
        actions[agent] = int(np.argmin(miss))
    return actions


def test_parallel_api():
    parallel_api_test(parallel_env(), num_cycles=200)


def test_import_from_package_and_scenario_arguments():
    by_name = parallel_env("icc2021")
    by_path = parallel_env(SCENARIO_DIR / "icc2021.toml")
    by_str_path = parallel_env(str(SCENARIO_DIR / "icc2021.toml"))
    by_object = parallel_env(load_scenario(), num_uavs=2)
    assert by_name.metadata["name"] == "jamnav_v0"
    assert by_name.possible_agents == ["uav_0", "uav_1", "uav_2", "uav_3"]
    assert by_object.possible_agents == ["uav_0", "uav_1"]
    obs_name, _ = by_name.reset(seed=3)
    obs_path, _ = by_path.reset(seed=3)
    by_str_path.reset(seed=3)
    for agent, obs in obs_name.items():
        np.testing.assert_array_equal(obs, obs_path[agent])


def test_spaces_and_observation_layout():
    env = parallel_env(num_uavs=3)
    j_n = env.scenario.policy.observed_uavs
    obs, infos = env.reset(seed=0)
    for agent in env.possible_agents:
        assert env.observation_space(agent) is env.observation_space(agent)
        assert env.action_space(agent) is env.action_space(agent)
        assert env.action_space(agent).n == len(env.action_set)
        space = env.observation_space(agent)
        assert space.dtype == np.float32 and space.shape == (10 + 6 * j_n,)
        assert obs[agent].dtype == np.float32 and space.contains(obs[agent])
        assert infos[agent]["outcome"] == "active"
        assert np.isfinite(infos[agent]["sinr_db"])
    w, o = env.world, obs["uav_1"]
    np.testing.assert_allclose(o[0:2], w.position[0, 1], rtol=1e-6)
    np.testing.assert_allclose(o[5:7], w.destination[0, 1], rtol=1e-6)
    assert o[7] == env.scenario.uav.radius_m and o[8] == env.scenario.uav.max_speed_mps
    others = o[10:].reshape(j_n, 6)
    # Two other UAVs are present (nearest first); the remaining slots are zero padding.
    assert others[:2, 5].tolist() == [1.0, 1.0] and not others[2:].any()
    assert np.hypot(*others[0, :2]) <= np.hypot(*others[1, :2])
    assert env.state().dtype == np.float32 and env.state_space.contains(env.state())


def test_same_seed_same_actions_same_observations():
    a, b = parallel_env(), parallel_env()
    obs_a, _ = a.reset(seed=11)
    obs_b, _ = b.reset(seed=11)
    rng = np.random.default_rng(0)
    while True:
        assert obs_a.keys() == obs_b.keys()
        for agent in obs_a:
            np.testing.assert_array_equal(obs_a[agent], obs_b[agent])
        if not a.agents:
            break
        actions = {agent: int(rng.integers(len(a.action_set))) for agent in a.agents}
        obs_a, rew_a, *_ = a.step(actions)
        obs_b, rew_b, *_ = b.step(actions)
        assert rew_a == rew_b
    assert not b.agents
    # Unseeded resets continue the seeded run reproducibly; another seed gives other missions.
    second_a, _ = a.reset()
    second_b, _ = b.reset()
    np.testing.assert_array_equal(second_a["uav_0"], second_b["uav_0"])
    other, _ = a.reset(seed=12)
    assert not np.array_equal(other["uav_0"], second_a["uav_0"])


@pytest.mark.parametrize("jammer", [None, (0.0, 0.0, 1.0)])
def test_heading_for_destination_ends_every_mission(jammer):
    env = parallel_env()
    outcomes: dict[str, str] = {}
    for seed in range(5):
        env.reset(seed=seed, options={"jammer": jammer})
        for _ in range(env.world.step_limit):
            alive = list(env.agents)
            obs, rewards, terms, truncs, infos = env.step(toward_destination(env))
            assert set(obs) == set(rewards) == set(terms) == set(truncs) == set(infos) == set(alive)
            for agent in alive:
                assert env.observation_space(agent).contains(obs[agent])
                assert infos[agent]["outcome"] in OUTCOME_LABELS
                ended = terms[agent] or truncs[agent]
                assert ended == (agent not in env.agents)
                assert ended == (infos[agent]["outcome"] in FINAL)
                assert truncs[agent] == (infos[agent]["outcome"] == "timeout")
                if ended:
                    outcomes[f"{seed}/{agent}"] = infos[agent]["outcome"]
            if not env.agents:
                break
        assert env.agents == []
        assert env.step({}) == ({}, {}, {}, {}, {})
    assert len(outcomes) == 5 * len(env.possible_agents)
    assert set(outcomes.values()) <= FINAL
    if jammer is None:
        assert "success" in outcomes.values()


def jammer_slots(env) -> np.ndarray:
    """The state's tail: [x, y, power_w] of each jammer slot."""
    return env.state()[-3 * MAX_JAMMERS:].reshape(MAX_JAMMERS, 3)


def test_the_jammers_option_sets_several_and_moves_them_along_their_paths():
    env = parallel_env()
    convoy = {"x": -40.0, "y": 0.0, "power_w": 0.5,
              "path": {"waypoints": [[40.0, 0.0]], "speed_mps": 3.0}}
    env.reset(seed=4, options={"jammers": [(10.0, -20.0, 1.0), convoy]})
    assert jammer_slots(env)[:2].tolist() == [[10.0, -20.0, 1.0], [-40.0, 0.0, 0.5]]
    for _ in range(10):
        env.step({})
    # 10 steps of the scenario's step, at 3 m/s along +x; the still one has stayed.
    moved = -40.0 + 3.0 * 10 * env.scenario.timing.step_s
    # float64 along the leg, then the state's float32: -10 m is exact in both.
    assert jammer_slots(env)[1, 0] == pytest.approx(moved, abs=1e-9)
    assert jammer_slots(env)[0].tolist() == [10.0, -20.0, 1.0]
    env.reset(options={"jammers": []})
    assert not jammer_slots(env).any()


@pytest.mark.parametrize(("jammers", "said"), [
    ([(0.0, 0.0, 1.0)] * 5, "at most 4"),
    ([{"x": 0.0, "y": 0.0, "power_w": 1.0,
       "path": {"waypoints": [[500.0, 0.0]], "speed_mps": 3.0}}], "outside the area"),
    ([{"x": 0.0, "y": 0.0, "power_w": 1.0,
       "path": {"waypoints": [[10.0, 0.0]], "speed_mps": -3.0}}], "speed_mps"),
    ([{"x": 0.0, "y": 0.0, "power_w": 1.0,
       "schedule": {"kind": "duty", "on_s": 0.0, "off_s": 5.0}}], "on_s"),
])
def test_bad_jammers_are_refused_in_one_line(jammers, said):
    env = parallel_env()
    with pytest.raises(ValueError, match=said) as caught:
        env.reset(seed=0, options={"jammers": jammers})
    assert "\n" not in str(caught.value)


def test_hovering_times_out_and_jammer_option():
    env = parallel_env()
    _, jammed = env.reset(seed=4, options={"jammer": (0.0, 0.0, 1.0)})
    assert jammer_slots(env)[:, 2].tolist() == [1.0, 0.0, 0.0, 0.0]
    _, clear = env.reset(seed=4, options={"jammer": None})
    assert not jammer_slots(env).any()
    for agent in env.possible_agents:
        assert clear[agent]["sinr_db"] >= jammed[agent]["sinr_db"]
    truncated = set()
    for _ in range(env.world.step_limit):
        _, _, terms, truncs, infos = env.step({})  # absent agents hover
        truncated |= {agent for agent, flag in truncs.items() if flag}
        if not env.agents:
            break
    assert not env.agents
    connected = {a for a in env.possible_agents if clear[a]["sinr_db"] > -3.0}
    assert connected and connected <= truncated
    with pytest.raises(ValueError):
        env.reset(options={"jammer": (0.0, 0.0)})


@pytest.mark.parametrize("action", [46, -1, 1.5, 1.0, float("nan"), float("inf"), None, "1",
                                    True, [1], np.array([1, 2]), np.float64(2.0)])
def test_an_invalid_action_is_refused_naming_the_agent_and_the_space(action):
    env = parallel_env()
    env.reset(seed=0)
    before = env.world.position.copy()
    with pytest.raises(ValueError, match=r"uav_1: action .* is not in Discrete\(46\)"):
        env.step({"uav_0": 0, "uav_1": action})
    assert np.array_equal(env.world.position, before)  # nothing moved


@pytest.mark.parametrize("action", [3, np.int64(3), np.array(3)])
def test_every_integer_form_of_an_action_flies_the_same(action):
    env = parallel_env()
    env.reset(seed=0)
    plain = env.step({"uav_0": 3})[0]["uav_0"]
    env.reset(seed=0)
    assert np.array_equal(env.step({"uav_0": action})[0]["uav_0"], plain)


def test_bad_seeds_options_and_arguments_are_refused():
    env = parallel_env()
    for seed in (1.5, -1, 2**32, "3", True):
        with pytest.raises(ValueError, match="seed"):
            env.reset(seed=seed)
    with pytest.raises(ValueError, match="expected a dict"):
        env.reset(options=[1])
    for jammer in ((float("nan"), 0.0, 1.0), (0.0, 0.0, -1.0)):
        with pytest.raises(ValueError, match="must be finite, power and height >= 0"):
            env.reset(options={"jammer": jammer})
    env.reset(seed=0)
    with pytest.raises(TypeError, match="expected a dict"):
        env.step([1, 1, 1, 1])
    with pytest.raises(TypeError, match="scenario 5"):
        parallel_env(5)
    with pytest.raises(TypeError, match="num_uavs"):
        parallel_env(num_uavs=2.5)


def test_rgb_render():
    env = parallel_env(num_uavs=2, render_mode="rgb_array")
    env.reset(seed=0)
    frame = env.render()
    assert frame.dtype == np.uint8 and frame.ndim == 3 and frame.shape[2] == 3
    env.close()


def test_bad_scenario_raises():
    with pytest.raises(ScenarioError):
        parallel_env("no_such_scenario")
    with pytest.raises(ScenarioError):
        parallel_env(SCENARIO_DIR / "missing.toml")

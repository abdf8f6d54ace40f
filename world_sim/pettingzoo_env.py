"""A PettingZoo ``ParallelEnv`` over one environment of :class:`world_sim.core.VectorWorld`.

A thin wrapper with no physics of its own: the world moves the UAVs, measures the SINR, books
rewards and outcomes; this module only translates discrete actions into commanded speeds and
headings and the world's arrays into per-agent observations.

Agents are ``"uav_0" .. "uav_{J-1}"``. An agent leaves ``agents`` in the step its mission ends:
``terminated`` for success, disconnection or collision, ``truncated`` for a timeout.

Action (per agent): ``Discrete(len(ActionSet))``; action ``a`` commands speed
``action_set.speeds[a]`` and heading ``current heading + action_set.turns[a]`` (action 0 hovers
and keeps the heading). Agents missing from the action dict hover.

Observation (per agent): a float32 vector of ``10 + 6 * J_n`` entries, with
``J_n = scenario.policy.observed_uavs``:

====  ==============  ======================================================================
idx   name            meaning
====  ==============  ======================================================================
0-1   x, y            own position (m)
2-3   vx, vy          own velocity (m/s), within +-max_speed
4     heading         own heading (rad), within [-pi, pi]
5-6   dest_x, dest_y  own destination (m), inside the scenario area
7     radius          own radius (m)
8     max_speed       own maximum speed (m/s)
9     sinr_level      quantized SINR level, 0 (below T_s) .. level_count - 1
====  ==============  ======================================================================

then, for each of the ``J_n`` nearest other *active* UAVs (nearest first), 6 entries
``[dx, dy, vx, vy, radius, present]``: position relative to the agent (m), the other's velocity
(m/s), its radius (m) and ``present = 1``. Missing slots are all zeros (``present = 0``).

Seeding: ``reset(seed=s)`` starts episode ``episode_seed(s, 0)``; each later ``reset()`` without
a seed starts the next episode of the same run, ``episode_seed(s, k)``. Without any seed the
run's master seed is drawn at random (and exposed as ``master_seed``).

Jammers: ``reset(options={"jammer": (x, y, power_w)})`` sets one still jammer (height from the
scenario), ``{"jammer": None}`` switches every jammer off, and ``{"jammers": [...]}`` sets up to
4, each ``(x, y, power_w)`` or a mapping of a scenario's ``[[jammers]]`` entry (with a ``path``
or ``schedule``). The setting persists over later resets until changed; the initial jammers are
the scenario's. The global state ends with ``[x, y, power_w]`` of each of 4 jammer slots
(power 0: off or absent), where they are now.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv
from pydantic import ValidationError

from shared.outcomes import Outcome
from shared.radio import JammerParams
from shared.scenario import MAX_JAMMERS, SEED_MAX, Jammer, Scenario, load_scenario
from world_sim.core import VectorWorld, episode_seed

# The observation's entries, in order (the table above): the UAV's own, then each other's.
# Not the value network's joint state (planning.features), which turns the world toward the
# destination: a PettingZoo policy learns from the world's frame.
OWN_ENTRIES = ("x", "y", "vx", "vy", "heading", "dest_x", "dest_y", "radius", "max_speed",
               "sinr_level")
OTHER_ENTRIES = ("dx", "dy", "vx", "vy", "radius", "present")
_TERMINATING = (int(Outcome.SUCCESS), int(Outcome.DISCONNECTION), int(Outcome.COLLISION))


def _is_integer(value: Any) -> bool:
    """An int, a numpy integer or a 0-d integer array; never a bool, float or string."""
    if isinstance(value, np.ndarray):
        return value.ndim == 0 and np.issubdtype(value.dtype, np.integer)
    return isinstance(value, int | np.integer) and not isinstance(value, bool | np.bool_)


def parallel_env(
    scenario: str | Path | Scenario | None = None,
    num_uavs: int | None = None,
    render_mode: str | None = None,
) -> JamnavParallelEnv:
    """The jamnav world as a PettingZoo parallel environment (see the module docstring)."""
    return JamnavParallelEnv(scenario, num_uavs=num_uavs, render_mode=render_mode)


class JamnavParallelEnv(ParallelEnv):
    """The world as a PettingZoo parallel environment: one environment of ``VectorWorld``,
    discrete actions and per-UAV observations as the module docstring lays them out."""

    metadata = {
        "name": "jamnav_v0",
        "render_modes": ["human", "rgb_array"],
        "is_parallelizable": True,
    }

    def __init__(
        self,
        scenario: str | Path | Scenario | None = None,
        num_uavs: int | None = None,
        render_mode: str | None = None,
    ):
        if not isinstance(scenario, Scenario | str | Path | None):
            raise TypeError(f"scenario {scenario!r}: expected a Scenario, a scenario name or "
                            "a TOML path")
        if not isinstance(scenario, Scenario):
            scenario = load_scenario(scenario)
        if num_uavs is not None and not _is_integer(num_uavs):
            raise TypeError(f"num_uavs {num_uavs!r}: expected an integer")
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode {render_mode!r} not in {self.metadata['render_modes']}")
        self.scenario = scenario
        self.render_mode = render_mode
        self.world = VectorWorld(scenario, num_envs=1, num_uavs=num_uavs)
        self.action_set = self.world.actions
        self.num_uavs = self.world.num_uavs
        self.observed_uavs = scenario.policy.observed_uavs
        self.possible_agents = [f"uav_{j}" for j in range(self.num_uavs)]
        self.agents: list[str] = []
        self._index = {agent: j for j, agent in enumerate(self.possible_agents)}
        self.master_seed: int | None = None
        self._episode = 0
        # One space object per agent, returned as is on every call (the API test checks it).
        self._observation_spaces = {
            agent: self._build_observation_space() for agent in self.possible_agents
        }
        self._action_spaces = {
            agent: spaces.Discrete(len(self.action_set)) for agent in self.possible_agents
        }
        self.state_space = spaces.Box(
            -np.inf, np.inf, shape=(self.num_uavs * (len(OWN_ENTRIES) + 1) + 3 * MAX_JAMMERS,),
            dtype=np.float32
        )

    # -- spaces ------------------------------------------------------------------------------
    def _build_observation_space(self) -> spaces.Box:
        area, uav = self.scenario.area, self.scenario.uav
        inf, v = np.inf, uav.max_speed_mps
        top_level = self.scenario.channel.level_count - 1
        own = {"x": (-inf, inf), "y": (-inf, inf), "vx": (-v, v), "vy": (-v, v),
               "heading": (-math.pi, math.pi), "dest_x": (area.x_min, area.x_max),
               "dest_y": (area.y_min, area.y_max), "radius": (0.0, inf),
               "max_speed": (0.0, inf), "sinr_level": (0.0, top_level)}
        other = {"dx": (-inf, inf), "dy": (-inf, inf), "vx": (-v, v), "vy": (-v, v),
                 "radius": (0.0, inf), "present": (0.0, 1.0)}
        bounds = ([own[name] for name in OWN_ENTRIES]
                  + [other[name] for name in OTHER_ENTRIES] * self.observed_uavs)
        return spaces.Box(np.array([low for low, _ in bounds], dtype=np.float32),
                          np.array([high for _, high in bounds], dtype=np.float32),
                          dtype=np.float32)

    def observation_space(self, agent: str) -> spaces.Box:
        return self._observation_spaces[agent]

    def action_space(self, agent: str) -> spaces.Discrete:
        return self._action_spaces[agent]

    # -- episode -----------------------------------------------------------------------------
    def reset(
        self, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, dict[str, Any]]]:
        if seed is not None:
            if not _is_integer(seed) or not 0 <= seed <= SEED_MAX:
                raise ValueError(f"seed {seed!r}: expected an integer from 0 to {SEED_MAX}")
            self.master_seed = int(seed)
            self._episode = 0
        elif self.master_seed is None:
            self.master_seed = int(np.random.SeedSequence().generate_state(1)[0])
            self._episode = 0
        else:
            self._episode += 1
        # Other keys are ignored, as PettingZoo's API test expects of every environment.
        if options is not None and not isinstance(options, dict):
            raise ValueError(f"options {options!r}: expected a dict such as "
                             "{'jammer': (x, y, power_w)}")
        if options and "jammer" in options:
            self.world.set_jammer(0, self._jammer_from(options["jammer"]))
        if options and "jammers" in options:
            self.world.set_jammers(0, self._jammers_from(options["jammers"]))
        self.world.reset([0], [episode_seed(self.master_seed, self._episode)])
        self.agents = self.possible_agents[:]
        own = self._own_entries()
        observations = {agent: self._observe(self._index[agent], own) for agent in self.agents}
        infos = {agent: self._info(self._index[agent]) for agent in self.agents}
        if self.render_mode == "human":
            self.render()
        return observations, infos

    def _jammer_from(self, value: Any) -> JammerParams | None:
        if value is None:
            return None
        try:
            x, y, power_w = (float(v) for v in value)
        except (TypeError, ValueError):
            raise ValueError(
                f"options['jammer'] must be (x, y, power_w) or None, got {value!r}"
            ) from None
        # VectorWorld.set_jammer refuses what is not finite or of negative power.
        return JammerParams(x, y, power_w, self.scenario.jammer.height_m)

    def _jammers_from(self, value: Any) -> tuple[Jammer, ...]:
        """Each entry as a scenario's jammer (the first one's height and efficiency unless
        given), checked as a scenario file would be: inside the area, at most 4."""
        if not isinstance(value, list | tuple):
            raise ValueError(f"options['jammers'] must be a list, got {value!r}")
        if not value:
            return ()
        entries = []
        for entry in value:
            if isinstance(entry, dict):
                entries.append({**self.scenario.jammer.model_dump(), "path": None,
                                "schedule": None, **entry})
            elif entry is None:
                raise ValueError("options['jammers']: an entry is None (no jammers: an empty list)")
            else:
                x, y, power_w = self._jammer_from(entry)[:3]
                entries.append({**self.scenario.jammer.model_dump(), "x": x, "y": y,
                                "power_w": power_w, "path": None, "schedule": None})
        try:
            return Scenario.model_validate({**self.scenario.model_dump(),
                                            "jammers": entries}).jammers
        except ValidationError as exc:
            first = exc.errors()[0]
            where = ".".join(str(part) for part in first["loc"])
            raise ValueError(f"options['jammers']: {where}: {first['msg']}") from None

    def step(
        self, actions: dict[str, Any]
    ) -> tuple[
        dict[str, np.ndarray],
        dict[str, float],
        dict[str, bool],
        dict[str, bool],
        dict[str, dict[str, Any]],
    ]:
        if not isinstance(actions, dict):
            raise TypeError(f"actions: expected a dict of agent -> action, got "
                            f"{type(actions).__name__}")
        if not self.agents:
            return {}, {}, {}, {}, {}
        world = self.world
        speed = np.zeros((1, self.num_uavs))
        heading = world.heading.copy()
        for agent, action in actions.items():
            j = self._index.get(agent)
            if j is None:
                raise KeyError(f"unknown agent {agent!r}")
            if agent not in self.agents:
                continue  # finished agents stay put whatever they are told
            if not _is_integer(action) or not 0 <= action < len(self.action_set):
                raise ValueError(f"{agent}: action {action!r} is not in {self.action_space(agent)}")
            a = int(action)
            speed[0, j] = self.action_set.speeds[a]
            heading[0, j] += self.action_set.turns[a]
        result = world.step(speed, heading)

        alive = self.agents
        status = world.status[0]
        own = self._own_entries()
        observations = {agent: self._observe(self._index[agent], own) for agent in alive}
        rewards = {agent: float(result.reward[0, self._index[agent]]) for agent in alive}
        terminations = {agent: bool(status[self._index[agent]] in _TERMINATING) for agent in alive}
        truncations = {
            agent: bool(status[self._index[agent]] == Outcome.TIMEOUT) for agent in alive
        }
        infos = {agent: self._info(self._index[agent]) for agent in alive}
        self.agents = [agent for agent in alive if status[self._index[agent]] == Outcome.ACTIVE]
        if self.render_mode == "human":
            self.render()
        return observations, rewards, terminations, truncations, infos

    # -- views of the world ------------------------------------------------------------------
    def _own_entries(self) -> np.ndarray:
        """Every UAV's own entries (J, len(OWN_ENTRIES)), in OWN_ENTRIES' order."""
        w = self.world
        columns = {"x": w.position[0, :, 0], "y": w.position[0, :, 1],
                   "vx": w.velocity[0, :, 0], "vy": w.velocity[0, :, 1], "heading": w.heading[0],
                   "dest_x": w.destination[0, :, 0], "dest_y": w.destination[0, :, 1],
                   "radius": w.radius[0], "max_speed": w.max_speed[0], "sinr_level": w.level[0]}
        return np.column_stack([columns[name] for name in OWN_ENTRIES])

    def _observe(self, j: int, own: np.ndarray) -> np.ndarray:
        """UAV ``j``'s observation, its own entries taken from ``own`` (``_own_entries``)."""
        w = self.world
        obs = np.zeros(len(OWN_ENTRIES) + len(OTHER_ENTRIES) * self.observed_uavs,
                       dtype=np.float32)
        obs[: len(OWN_ENTRIES)] = own[j]
        if self.observed_uavs:
            others = np.flatnonzero(w.active[0])
            others = others[others != j]
            offset = w.position[0, others] - w.position[0, j]
            nearest = np.argsort(np.hypot(offset[:, 0], offset[:, 1]), kind="stable")
            nearest = nearest[: self.observed_uavs]
            block = np.zeros((self.observed_uavs, len(OTHER_ENTRIES)))
            n = nearest.shape[0]
            block[:n, 0:2] = offset[nearest]
            block[:n, 2:4] = w.velocity[0, others[nearest]]
            block[:n, 4] = w.radius[0, others[nearest]]
            block[:n, 5] = 1.0
            obs[len(OWN_ENTRIES):] = block.ravel()
        return obs

    def _info(self, j: int) -> dict[str, Any]:
        w = self.world
        return {
            "outcome": Outcome(int(w.status[0, j])).label,
            "sinr_db": float(w.sinr_db[0, j]),
        }

    def state(self) -> np.ndarray:
        """Global state: per UAV the own entries of its observation plus its outcome code,
        then [x, y, power_w] of each jammer slot (power 0 = off or absent)."""
        w = self.world
        per_uav = np.concatenate([self._own_entries(), w.status[0, :, None]], axis=1)
        jammers = np.zeros((MAX_JAMMERS, 3))
        slots = w.jammer_x.shape[1]
        jammers[:slots] = np.stack([w.jammer_x[0], w.jammer_y[0], w.jammer_power[0]], axis=1)
        return np.concatenate([per_uav.ravel(), jammers.ravel()]).astype(np.float32)

    # -- rendering ---------------------------------------------------------------------------
    def render(self) -> np.ndarray | None:
        if self.render_mode is None:
            return None
        if self.render_mode == "human":
            w = self.world
            lines = [f"step {int(w.steps[0])}"]
            for agent, j in self._index.items():
                x, y = w.position[0, j]
                gx, gy = w.destination[0, j]
                lines.append(
                    f"  {agent}: ({x:7.2f}, {y:7.2f}) -> ({gx:7.2f}, {gy:7.2f})  "
                    f"sinr {w.sinr_db[0, j]:6.2f} dB  {Outcome(int(w.status[0, j])).label}"
                )
            print("\n".join(lines))
            return None
        return self._render_rgb()

    def _render_rgb(self) -> np.ndarray:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        w, area = self.world, self.scenario.area
        figure = Figure(figsize=(3, 3), dpi=64)
        canvas = FigureCanvasAgg(figure)
        ax = figure.add_axes((0.0, 0.0, 1.0, 1.0))
        ax.set_xlim(area.x_min, area.x_max)
        ax.set_ylim(area.y_min, area.y_max)
        ax.set_aspect("equal")
        ax.set_axis_off()
        gbs = np.asarray(self.scenario.gbs.positions)
        ax.scatter(gbs[:, 0], gbs[:, 1], marker="^", c="grey", s=20)
        for x, y, _, _ in w.jammers_now(0):
            ax.scatter([x], [y], marker="x", c="red", s=40)
        colors = ["tab:blue", "tab:green", "tab:red", "tab:purple", "tab:orange", "tab:brown"]
        for j in range(self.num_uavs):
            color = colors[j % len(colors)]
            ax.plot(*w.destination[0, j], marker="*", c=color, ms=6)
            alpha = 1.0 if w.status[0, j] == Outcome.ACTIVE else 0.3
            ax.plot(*w.position[0, j], marker="o", c=color, alpha=alpha, ms=5)
        canvas.draw()
        return np.asarray(canvas.buffer_rgba())[..., :3].copy()

    def close(self) -> None:
        self.agents = []

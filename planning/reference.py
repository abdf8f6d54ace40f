"""One-step lookahead (Algorithm 1, lines 11-20): the policy every UAV runs.

For every permissible action the UAV predicts its next state (other UAVs propagated at their
last observed velocity, the CADRL "filtered velocity", or with policy.others_model "reciprocal"
each taking half of the avoidance as in ORCA), the SINR level there from a radio map, and the
reward; it picks argmax R + gamma * V(next joint state). All UAVs and all actions go
through the value network in one forward pass. Training, evaluation and the agent processes
call this same code; the compiled core (``planning.lookahead``) takes only the decision itself
over, and is tested against this one. The radio maps it reads are those of ``planning.maps``.

With policy.lookahead_depth > 1 a UAV at risk of disconnection (weak now or about to be, and
its best one-step move leaving no next move onto a connected level) searches deeper: its most
promising first moves scored R1 + gamma * max_a2 [R2 + gamma * V(s2)] (and so on), which sees
a jammed zone that no move within the turn limit leaves in time before the UAV turns into it.
The paper's method stays the one-step, constant-velocity lookahead it publishes.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import numpy as np

from planning.features import PAPER_METHOD, MethodOptions, joint_state, joint_state_size
from planning.maps import RadioMap
from planning.networks import ValueNetwork, WeightsError
from planning.orca import orca_velocities
from shared.kinematics import ActionSet, clamp, closest_approach
from shared.observation import CELL_CLEARANCE_M, Observation
from shared.outcomes import arrivals, disconnections
from shared.rewards import RewardModel
from shared.scenario import Scenario

CLOSING_TOLERANCE_M = 0.01  # inside the margin, closing by less than this still counts as holding
# Far above the rounding of a gap bound over the area, far below anything R_c can tell apart.
GAP_SLACK_M = 1e-6


def inside_safe_cells(
    position: np.ndarray,
    end: np.ndarray,
    radius: np.ndarray,
    others_position: np.ndarray,
    others_present: np.ndarray,
) -> np.ndarray:
    """Which moves (N, A) from ``position`` (N, 2) to ``end`` (N, A, 2) stay in the UAV's
    buffered Voronoi cell (Zhou et al., 2017): for every present other, no farther toward it
    than half their distance less the UAV's own ``radius`` (N,). A cell is convex, so a
    straight move whose end is inside never leaves it; if every UAV starts and stays in its
    cell, two UAVs are always at least r_i + r_j apart. Staying put is always allowed: a UAV already
    closer than its cell permits must not be left without a move."""
    toward = others_position - position[:, None]  # (N, M, 2)
    distance = np.linalg.norm(toward, axis=-1)
    unit = toward / np.maximum(distance, 1e-12)[..., None]
    move = end - position[:, None]  # (N, A, 2)
    # The advance toward each other (N, M, A), written out: an einsum over two coordinates
    # costs twice as much.
    advance = move[:, None, :, 0] * unit[..., 0, None]
    advance += move[:, None, :, 1] * unit[..., 1, None]
    limit = distance / 2 - radius[:, None] - CELL_CLEARANCE_M
    leaves = ((advance > limit[..., None]) & others_present[..., None]).any(axis=1)
    still = (move[..., 0] == 0) & (move[..., 1] == 0)
    return still | ~leaves


def reciprocal_velocities(observation: Observation, time_horizon: float,
                          time_step: float) -> np.ndarray:
    """Each other's next velocity (N, K, 2) if it avoids the observing UAV as a reciprocal ORCA
    agent keen to keep its observed velocity: unchanged unless the two are on collision course
    within ``time_horizon``, else its half of the avoidance, the other half left to the
    observer. A UAV that reasons so about its neighbour, and the neighbour about it, predict
    mirrored halves to the same passing side (ORCA breaks a head-on tie to the right leg for
    both), where constant velocity has each expect the other to hold its course. The others'
    top speed is not observed; a fleet shares one, so each UAV lends them its own."""
    others_velocity = observation.others_velocity
    # ORCA changes the velocity of a pair on collision course only: solving for those alone
    # keeps the cost near nothing when no UAV is close to another.
    colliding = observation.others_present & (closest_approach(
        observation.others_position - observation.position[:, None],
        others_velocity - observation.velocity[:, None],
        time_horizon,
    ) < observation.radius[:, None] + observation.others_radius)
    uav, other = np.nonzero(colliding)
    if uav.size == 0:
        return others_velocity

    def pairs(own: np.ndarray, others: np.ndarray) -> np.ndarray:
        """Two-agent worlds (P, 2, ...): the observing UAV, then the other it sees."""
        return np.stack([own[uav], others[uav, other]], axis=1)

    velocity = pairs(observation.velocity, others_velocity)
    avoiding = orca_velocities(
        pairs(observation.position, observation.others_position), velocity,
        pairs(observation.radius, observation.others_radius), velocity,
        observation.max_speed[uav, None], True, time_horizon, time_step)
    predicted = others_velocity.copy()
    predicted[uav, other] = avoiding[:, 1]
    return predicted


def smallest_gaps(
    own_position: np.ndarray,
    own_velocity: np.ndarray,
    own_radius: np.ndarray,
    other_position: np.ndarray,
    other_velocity: np.ndarray,
    other_radius: np.ndarray,
    other_present: np.ndarray,
    duration: float,
    margin: float | np.ndarray = 0.0,
) -> np.ndarray:
    """Smallest gap over one step between each UAV and the others it can see, less a safety
    ``margin`` per other (broadcast against other_radius).

    Shapes: own_* (..., 2) / (...); other_* (..., M, 2) / (..., M); returns (...). Absent
    others (padding, finished UAVs) count as infinitely far.
    """
    distance = closest_approach(
        other_position - own_position[..., None, :],
        other_velocity - own_velocity[..., None, :],
        duration,
    )
    gap = distance - own_radius[..., None] - other_radius - margin
    return np.where(other_present, gap, np.inf).min(axis=-1, initial=np.inf)


class Decision(NamedTuple):
    """What the lookahead chose for each of N UAVs: the commanded speed and heading, the
    action's index in the action set, and its score."""

    speed: np.ndarray  # (N,)
    heading: np.ndarray  # (N,)
    action: np.ndarray  # (N,) index into the action set
    value: np.ndarray  # (N,) R + gamma V of the chosen action (NaN when explored)


class Expansion(NamedTuple):
    """Every candidate action of N UAVs, one step ahead: arrays (N, A, ...)."""

    speed: np.ndarray
    heading: np.ndarray
    velocity: np.ndarray
    position: np.ndarray  # where each action ends (at the destination if it arrives)
    level: np.ndarray
    below_steps: np.ndarray
    reward: np.ndarray  # R of the step, the disconnection reward of a lost mission included
    terminal: np.ndarray  # arrival, collision, or (with disconnection memory) a lost mission
    states: np.ndarray  # (N, A, F) joint states after the step
    others_position: np.ndarray  # (N, K, 2) the others after the step
    others_velocity: np.ndarray  # (N, K, 2) and the velocity that took them there

    def select(self, rows: np.ndarray) -> Expansion:
        return Expansion(*(field[rows] for field in self))


# The paper's lookahead: one step, the others flying on at their observed velocity. The
# paper's method always flies it, and training flies it whatever the scenario deploys.
PUBLISHED_LOOKAHEAD = {"lookahead_depth": 1, "others_model": "constant_velocity"}
DEEP_SEARCH_LEAVES = 1 << 16  # leaves per forward pass of the deep search: bounds its memory
# First moves a UAV at risk searches deeper: its DEEP_SEARCH_BEAM best by one step and its
# DEEP_SEARCH_BEAM best escapes (moves after which some next move lands on a connected level),
# so that an escape one step ranks low, a full turn out of a trap, is always searched. Searching
# every first move of every UAV weak now or about to be flew no better, at a fraction of the
# decisions a second (docs/lookahead_depth.md has the runs).
DEEP_SEARCH_BEAM = 4


class LookaheadPolicy:
    """The one-step lookahead every UAV flies (Algorithm 1): scores each permissible action by
    its reward plus the discounted value of the joint state it leads to, searching deeper for
    a UAV at risk of disconnection. The numpy reference of the compiled core."""

    def __init__(self, scenario: Scenario, value_net: ValueNetwork, shield: bool = True,
                 lookahead_depth: int | None = None, others_model: str | None = None):
        """``shield=False`` flies without the method's safe cells even if it has them: how
        training flies, so the value network learns what a collision costs.
        ``lookahead_depth`` and ``others_model`` override the scenario's policy settings
        (which the paper's method never reads)."""
        self.scenario = scenario
        self.actions = ActionSet(scenario)
        self.rewards = RewardModel(scenario)
        self.dt = scenario.timing.step_s
        self.gamma = scenario.policy.gamma
        self.observed_uavs = scenario.policy.observed_uavs
        self.tolerance = scenario.uav.arrival_tolerance_m
        self.options = MethodOptions.from_dict(value_net.method)
        self.safe_cells = self.options.safe_cells and shield
        wanted = joint_state_size(scenario, self.options)
        if value_net.input_size != wanted:
            raise WeightsError(f"value network reads {value_net.input_size} features, this "
                               f"scenario gives {wanted}")
        self.disconnection_limit = scenario.timing.disconnection_limit_steps
        self.value_net = value_net
        # The scenario's deeper search and reciprocal model belong to the methods that extend
        # the paper's; the paper's method flies the lookahead it publishes.
        published = PUBLISHED_LOOKAHEAD if self.options == PAPER_METHOD else {}
        if lookahead_depth is None:
            lookahead_depth = published.get("lookahead_depth", scenario.policy.lookahead_depth)
        if others_model is None:
            others_model = published.get("others_model", scenario.policy.others_model)
        self.depth = lookahead_depth
        self.others_model = others_model
        if self.depth < 1:
            raise ValueError(f"lookahead_depth must be at least 1, not {self.depth}")
        # Levels under this are weak: below T_s, and the marginal band above it if there is one.
        self.weak_levels = min(2, scenario.channel.level_count - 1)
        self.orca_time_horizon = scenario.policy.orca_time_horizon_s

    def others_velocity(self, observation: Observation) -> np.ndarray:
        """The velocity (N, K, 2) each other is predicted to fly over the next step."""
        if self.others_model == "reciprocal":
            return reciprocal_velocities(observation, self.orca_time_horizon, self.dt)
        return observation.others_velocity

    def values(self, states: np.ndarray) -> np.ndarray:
        return self.value_net(states).astype(np.float64)

    def _margins(self, observation: Observation) -> np.ndarray:
        """The safety margin kept to each other UAV (N, M): the method's margin, or less than
        the gap there is now to a UAV already closer. A fixed margin would make every move,
        hovering included, look like a collision once two UAVs are inside it, and both would
        hover there for ever; this way only moves that close the gap further count as one."""
        margin = self.options.collision_margin_m
        if margin == 0:
            return np.zeros_like(observation.others_radius)
        now = (np.linalg.norm(observation.others_position - observation.position[:, None],
                              axis=-1) - observation.radius[:, None] - observation.others_radius)
        return clamp(now - CLOSING_TOLERANCE_M, 0.0, margin)

    def _gaps(self, observation: Observation, velocity: np.ndarray,
              others_velocity: np.ndarray) -> np.ndarray:
        """The smallest gap (N, A) to the others over each action's step, less the margins.
        R_c and collision read a gap only under the discomfort distance, and no step closes
        a gap by more than both UAVs fly in it: the pairs that cannot come that close count
        as infinitely far, and only the UAVs with a nearer other are computed."""
        margin = self._margins(observation)
        relative = observation.others_position - observation.position[:, None]
        reach = (self.actions.max_speed + np.hypot(others_velocity[..., 0],
                                                   others_velocity[..., 1])) * self.dt
        nearest = (np.hypot(relative[..., 0], relative[..., 1]) - reach - margin
                   - observation.radius[:, None] - observation.others_radius)
        near = observation.others_present & (nearest < self.rewards.discomfort + GAP_SLACK_M)
        rows = np.flatnonzero(near.any(axis=1))
        gap = np.full(velocity.shape[:2], np.inf)
        gap[rows] = smallest_gaps(
            observation.position[rows, None],
            velocity[rows],
            observation.radius[rows, None],
            observation.others_position[rows, None],
            others_velocity[rows, None],
            observation.others_radius[rows, None],
            near[rows, None],
            self.dt,
            margin[rows, None],
        )
        return gap

    def expand(self, observation: Observation, radio_map: RadioMap) -> Expansion:
        """Each candidate action of each UAV of ``observation`` (its J_n nearest others
        only) one step ahead, others propagated by the scenario's others_model."""
        speeds, headings, velocity = self.actions.moves(observation.heading)  # (N, A, ...)
        position = observation.position[:, None, :]
        destination = observation.destination[:, None, :]
        arrived, next_position = arrivals(position, velocity, destination, self.dt,
                                          self.tolerance)

        others_velocity = self.others_velocity(observation)
        others_next = observation.others_position + others_velocity * self.dt
        gap = self._gaps(observation, velocity, others_velocity)
        level = radio_map.level_at(next_position)
        below, lost = disconnections(level, observation.below_steps[:, None],
                                     self.disconnection_limit, still_flying=~arrived & (gap > 0))
        check_now = self.rewards.is_check_step(observation.step)[:, None]
        reward = self.rewards.total(level, check_now, gap, arrived)

        states = joint_state(
            next_position,
            velocity,
            headings,
            destination,
            observation.radius[:, None],
            observation.max_speed[:, None],
            level,
            others_next[:, None],
            others_velocity[:, None],
            observation.others_present[:, None],
            self.observed_uavs,
            below if self.options.disconnection_memory else None,
            radio_map.route_distance(next_position, observation.destination)
            if self.options.route_distance else None,
        )
        # Arrival and collision end the mission: nothing follows them. A UAV that counts its
        # time below T_s also knows which steps would end it by disconnection.
        terminal = arrived | (gap <= 0)
        if self.options.disconnection_memory:
            terminal |= lost
            reward = reward + self.options.disconnection_reward * lost
        return Expansion(speeds, headings, velocity, next_position, level, below, reward,
                         terminal, states, others_next, others_velocity)

    def scores(self, expansion: Expansion, follow: np.ndarray) -> np.ndarray:
        """R + gamma * ``follow`` (the value of what comes after), nothing after a terminal."""
        return expansion.reward + self.gamma * np.where(expansion.terminal, 0.0, follow)

    def leaf_scores(self, expansion: Expansion) -> np.ndarray:
        """R + gamma V(next state) of every action (N, A): one forward pass for all."""
        states = expansion.states
        follow = self.values(states.reshape(-1, states.shape[-1])).reshape(states.shape[:2])
        return self.scores(expansion, follow)

    def after(self, observation: Observation, expansion: Expansion, uav: np.ndarray,
              action: np.ndarray) -> Observation:
        """Observations one step on, one per pair of ``uav`` and ``action`` taken: the UAV where
        the action leaves it, the others where the others model takes them."""
        moved = {name: getattr(expansion, name)[uav, action]
                 for name in ("position", "velocity", "heading", "level", "below_steps")}
        return dataclasses.replace(observation.select(uav), **moved,
                                   step=observation.step[uav] + 1,
                                   others_position=expansion.others_position[uav],
                                   others_velocity=expansion.others_velocity[uav])

    def deep_scores(self, observation: Observation, expansion: Expansion,
                    radio_map: RadioMap, depth: int, searched: np.ndarray) -> np.ndarray:
        """Score (N, A) of each action followed by the best of ``depth - 1`` more steps,
        R1 + gamma * max_a2 [R2 + gamma * ... V], for the actions ``searched`` marks (N, A);
        the others, and terminal ones, score R1 alone. All leaves in one forward pass."""
        if depth == 1:
            return self.leaf_scores(expansion)
        uav, action = np.nonzero(searched & ~expansion.terminal)
        onward = self.after(observation, expansion, uav, action)
        onward_map = radio_map.for_rows(uav)
        deeper = self.expand(onward, onward_map)
        best_next = np.zeros(expansion.reward.shape)
        best_next[uav, action] = self.deep_scores(
            onward, deeper, onward_map, depth - 1, np.ones_like(deeper.terminal)).max(axis=1)
        return self.scores(expansion, best_next)

    def escapes(self, position: np.ndarray, heading: np.ndarray, level: np.ndarray,
                terminal: np.ndarray, radio_map: RadioMap) -> np.ndarray:
        """Whether from ``position`` (N, B, 2), flying at ``heading`` and on ``level`` (N, B),
        some next move lands on a connected level (N, B): levels only, no value. A move that
        ends the mission (``terminal``) has no next one and counts as an escape; one that
        lands on a connected level escapes by hovering there."""
        escape = terminal | (level >= self.weak_levels)
        uav, move = np.nonzero(~escape)
        if uav.size:
            ends = (position[uav, move, None]
                    + self.actions.moves(heading[uav, move])[2] * self.dt)  # (P, A, 2)
            levels = radio_map.for_rows(uav).level_at(ends)
            escape[uav, move] = (levels >= self.weak_levels).any(axis=-1)
        return escape

    def at_risk(self, observation: Observation, expansion: Expansion, radio_map: RadioMap,
                best: np.ndarray) -> np.ndarray:
        """UAVs (N,) whose decision a deeper search may change for the better: those on a weak
        level now or whose best one-step move ends on one, when that move leaves no next move
        onto a connected level. A jammed zone can hold a trap that no move within the turn
        limit leaves in time, which one step does not show."""
        landing = expansion.level[np.arange(len(observation)), best]
        weak = np.flatnonzero((observation.level < self.weak_levels)
                              | (landing < self.weak_levels))
        pick = best[weak]
        risk = np.zeros(len(observation), dtype=bool)
        risk[weak] = ~self.escapes(
            *(getattr(expansion, name)[weak, pick][:, None]
              for name in ("position", "heading", "level", "terminal")),
            radio_map.for_rows(weak))[:, 0]
        return risk

    def first_moves(self, expansion: Expansion, radio_map: RadioMap, score: np.ndarray,
                    allowed: np.ndarray) -> np.ndarray:
        """The first moves (N, A) the deep search expands: the DEEP_SEARCH_BEAM best by one
        step and the DEEP_SEARCH_BEAM best escapes, of the ``allowed`` ones."""
        escape = self.escapes(expansion.position, expansion.heading, expansion.level,
                              expansion.terminal, radio_map)
        searched = np.zeros_like(allowed)
        for candidates in (score, np.where(escape, score, -np.inf)):
            beam = np.argsort(-candidates, axis=1, kind="stable")[:, :DEEP_SEARCH_BEAM]
            best = np.zeros_like(allowed)
            np.put_along_axis(best, beam, np.isfinite(np.take_along_axis(candidates, beam, 1)), 1)
            searched |= best
        return searched & allowed

    def deepened(self, observation: Observation, expansion: Expansion, radio_map: RadioMap,
                 score: np.ndarray, allowed: np.ndarray) -> np.ndarray:
        """``score`` (N, A) with the first moves of the UAVs at risk scored ``depth`` steps
        deep (``first_moves``; the rest ruled out), a group of UAVs at a time, each group's
        leaves in one forward pass."""
        risky = np.flatnonzero(self.at_risk(observation, expansion, radio_map,
                                            score.argmax(axis=1)))
        group = max(1, DEEP_SEARCH_LEAVES // (2 * DEEP_SEARCH_BEAM
                                             * len(self.actions) ** (self.depth - 1)))
        score = score.copy()
        for start in range(0, risky.size, group):
            rows = risky[start : start + group]
            rows_map, rows_expansion = radio_map.for_rows(rows), expansion.select(rows)
            searched = self.first_moves(rows_expansion, rows_map, score[rows], allowed[rows])
            deep = self.deep_scores(observation.select(rows), rows_expansion, rows_map,
                                    self.depth, searched)
            score[rows] = np.where(searched, deep, -np.inf)
        return score

    def scored(self, observation: Observation,
               radio_map: RadioMap) -> tuple[Expansion, np.ndarray, np.ndarray]:
        """Every action of every UAV one step ahead, its score (N, A) (R + gamma V, searched
        deeper for the UAVs at risk, -inf outside the safe cell), and which actions the safe
        cells allow (N, A)."""
        seen = observation
        observation = observation.nearest_neighbours(self.observed_uavs)
        expansion = self.expand(observation, radio_map)
        score = self.leaf_scores(expansion)
        allowed = np.ones_like(score, dtype=bool)
        if self.safe_cells:
            # The whole step's path counts, arrival included: the world checks it so. Every
            # UAV in sight bounds the cell, not only the J_n the value network reads.
            end = seen.position[:, None] + expansion.velocity * self.dt
            allowed = inside_safe_cells(seen.position, end, seen.radius, seen.others_position,
                                        seen.others_present)
            score = np.where(allowed, score, -np.inf)
        if self.depth > 1:
            score = self.deepened(observation, expansion, radio_map, score, allowed)
        return expansion, score, allowed

    def decide(
        self,
        observation: Observation,
        radio_map: RadioMap,
        epsilon: float = 0.0,
        rng: np.random.Generator | None = None,
    ) -> Decision:
        expansion, score, allowed = self.scored(observation, radio_map)
        rows = np.arange(len(observation))
        chosen = score.argmax(axis=1)
        chosen, value = explored(chosen, score[rows, chosen], allowed, epsilon, rng)
        return Decision(expansion.speed[rows, chosen], expansion.heading[rows, chosen], chosen,
                        value)


def explored(chosen: np.ndarray, value: np.ndarray, allowed: np.ndarray, epsilon: float,
             rng: np.random.Generator | None) -> tuple[np.ndarray, np.ndarray]:
    """The ``chosen`` actions (N,) and their ``value`` with, at probability ``epsilon`` each,
    a random action the safe cells ``allowed`` (N, A) instead, valued NaN."""
    if epsilon <= 0:
        return chosen, value
    n, actions = allowed.shape
    rng = rng or np.random.default_rng()
    explore = rng.random(n) < epsilon
    tried = rng.integers(0, actions, n)
    # A random move that would leave the safe cell hovers instead.
    tried = np.where(allowed[np.arange(n), tried], tried, 0)
    return np.where(explore, tried, chosen), np.where(explore, np.nan, value)

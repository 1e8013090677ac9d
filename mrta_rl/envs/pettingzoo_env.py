"""PettingZoo parallel view of the auction (docs/spec/auction_env.md): one agent per robot."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from gymnasium import spaces
from gymnasium.utils import seeding
from pettingzoo import ParallelEnv

from mrta_rl.envs import encodings, view_inputs
from mrta_rl.envs.params import AuctionParams
from mrta_rl.envs.view_inputs import InvalidAction, SystemLike
from mrta_rl.types import RobotId


class AuctionParallelEnv(ParallelEnv):
    """One auction (``B = 1`` :class:`AuctionEnv` underneath) as a PettingZoo ``ParallelEnv``.

    Description:
        Each robot ``R1..Rm`` is an agent; all act at every tick (spec step 4). Dynamics, rewards
        and masks are the core's, unchanged.

    Action Space:
        ``Discrete(K + 1)`` per agent: 0 = wait, ``k`` = bid for slot ``k``. The valid ones are
        ``infos[agent]["action_mask"]`` (int8 ``[K + 1]``, after reset and every step; PettingZoo's
        info-dict masking convention, which its tests sample with) and :meth:`action_mask`. With
        ``invalid_action="wait"`` (default) an invalid or out-of-range action is played as a wait
        and flagged in ``infos[agent]["invalid_action"]``, so unmasked samples
        (``parallel_seed_test``) are accepted; ``"raise"`` raises the core's ``ValueError``.
        An agent missing from the action dict waits.

    Observation Space:
        ``Box(0, 1, (F,), float32)``: the robot's local features
        (:func:`~mrta_rl.envs.encodings.local_features`), a NumPy array as PettingZoo's
        AEC tests expect.

    Reward:
        Each robot's individual reward (spec step 8); they add up to the team reward, which
        ``infos[agent]["team_reward"]`` also carries after a step.

    Episode End:
        Every agent is truncated after ``horizon`` ticks (never terminated); ``agents`` then
        becomes empty.

    Seeding:
        ``reset(seed=s)`` plays the task stream of ``AuctionEnv(..., seed=s)``; later resets
        without a seed play that copy's next episodes. The first reset without any seed plays
        the constructor's ``seed``, or fresh entropy when it is ``None`` (default), so fresh
        envs play different streams.

    Arguments:
        system: The robot team, or its name (``"system1"``), yaml path or config mapping.
        params: Dynamics parameters, or a mapping of overrides (default: spec defaults plus the
            system file's ``env:`` block).
        active_tasks: ``[m, n]`` bool ``Lambda_i`` (default ``Gamma_i``).
        seed: Seed of the first episode when ``reset`` gets none (default: fresh entropy).
        invalid_action: ``"wait"`` (default) or ``"raise"`` (see Action Space).
    """

    metadata = {"name": "mrta_auction_v0", "render_modes": [], "is_parallelizable": True}

    def __init__(
        self,
        system: SystemLike,
        params: AuctionParams | Mapping[str, Any] | None = None,
        *,
        active_tasks: np.ndarray | None = None,
        seed: int | None = None,
        invalid_action: InvalidAction = view_inputs.DEFAULT_INVALID_ACTION,
    ) -> None:
        self.core = view_inputs.build_core(system, params, active_tasks, invalid_action)
        self._first_seed = seed
        self._seeded = False  # has an episode been seeded yet (then resets continue its copy)
        self.invalid_action = invalid_action
        self.render_mode = None
        self.possible_agents: list[RobotId] = list(self.core.system.robots)
        self.agents: list[RobotId] = []
        n_features, n_actions = encodings.local_feature_size(self.core), self.core.n_actions
        self._observation_spaces = {
            agent: spaces.Box(0.0, 1.0, (n_features,), np.float32) for agent in self.possible_agents
        }
        self._action_spaces = {agent: spaces.Discrete(n_actions) for agent in self.possible_agents}
        self.state_space = spaces.Box(
            0.0, 1.0, (encodings.global_feature_size(self.core),), np.float32
        )
        self._index = {agent: i for i, agent in enumerate(self.possible_agents)}

    def observation_space(self, agent: RobotId) -> spaces.Space:
        """The (cached) observation space of one robot."""
        return self._observation_spaces[agent]

    def action_space(self, agent: RobotId) -> spaces.Space:
        """The (cached) action space of one robot."""
        return self._action_spaces[agent]

    def action_mask(self, agent: RobotId) -> np.ndarray:
        """Valid actions of one robot at this tick, int8 ``[K + 1]`` (1 = valid)."""
        return self.core.action_mask[0, self._index[agent]].astype(np.int8)

    def _observe(self) -> tuple[dict[RobotId, np.ndarray], dict[RobotId, dict[str, Any]]]:
        features = encodings.local_features(self.core)[0]  # [m, F] float32
        mask = self.core.action_mask[0].astype(np.int8)  # [m, K + 1]
        live = [(i, agent) for i, agent in enumerate(self.possible_agents) if agent in self.agents]
        obs = {agent: features[i] for i, agent in live}
        infos = {agent: {"action_mask": mask[i]} for i, agent in live}
        return obs, infos

    def reset(
        self, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[RobotId, np.ndarray], dict[RobotId, dict[str, Any]]]:
        """Start an episode (see Seeding in the class docstring; ``options`` are unused).

        Returns:
            Observations and infos (``action_mask``) of every agent.
        """
        if seed is None and not self._seeded:
            seed = self._first_seed
            if seed is None:
                seed = view_inputs.fresh_seed(seeding.np_random(None)[0])  # fresh entropy
        self.core.reset(seed=seed)  # None: the copy's next episode
        self._seeded = True
        self.agents = list(self.possible_agents)
        return self._observe()

    def step(self, actions: dict[RobotId, int]) -> tuple[dict, dict, dict, dict, dict]:
        """Play one tick with every live agent's action (missing agents wait).

        Returns:
            Observations, rewards, terminations, truncations and infos (``action_mask``,
            ``team_reward``, ``invalid_action``: the action was played as a wait), by agent.

        Raises:
            ValueError: on an invalid bid with ``invalid_action="raise"``, or after the end.
        """
        if not self.agents:
            raise ValueError("the episode has ended; call reset()")
        joint = np.array([[int(actions.get(agent, 0)) for agent in self.possible_agents]])  # [1, m]
        joint, invalid = view_inputs.sanitize_actions(
            joint, self.core.action_mask, self.invalid_action
        )
        result = self.core.step(joint)
        truncated = bool(result.done[0])  # spec: the horizon truncates, nothing terminates
        agents = list(self.agents)
        obs, infos = self._observe()
        robot_reward = result.robot_reward[0]  # [m], spec step 8
        team_reward = float(result.team_reward[0])
        rewards = {a: float(robot_reward[self._index[a]]) for a in agents}
        terminations = dict.fromkeys(agents, False)
        truncations = dict.fromkeys(agents, truncated)
        for agent in agents:
            infos[agent]["team_reward"] = team_reward
            infos[agent]["invalid_action"] = bool(invalid[0, self._index[agent]])
        if truncated:
            self.agents = []
        return obs, rewards, terminations, truncations, infos

    def state(self) -> np.ndarray:
        """Global features (:func:`~mrta_rl.envs.encodings.global_features`), in ``state_space``.

        Returns:
            float32 ``[G]``.
        """
        return encodings.global_features(self.core)[0]

    def render(self) -> None:
        """No rendering (``render_modes`` is empty)."""

    def close(self) -> None:
        """Nothing to release."""

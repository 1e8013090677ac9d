"""PettingZoo parallel view of the auction (spec ``auction_env.md``): one agent per robot."""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

from mrta_rl.envs import observations
from mrta_rl.envs.auction import AuctionEnv
from mrta_rl.envs.params import AuctionParams
from mrta_rl.systems import RobotSystem
from mrta_rl.types import RobotId

InvalidAction = Literal["raise", "wait"]


def sanitize_actions(
    actions: np.ndarray, mask: np.ndarray, invalid_action: InvalidAction
) -> np.ndarray:
    """Apply the invalid-action policy to ``[B, m]`` actions under ``mask`` ``[B, m, K + 1]``.

    Args:
        actions: Joint actions.
        mask: The core's action mask.
        invalid_action: ``"raise"`` leaves them for the core to reject (spec step 4: a clear
            ``ValueError``); ``"wait"`` turns every invalid or out-of-range action into 0 (wait).

    Returns:
        The actions to send to the core.
    """
    if invalid_action == "raise":
        return actions
    in_range = (actions >= 0) & (actions < mask.shape[-1])
    safe = np.where(in_range, actions, 0)
    valid = in_range & np.take_along_axis(mask, safe[..., None], axis=-1)[..., 0]
    return np.where(valid, actions, 0)


class AuctionParallelEnv(ParallelEnv):
    """One auction (``B = 1`` :class:`AuctionEnv` underneath) as a PettingZoo ``ParallelEnv``.

    Description:
        Each robot ``R1..Rm`` is an agent; all act at every tick (spec step 4). Dynamics, rewards
        and masks are the core's, unchanged.

    Action Space:
        ``Discrete(K + 1)`` per agent: 0 = wait, ``k`` = bid for slot ``k``. Invalid bids raise
        the core's ``ValueError`` (``invalid_action="raise"``, default) or become waits
        (``invalid_action="wait"``). An agent missing from the action dict waits.

    Observation Space:
        ``Dict(observation=Box(0, 1, (F,), float32), action_mask=Box(0, 1, (K + 1,), int8))``:
        the robot's local features (:func:`~mrta_rl.envs.observations.local_features`) and its
        valid actions, PettingZoo's masking convention (``parallel_api_test`` samples with it).

    Reward:
        Each robot's individual reward (spec step 8); they add up to the team reward, which
        ``infos[agent]["team_reward"]`` also carries after a step.

    Episode End:
        Every agent is truncated after ``horizon`` ticks (never terminated); ``agents`` then
        becomes empty.

    Arguments:
        system: The robot team.
        params: Dynamics parameters (default: spec defaults plus the system file's ``env:`` block).
        active_tasks: ``[m, n]`` bool ``Lambda_i`` (default ``Gamma_i``).
        seed: Seed of the first episode; ``reset(seed=...)`` reseeds.
        invalid_action: ``"raise"`` or ``"wait"`` (see Action Space).
    """

    metadata = {"name": "mrta_auction_v0", "render_modes": [], "is_parallelizable": True}

    def __init__(
        self,
        system: RobotSystem,
        params: AuctionParams | None = None,
        *,
        active_tasks: np.ndarray | None = None,
        seed: int = 0,
        invalid_action: InvalidAction = "raise",
    ) -> None:
        if invalid_action not in ("raise", "wait"):
            raise ValueError(f"invalid_action must be 'raise' or 'wait', got {invalid_action!r}")
        self.core = AuctionEnv(system, params, batch_size=1, active_tasks=active_tasks, seed=seed)
        self.invalid_action = invalid_action
        self.render_mode = None
        self.possible_agents: list[RobotId] = list(system.robots)
        self.agents: list[RobotId] = []
        n_features, n_actions = observations.local_feature_size(self.core), self.core.n_actions
        self._observation_spaces = {
            agent: spaces.Dict(
                observation=spaces.Box(0.0, 1.0, (n_features,), np.float32),
                action_mask=spaces.Box(0, 1, (n_actions,), np.int8),
            )
            for agent in self.possible_agents
        }
        self._action_spaces = {agent: spaces.Discrete(n_actions) for agent in self.possible_agents}
        self._index = {agent: i for i, agent in enumerate(self.possible_agents)}

    def observation_space(self, agent: RobotId) -> spaces.Space:
        """The (cached) observation space of one robot."""
        return self._observation_spaces[agent]

    def action_space(self, agent: RobotId) -> spaces.Space:
        """The (cached) action space of one robot."""
        return self._action_spaces[agent]

    def _observe(self) -> dict[RobotId, dict[str, np.ndarray]]:
        features = observations.local_features(self.core)[0]  # [m, F]
        mask = self.core.action_mask[0].astype(np.int8)  # [m, K + 1]
        return {
            agent: {"observation": features[i], "action_mask": mask[i]}
            for i, agent in enumerate(self.possible_agents)
            if agent in self.agents
        }

    def reset(
        self, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[RobotId, dict[str, np.ndarray]], dict[RobotId, dict[str, Any]]]:
        """Start an episode (reseeding the copy when ``seed`` is given; ``options`` are unused).

        Returns:
            Observations and (empty) infos of every agent.
        """
        self.core.reset(seed=seed)
        self.agents = list(self.possible_agents)
        return self._observe(), {agent: {} for agent in self.agents}

    def step(self, actions: dict[RobotId, int]) -> tuple[dict, dict, dict, dict, dict]:
        """Play one tick with every live agent's action (missing agents wait).

        Returns:
            Observations, rewards, terminations, truncations and infos, keyed by agent.

        Raises:
            ValueError: on an invalid bid with ``invalid_action="raise"``, or after the end.
        """
        if not self.agents:
            raise ValueError("the episode has ended; call reset()")
        joint = np.array([[int(actions.get(agent, 0)) for agent in self.possible_agents]])  # [1, m]
        result = self.core.step(sanitize_actions(joint, self.core.action_mask, self.invalid_action))
        truncated = bool(result.done[0])  # spec: the horizon truncates, nothing terminates
        agents = list(self.agents)
        obs = self._observe()
        robot_reward = result.robot_reward[0]  # [m], spec step 8
        rewards = {a: float(robot_reward[self._index[a]]) for a in agents}
        terminations = dict.fromkeys(agents, False)
        truncations = dict.fromkeys(agents, truncated)
        infos = {agent: {"team_reward": float(result.team_reward[0])} for agent in agents}
        if truncated:
            self.agents = []
        return obs, rewards, terminations, truncations, infos

    def state(self) -> np.ndarray:
        """Global features (:func:`~mrta_rl.envs.observations.global_features`), float32 ``[G]``."""
        return observations.global_features(self.core)[0]

    def render(self) -> None:
        """No rendering (``render_modes`` is empty)."""

    def close(self) -> None:
        """Nothing to release."""

"""Gymnasium view of the auction (spec ``auction_env.md``): one agent picks the joint action."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from mrta_rl.envs import observations
from mrta_rl.envs.auction import AuctionEnv
from mrta_rl.envs.params import AuctionParams
from mrta_rl.envs.pettingzoo_env import InvalidAction, sanitize_actions
from mrta_rl.systems import RobotSystem


class AuctionGymEnv(gym.Env):
    """One auction (``B = 1`` :class:`AuctionEnv` underneath) as a single-agent Gymnasium env.

    Description:
        A central controller chooses every robot's action at once (the joint action of CQL);
        dynamics, rewards and masks are the core's, unchanged.

    Action Space:
        ``MultiDiscrete([K + 1] * m)``: robot ``i``'s action, 0 = wait, ``k`` = bid for slot ``k``
        (spec step 4). Valid actions are ``info["action_mask"]`` (int8 ``[m, K + 1]``; pass
        ``tuple(mask)`` to ``action_space.sample(mask=...)``). Invalid bids raise the core's
        ``ValueError`` (``invalid_action="raise"``, default) or become waits (``"wait"``, needed
        by ``gymnasium.utils.env_checker.check_env``, which sends unmasked random actions).

    Observation Space:
        ``Box(0, 1, (G,), float32)``: global features
        (:func:`~mrta_rl.envs.observations.global_features`).

    Reward:
        The team reward (spec step 8); ``info["robot_reward"]`` holds the individual ones.

    Episode End:
        Truncated after ``horizon`` ticks; never terminated.

    Arguments:
        system: The robot team.
        params: Dynamics parameters (default: spec defaults plus the system file's ``env:`` block).
        active_tasks: ``[m, n]`` bool ``Lambda_i`` (default ``Gamma_i``).
        invalid_action: ``"raise"`` or ``"wait"`` (see Action Space).
        render_mode: Only ``None``.
    """

    metadata = {"render_modes": []}

    def __init__(
        self,
        system: RobotSystem,
        params: AuctionParams | None = None,
        *,
        active_tasks: np.ndarray | None = None,
        invalid_action: InvalidAction = "raise",
        render_mode: None = None,
    ) -> None:
        if invalid_action not in ("raise", "wait"):
            raise ValueError(f"invalid_action must be 'raise' or 'wait', got {invalid_action!r}")
        if render_mode is not None:
            raise ValueError("AuctionGymEnv has no render modes")
        self.core = AuctionEnv(system, params, batch_size=1, active_tasks=active_tasks)
        self.invalid_action = invalid_action
        self.render_mode = render_mode
        m, n_actions = self.core.n_robots, self.core.n_actions
        self.observation_space = spaces.Box(
            0.0, 1.0, (observations.global_feature_size(self.core),), np.float32
        )
        self.action_space = spaces.MultiDiscrete([n_actions] * m)

    def _observe(self) -> tuple[np.ndarray, dict[str, Any]]:
        obs = observations.global_features(self.core)[0]  # [G]
        return obs, {"action_mask": self.core.action_mask[0].astype(np.int8)}  # [m, K + 1]

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Start an episode; ``seed`` reseeds the copy (the core's counter-based randomness).

        Returns:
            The observation and an info dict with ``action_mask``.
        """
        super().reset(seed=seed)  # keeps Gymnasium's np_random contract; the core has its own
        self.core.reset(seed=seed)
        return self._observe()

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Play one tick with the joint action.

        Returns:
            Observation, team reward, terminated (always False), truncated, info
            (``action_mask``, ``robot_reward``).

        Raises:
            ValueError: on an invalid bid with ``invalid_action="raise"``, or after the end.
        """
        joint = np.asarray(action, dtype=np.int64).reshape(1, self.core.n_robots)  # [1, m]
        result = self.core.step(sanitize_actions(joint, self.core.action_mask, self.invalid_action))
        obs, info = self._observe()
        info["robot_reward"] = result.robot_reward[0].copy()  # [m]
        return obs, float(result.team_reward[0]), False, bool(result.done[0]), info

"""Gymnasium view of the auction (docs/spec/auction_env.md): one agent picks the joint action.

Importing ``mrta_rl.envs`` (or any module under it) registers the Gymnasium ids of
:data:`GYM_IDS`, so ``gym.make`` works after ``import mrta_rl.envs``; without that import,
``gym.make("mrta_rl.envs:mrta_rl/Auction-System1-v0")`` imports it itself.

``mrta_rl/Auction-v0`` plays the team given as ``system=`` (required); a per-system id plays its
own team, and refuses a ``system=`` that names another one (:func:`make_gym_env`).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from mrta_rl.conf_paths import shipped_systems
from mrta_rl.envs import encodings, view_inputs
from mrta_rl.envs.params import AuctionParams
from mrta_rl.envs.view_inputs import InvalidAction, SystemLike
from mrta_rl.systems import RobotSystem

# id -> the team it plays: None = the system= keyword's (a name, yaml path, mapping or
# RobotSystem), else a shipped system's name
GYM_IDS: dict[str, str | None] = {
    "mrta_rl/Auction-v0": None,
    "mrta_rl/Auction-System1-v0": "system1",  # paper Table 1
    "mrta_rl/Auction-System2-v0": "system2",  # paper Table 2
}


class AuctionGymEnv(gym.Env):
    """One auction (``B = 1`` :class:`AuctionEnv` underneath) as a single-agent Gymnasium env.

    Description:
        A central controller chooses every robot's action at once (the joint action of CQL);
        dynamics, rewards and masks are the core's, unchanged.

    Action Space:
        ``MultiDiscrete([K + 1] * m)``: robot ``i``'s action, 0 = wait, ``k`` = bid for slot ``k``
        (spec step 4). The valid ones are in ``info["action_mask"]`` (int8 ``[m, K + 1]``; pass
        ``tuple(mask)`` to ``action_space.sample(mask=...)``) and in :meth:`action_masks` (flat,
        sb3-contrib's ``MaskablePPO`` convention). With ``invalid_action="wait"`` (default) an
        invalid or out-of-range sub-action is played as a wait and flagged in
        ``info["invalid_action"]``, so unmasked samples (``check_env``) are accepted; with
        ``"raise"`` it raises the core's ``ValueError``.

    Observation Space:
        ``Box(0, 1, (G,), float32)``: global features
        (:func:`~mrta_rl.envs.encodings.global_features`).

    Reward:
        The team reward (spec step 8); ``info["robot_reward"]`` holds the individual ones.

    Episode End:
        Truncated after ``horizon`` ticks; never terminated.

    Seeding:
        ``reset(seed=s)`` plays the task stream of ``AuctionEnv(..., seed=s)``; later resets
        without a seed play that copy's next episodes. The first reset without any seed draws
        fresh entropy (Gymnasium's ``np_random``), so fresh envs play different streams.

    Arguments:
        system: The robot team, or its name (``"system1"``), yaml path or config mapping.
        params: Dynamics parameters, or a mapping of overrides (default: spec defaults plus the
            system file's ``env:`` block).
        active_tasks: ``[m, n]`` bool ``Lambda_i`` (default ``Gamma_i``).
        invalid_action: ``"wait"`` (default) or ``"raise"`` (see Action Space).
        render_mode: Only ``None``.
    """

    metadata = {"render_modes": []}

    def __init__(
        self,
        system: SystemLike,
        params: AuctionParams | Mapping[str, Any] | None = None,
        *,
        active_tasks: np.ndarray | None = None,
        invalid_action: InvalidAction = view_inputs.DEFAULT_INVALID_ACTION,
        render_mode: None = None,
    ) -> None:
        if render_mode is not None:
            raise ValueError(f"AuctionGymEnv has no render modes, got render_mode={render_mode!r}")
        self.core = view_inputs.build_core(system, params, active_tasks, invalid_action)
        self._seeded = False  # has an episode been seeded yet (then resets continue its copy)
        self.invalid_action = invalid_action
        self.render_mode = render_mode
        m, n_actions = self.core.n_robots, self.core.n_actions
        self.observation_space = spaces.Box(
            0.0, 1.0, (encodings.global_feature_size(self.core),), np.float32
        )
        self.action_space = spaces.MultiDiscrete([n_actions] * m)

    def _observe(self) -> tuple[np.ndarray, dict[str, Any]]:
        obs = encodings.global_features(self.core)[0]  # [G]
        return obs, {"action_mask": self.core.action_mask[0].astype(np.int8)}  # [m, K + 1]

    def action_masks(self) -> np.ndarray:
        """Valid sub-actions, flat bool ``[m * (K + 1)]``: robot 0's ``K + 1`` actions first.

        sb3-contrib's ``MaskablePPO`` reads this method for ``MultiDiscrete`` spaces.
        """
        return self.core.action_mask[0].reshape(-1).copy()

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Start an episode (see Seeding in the class docstring; ``options`` are unused).

        Returns:
            The observation and an info dict with ``action_mask``.
        """
        super().reset(seed=seed)  # without a seed, np_random holds fresh entropy until seeded
        if seed is not None:
            self.core.reset(seed=seed)  # the stream of AuctionEnv(seed=seed)
        elif not self._seeded:
            self.core.reset(seed=view_inputs.fresh_seed(self.np_random))
        else:
            self.core.reset()  # the copy's next episode
        self._seeded = True
        return self._observe()

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Play one tick with the joint action.

        Returns:
            Observation, team reward, terminated (always False), truncated, info
            (``action_mask``, ``robot_reward`` ``[m]``, ``invalid_action`` ``[m]`` bool: the
            sub-actions played as waits).

        Raises:
            ValueError: on an invalid bid with ``invalid_action="raise"``, or after the end.
        """
        joint = np.asarray(action, dtype=np.int64).reshape(1, self.core.n_robots)  # [1, m]
        joint, invalid = view_inputs.sanitize_actions(
            joint, self.core.action_mask, self.invalid_action
        )
        result = self.core.step(joint)
        obs, info = self._observe()
        info["robot_reward"] = result.robot_reward[0].copy()  # [m]
        info["invalid_action"] = invalid[0]  # [m]
        return obs, float(result.team_reward[0]), False, bool(result.done[0]), info


def _same_team(a: RobotSystem, b: RobotSystem) -> bool:
    """True if two teams play the same env: robots, task types, willingness, durations, env:."""
    return (
        a.robots == b.robots
        and a.task_types == b.task_types
        and np.array_equal(a.willingness, b.willingness)
        and dict(a.durations) == dict(b.durations)
        and dict(a.env_overrides) == dict(b.env_overrides)
    )


def make_gym_env(gym_id: str, system: SystemLike | None = None, **kwargs: Any) -> AuctionGymEnv:
    """The env of a Gymnasium id of :data:`GYM_IDS` (the entry point ``gym.make`` calls).

    Args:
        gym_id: The id (``gym.make`` passes it: it is registered with the id).
        system: The team (:class:`AuctionGymEnv`); required by ``mrta_rl/Auction-v0``. A
            per-system id plays its own team: ``system`` may name that team again, never another.
        **kwargs: The other arguments of :class:`AuctionGymEnv`.

    Returns:
        The env.

    Raises:
        ValueError: naming the keyword ``system``: missing for ``mrta_rl/Auction-v0``, or another
            team than a per-system id's.
    """
    own = GYM_IDS[gym_id]
    if own is None:
        if system is None:
            raise ValueError(
                f"{gym_id}: pass the team as system=...: a shipped system's name "
                f"({', '.join(shipped_systems())}), a team yaml path, a mapping or a RobotSystem"
            )
        return AuctionGymEnv(system, **kwargs)
    if system is not None and not _same_team(
        view_inputs.resolve_system(system), view_inputs.resolve_system(own)
    ):
        raise ValueError(
            f"{gym_id} plays {own}; system={_shown(system)} is another team (drop system=, or "
            f"use mrta_rl/Auction-v0 with system=...)"
        )
    return AuctionGymEnv(own if system is None else system, **kwargs)


def _shown(system: SystemLike) -> str:
    """A ``system=`` value as a message shows it: its name, path or type."""
    if isinstance(system, RobotSystem):
        return f"<RobotSystem {system.name}>"
    if isinstance(system, Mapping):
        return f"<mapping {system.get('name', '?')}>"
    return repr(str(system))[:80]


def register_envs() -> None:
    """Register the ids of :data:`GYM_IDS` with Gymnasium (once; runs when this module loads)."""
    for env_id in GYM_IDS:
        if env_id not in gym.registry:
            gym.register(env_id, entry_point=f"{__name__}:make_gym_env", kwargs={"gym_id": env_id})


register_envs()

"""TorchRL view of the auction dynamics (spec ``auction_env.md``): an ``EnvBase`` with a group_map.

The dynamics stay in :class:`~mrta_rl.envs.auction.AuctionEnv`; this adapter only converts
actions in and arrays out (``torch.from_numpy``, zero-copy where dtypes agree), following
TorchRL's multi-agent conventions (``VmasEnv``, ``PettingZooWrapper``): one nested Composite per
group with shape ``[B, n_g]``, per-agent leaves under it and root ``done`` flags.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Binary, Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase, MarlGroupMapType

from mrta_rl.envs import observations
from mrta_rl.envs.auction import AuctionEnv
from mrta_rl.types import GroupMap

GroupMapArg = Mapping[str, Sequence[str | int]] | MarlGroupMapType | str | None


def resolve_group_map(robots: Sequence[str], group_map: GroupMapArg) -> GroupMap:
    """Turn a group map argument into ``{group: [robot ids]}`` covering every robot once.

    Args:
        robots: Robot ids of the system, in order (``("R1", ...)``).
        group_map: A dict group -> robot ids (or indices); ``MarlGroupMapType`` or its lowercase
            name (``"all_in_one_group"`` -> ``{"agents": all}``, ``"one_group_per_agent"`` ->
            ``{"R1": ["R1"], ...}``); ``None`` means all in one group.

    Returns:
        The group map with robot ids.

    Raises:
        ValueError: on an unknown robot or name, or if robots are missing or repeated.
    """
    if group_map is None:
        group_map = MarlGroupMapType.ALL_IN_ONE_GROUP
    if isinstance(group_map, str):
        try:
            group_map = MarlGroupMapType[group_map.upper()]
        except KeyError as err:
            raise ValueError(f"unknown group map {group_map!r}") from err
    if group_map is MarlGroupMapType.ALL_IN_ONE_GROUP:
        return {"agents": list(robots)}
    if group_map is MarlGroupMapType.ONE_GROUP_PER_AGENT:
        return {robot: [robot] for robot in robots}
    resolved: GroupMap = {}
    for group, members in dict(group_map).items():
        ids = [robots[r] if isinstance(r, int | np.integer) else str(r) for r in members]
        unknown = [r for r in ids if r not in robots]
        if unknown or not ids:
            raise ValueError(f"group {group!r}: unknown robots {unknown} or empty group")
        resolved[str(group)] = ids
    listed = [r for ids in resolved.values() for r in ids]
    if sorted(listed) != sorted(robots):
        raise ValueError(f"group_map must list every robot exactly once, got {listed}")
    return resolved


class AuctionTorchRLEnv(EnvBase):
    """Multi-agent TorchRL environment over a batched :class:`AuctionEnv` (spec ``auction_env.md``).

    Description:
        ``B`` copies of the auction (batch size ``[B]``, device cpu), its robots split into
        groups by ``group_map`` (DQL: one group per robot; CQL: one group; subG-CQL:
        ``partition.group_map()``). Copy ``b`` uses seed ``seed + b``.

    Action Space:
        ``(group, "action")``: ``Categorical(K + 1)`` of shape ``[B, n_g]`` (0 = wait, ``k`` = bid
        for slot ``k``, spec step 4); a one-hot ``[B, n_g, K + 1]`` tensor is accepted too.
        Invalid bids raise the core's ``ValueError``; :meth:`rand_action` samples valid ones.

    Observation Space:
        ``(group, "observation")``: float32 ``[B, n_g, F]`` local features
        (:func:`~mrta_rl.envs.observations.local_features`); ``(group, "action_mask")``: bool
        ``[B, n_g, K + 1]`` (the core's mask); root ``"state"``: float32 ``[B, G]`` global
        features (:func:`~mrta_rl.envs.observations.global_features`) for mixers.

    Reward:
        Root ``"reward"`` ``[B, 1]``: team reward (spec step 8). ``(group, "reward")``
        ``[B, n_g, 1]``: each robot's individual reward. ``(group, "group_reward")``
        ``[B, n_g, 1]``: the sub-group reward (sum of its robots' rewards, spec step 8), repeated
        for every robot of the group (the shared-reward convention of VMAS and BenchMARL; take
        ``[..., 0, :]`` for a ``[B, 1]`` group reward). All float32.

    Episode End:
        Root ``"truncated"``/``"done"`` ``[B, 1]`` after ``horizon`` ticks; ``"terminated"`` is
        always False. Partial resets follow TorchRL's ``"_reset"`` key.

    Arguments:
        env: The core environment (its batch size is the TorchRL batch size).
        group_map: See :func:`resolve_group_map`.
        device: Only ``"cpu"``.
    """

    batch_locked = True

    def __init__(
        self, env: AuctionEnv, group_map: GroupMapArg = None, device: str | torch.device = "cpu"
    ) -> None:
        if torch.device(device).type != "cpu":
            raise ValueError("AuctionTorchRLEnv runs on cpu (the dynamics are numpy)")
        super().__init__(device="cpu", batch_size=torch.Size([env.batch_size]))
        self.auction = env
        self.group_map = resolve_group_map(env.system.robots, group_map)
        self._group_index = {
            g: np.array([env.system.robots.index(r) for r in ids])
            for g, ids in self.group_map.items()
        }
        self._make_specs()

    # ------------------------------------------------------------------ specs
    def _make_specs(self) -> None:
        B, A = self.auction.batch_size, self.auction.n_actions
        F, G = (
            observations.local_feature_size(self.auction),
            observations.global_feature_size(self.auction),
        )
        obs, act, rew = {}, {}, {}
        for group, idx in self._group_index.items():
            shape = torch.Size([B, len(idx)])
            obs[group] = Composite(
                observation=Bounded(0.0, 1.0, shape=(*shape, F), dtype=torch.float32),
                action_mask=Binary(n=A, shape=(*shape, A), dtype=torch.bool),
                shape=shape,
            )
            act[group] = Composite(action=Categorical(A, shape=shape), shape=shape)
            rew[group] = Composite(
                reward=Unbounded(shape=(*shape, 1)),
                group_reward=Unbounded(shape=(*shape, 1)),
                shape=shape,
            )
        self.observation_spec = Composite(
            **obs, state=Bounded(0.0, 1.0, shape=(B, G), dtype=torch.float32), shape=(B,)
        )
        self.action_spec = Composite(**act, shape=(B,))
        self.reward_spec = Composite(**rew, reward=Unbounded(shape=(B, 1)), shape=(B,))
        self.done_spec = Composite(
            {
                key: Categorical(2, shape=(B, 1), dtype=torch.bool)
                for key in ("done", "terminated", "truncated")
            },
            shape=(B,),
        )

    # ------------------------------------------------------------------ EnvBase hooks
    def _observe(self) -> dict[str, torch.Tensor | TensorDict]:
        """Observation leaves of the current decision point (fresh arrays, wrapped zero-copy)."""
        core = self.auction
        local = torch.from_numpy(observations.local_features(core))  # [B, m, F]
        # [B, m, K + 1]: a view of the core's buffer, overwritten next tick; the per-group
        # advanced indexing below copies it, so returned data never changes afterwards
        mask = torch.from_numpy(core.action_mask)
        out: dict[str, torch.Tensor | TensorDict] = {
            "state": torch.from_numpy(observations.global_features(core))
        }
        for group, idx in self._group_index.items():
            out[group] = TensorDict(
                observation=local[:, idx],
                action_mask=mask[:, idx],
                batch_size=(len(mask), len(idx)),
            )
        return out

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        B = self.auction.batch_size
        mask = None
        if tensordict is not None and "_reset" in tensordict.keys():
            mask = tensordict.get("_reset").reshape(B).numpy()
        self.auction.reset(mask)
        done = torch.from_numpy(self.auction.done.copy()).reshape(B, 1)
        return TensorDict(
            {
                **self._observe(),
                "done": done,
                "terminated": torch.zeros_like(done),
                "truncated": done.clone(),
            },
            batch_size=self.batch_size,
        )

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        core = self.auction
        B = core.batch_size
        actions = np.zeros((B, core.n_robots), np.int64)  # [B, m]
        for group, idx in self._group_index.items():
            action = tensordict.get((group, "action"))
            if action.dim() == 3:  # one-hot [B, n_g, K + 1]
                action = action.argmax(-1)
            actions[:, idx] = action.reshape(B, len(idx)).numpy()
        result = core.step(actions)  # the core validates (ValueError on invalid bids)
        robot = torch.from_numpy(result.robot_reward.astype(np.float32))  # [B, m]
        out = self._observe()
        for group, idx in self._group_index.items():
            group_robot = robot[:, idx].unsqueeze(-1)  # [B, n_g, 1]
            group_sum = group_robot.sum(dim=1, keepdim=True).expand_as(group_robot)  # spec step 8
            out[group].update(reward=group_robot, group_reward=group_sum)
        done = torch.from_numpy(result.done).reshape(B, 1)
        out.update(
            reward=torch.from_numpy(result.team_reward.astype(np.float32)).reshape(B, 1),
            done=done,
            terminated=torch.zeros_like(done),  # the spec has no terminal state, only the horizon
            truncated=done.clone(),
        )
        return TensorDict(out, batch_size=self.batch_size)

    def _set_seed(self, seed: int | None) -> None:
        """Seed the copies (copy ``b`` gets ``seed + b``); applied at the next reset."""
        if seed is not None:
            self.auction.seed(seed)

    def rand_action(self, tensordict: TensorDictBase | None = None) -> TensorDictBase:
        """Uniformly random *valid* actions (the core's mask), so random rollouts never raise."""
        mask = torch.from_numpy(self.auction.action_mask)  # [B, m, K + 1]
        B = mask.shape[0]
        action = torch.multinomial(mask.reshape(-1, mask.shape[-1]).float(), 1).reshape(
            mask.shape[:2]
        )
        out = TensorDict(
            {
                g: TensorDict(action=action[:, idx], batch_size=(B, len(idx)))
                for g, idx in self._group_index.items()
            },
            batch_size=self.batch_size,
        )
        if tensordict is None:
            return out
        return tensordict.update(out)

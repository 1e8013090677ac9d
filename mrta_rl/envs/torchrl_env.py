"""TorchRL view of the auction dynamics (spec ``auction_env.md``): an ``EnvBase`` with a group_map.

The dynamics stay in :class:`~mrta_rl.envs.auction.AuctionEnv`; this adapter only converts
actions in and arrays out (``torch.from_numpy``, zero-copy where dtypes agree), following
TorchRL's multi-agent conventions (``VmasEnv``, ``PettingZooWrapper``): one nested Composite per
group with shape ``[B, n_g]``, per-agent leaves under it and root ``done`` flags.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Binary, Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase, MarlGroupMapType

from mrta_rl.envs import encodings
from mrta_rl.envs.auction import AuctionEnv
from mrta_rl.envs.view_inputs import (
    DEFAULT_INVALID_ACTION,
    InvalidAction,
    check_invalid_action,
    sanitize_actions,
)
from mrta_rl.logs import log_torchrl_plainly
from mrta_rl.types import GroupMap

log_torchrl_plainly()  # TorchRL's lines without colour codes, in the run's log (mrta_rl/logs.py)

GroupMapArg = Mapping[str, Sequence[str | int]] | MarlGroupMapType | str | None
# a prior policy read from the core env: ``[B, m]`` int64 actions (``mrta_rl/priors.py``)
PriorActions = Callable[[AuctionEnv], np.ndarray]
PRIOR_KEY = "prior_action"  # (group, PRIOR_KEY): the prior's action per robot, -1 if none
GROUP_SET_KEYS = ("robots", "robot_types")  # set inputs per group: (group, key) [B, n_g, ...]
ROOT_SET_KEYS = ("slots", "slot_type", "types")  # set inputs at the root: [B, K, ...], [B, n, T]


def set_input_tensors(env: AuctionEnv) -> dict[str, torch.Tensor]:
    """:func:`~mrta_rl.envs.encodings.set_inputs` of the env as fresh tensors, by name.

    Returns:
        ``robots`` ``[B, m, R]``, ``robot_types`` ``[B, m, n]`` bool, ``slots`` ``[B, K, S]``,
        ``slot_type`` ``[B, K]`` int64 and ``types`` ``[B, n, T]``.
    """
    inputs = encodings.set_inputs(env)._asdict()
    out = {k: torch.from_numpy(v) for k, v in inputs.items() if k != "robot_types"}
    out["robot_types"] = torch.from_numpy(env.active_tasks).expand(inputs["robot_types"].shape)
    return out


def prior_index(actions: np.ndarray, n_actions: int) -> torch.Tensor:
    """``[B, m]`` int actions of a prior -> the ``prior_action`` leaf (-1: none for that robot).

    Args:
        actions: The prior's actions, ``0..K`` or -1.
        n_actions: ``K + 1``, which sizes the dtype (:func:`~mrta_rl.envs.encodings.prior_dtype`).
    """
    return torch.from_numpy(actions.astype(encodings.prior_dtype(n_actions)))


def prior_one_hot(prior_action: torch.Tensor, n_actions: int) -> torch.Tensor:
    """The ``prior_action`` leaf ``[*, n_g]`` -> ``[*, n_g, K + 1]`` bool one-hot.

    What the networks read: the prior's action of each robot marked, a robot without one
    (-1) an all-False row.
    """
    actions = torch.arange(n_actions, device=prior_action.device)
    return prior_action.unsqueeze(-1) == actions


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
        for slot ``k``, spec step 4) whose ``mask`` is the current action mask (updated at every
        reset and step), so sampling the spec -- ``rand_action``, ``Collector(env, None)``,
        rollouts without a policy -- draws valid actions only. A one-hot ``[B, n_g, K + 1]``
        tensor is accepted too. TorchRL clones specs where it wraps an env (``RandomPolicy`` of
        ``Collector(env, None)``, ``TransformedEnv``, the parent of a ``SerialEnv`` /
        ``ParallelEnv``), and a clone's mask no longer follows the env: TorchRL's
        ``ActionMask((group, "action"), (group, "action_mask"))`` transform on the outer env
        keeps it current. Actions sampled from a stale mask are what ``invalid_action`` is for:
        ``"wait"`` (default, as the Gymnasium and PettingZoo views) plays an invalid or
        out-of-range bid as a wait and flags it in ``(group, "invalid_action")`` ``[B, n_g, 1]``;
        ``"raise"`` keeps the core's ``ValueError`` (spec step 4; the training runner uses it).

    Observation Space:
        ``(group, "observation")``: float32 ``[B, n_g, F]`` local features
        (:func:`~mrta_rl.envs.encodings.local_features`); ``(group, "action_mask")``: bool
        ``[B, n_g, K + 1]`` (the core's mask); root ``"state"``: float32 ``[B, G]`` global
        features (:func:`~mrta_rl.envs.encodings.global_features`) for mixers; both in the
        encoding ``features`` (``"paper"`` by default, ``"time_to_free"`` adds free and queue
        levels: ``encodings`` module docstring, "Features"). With a
        ``prior``, ``(group, "prior_action")`` ``[B, n_g]`` is that policy's action of every
        robot in the current state, -1 where it has none, in the smallest integer dtype that
        holds ``K`` (:func:`~mrta_rl.envs.encodings.prior_dtype`; the networks expand it with
        :func:`prior_one_hot`); the prior is e.g. the neural learners' ``hold`` rule, which
        reads the whole team, computed here from the core. Two reward
        breakdowns ride along as observations of the step (zero after a reset):
        ``(group, "robot_reward")`` ``[B, n_g, 1]``, each robot's individual reward, and
        ``(group, "group_reward")`` ``[B, n_g, 1]``, the sub-group reward (sum of its robots'
        rewards, spec step 8) repeated for every robot of the group. With ``set_inputs`` the
        team-size independent inputs of the set network
        (:func:`~mrta_rl.envs.encodings.set_inputs`) ride along: per group ``(group,
        "robots")`` float32 ``[B, n_g, R]`` and ``(group, "robot_types")`` bool ``[B, n_g,
        n]``, at the root ``"slots"`` float32 ``[B, K, S]``, ``"slot_type"`` int64 ``[B, K]``
        and ``"types"`` float32 ``[B, n, T]``.

    Reward:
        TorchRL's multi-agent convention (VMAS, BenchMARL): the only reward key of a group is
        ``(group, "reward")`` ``[B, n_g, 1]``, the *team* reward (spec step 8) repeated for
        every robot. With one group (the default) ``env.reward_key`` is ``("agents",
        "reward")`` and a plain ``RewardSum()`` sums the team return; with several groups
        ``env.reward_keys`` lists one per group (all equal). Learners that train on the
        individual or sub-group reward read ``robot_reward`` / ``group_reward``. All float32.

    Episode End:
        Root ``"truncated"``/``"done"`` ``[B, 1]`` after ``horizon`` ticks; ``"terminated"`` is
        always False. Partial resets follow TorchRL's ``"_reset"`` key.

    Arguments:
        env: The core environment (its batch size is the TorchRL batch size).
        group_map: See :func:`resolve_group_map`.
        device: Only ``"cpu"``.
        invalid_action: ``"wait"`` or ``"raise"`` (see Action Space).
        prior: None, or a function of the core env giving ``[B, m]`` actions, written as the
            observation ``(group, "prior_action")`` (see Observation Space).
        features: ``encodings.FEATURES``: the encoding of ``observation`` and ``state``
            (a neural learner's ``features``).
        set_inputs: Also write the set network's inputs (see Observation Space).
        local_features: Write ``(group, "observation")``; False leaves it out, for learners
            that read only the set inputs (its robot-id one-hot grows with the team).
    """

    batch_locked = True

    def __init__(
        self,
        env: AuctionEnv,
        group_map: GroupMapArg = None,
        device: str | torch.device = "cpu",
        invalid_action: InvalidAction = DEFAULT_INVALID_ACTION,
        prior: PriorActions | None = None,
        features: str = "paper",
        set_inputs: bool = False,
        local_features: bool = True,
    ) -> None:
        if torch.device(device).type != "cpu":
            raise ValueError("AuctionTorchRLEnv runs on cpu (the dynamics are numpy)")
        check_invalid_action(invalid_action)
        self.features = encodings.check_features(features)
        self.invalid_action = invalid_action
        self.prior = prior
        self.set_inputs = set_inputs
        self.local_features = local_features
        super().__init__(device="cpu", batch_size=torch.Size([env.batch_size]))
        self.auction = env
        self.group_map = resolve_group_map(env.system.robots, group_map)
        m = env.n_robots
        self._group_index: dict[str, np.ndarray] = {}
        # per group: the robots' columns, as a slice when contiguous (basic indexing is a view,
        # no gather) else as an index tensor
        self._columns: dict[str, slice | torch.Tensor] = {}
        for g, ids in self.group_map.items():
            idx = np.array([env.system.robots.index(r) for r in ids])
            self._group_index[g] = idx
            contiguous = np.array_equal(idx, np.arange(idx[0], idx[0] + len(idx)))
            self._columns[g] = (
                slice(int(idx[0]), int(idx[0]) + len(idx)) if contiguous else torch.from_numpy(idx)
            )
        self._whole = {g: len(idx) == m for g, idx in self._group_index.items()}
        self._actions = np.zeros((env.batch_size, m), np.int64)  # [B, m], reused every step
        self._make_specs()

    # ------------------------------------------------------------------ specs
    def _make_specs(self) -> None:
        B, A = self.auction.batch_size, self.auction.n_actions
        n, K = self.auction.n_task_types, self.auction.n_slots
        F, G = (
            encodings.local_feature_size(self.auction, self.features),
            encodings.global_feature_size(self.auction, self.features),
        )
        obs, act, rew = {}, {}, {}
        for group, idx in self._group_index.items():
            shape = torch.Size([B, len(idx)])
            local = {"observation": Bounded(0.0, 1.0, (*shape, F), dtype=torch.float32)}
            obs[group] = Composite(
                **(local if self.local_features else {}),
                action_mask=Binary(n=A, shape=(*shape, A), dtype=torch.bool),
                robot_reward=Unbounded(shape=(*shape, 1)),
                group_reward=Unbounded(shape=(*shape, 1)),
                shape=shape,
            )
            if self.prior is not None:
                dtype = getattr(torch, encodings.prior_dtype(A).name)  # torch.int8, ...
                obs[group][PRIOR_KEY] = Bounded(-1, A - 1, shape, dtype=dtype)
            if self.set_inputs:
                R = encodings.ROBOT_TOKEN_SIZE
                obs[group]["robots"] = Bounded(0.0, 1.0, shape=(*shape, R), dtype=torch.float32)
                obs[group]["robot_types"] = Binary(n=n, shape=(*shape, n), dtype=torch.bool)
            if self.invalid_action == "wait":
                obs[group]["invalid_action"] = Binary(n=1, shape=(*shape, 1), dtype=torch.bool)
            act[group] = Composite(
                action=Categorical(A, shape=shape, mask=torch.ones(*shape, A, dtype=torch.bool)),
                shape=shape,
            )
            rew[group] = Composite(reward=Unbounded(shape=(*shape, 1)), shape=shape)
        root = {"state": Bounded(0.0, 1.0, shape=(B, G), dtype=torch.float32)}
        if self.set_inputs:
            S, T = encodings.SLOT_TOKEN_SIZE, encodings.TYPE_TOKEN_SIZE
            root["slots"] = Bounded(0.0, 1.0, shape=(B, K, S), dtype=torch.float32)
            root["slot_type"] = Categorical(n, shape=(B, K), dtype=torch.int64)
            root["types"] = Bounded(0.0, 1.0, shape=(B, n, T), dtype=torch.float32)
        self.observation_spec = Composite(**obs, **root, shape=(B,))
        self.action_spec = Composite(**act, shape=(B,))
        self.reward_spec = Composite(**rew, shape=(B,))
        self.done_spec = Composite(
            {
                key: Categorical(2, shape=(B, 1), dtype=torch.bool)
                for key in ("done", "terminated", "truncated")
            },
            shape=(B,),
        )

    def _update_masks(self, out: TensorDictBase) -> None:
        """Write the new action masks into the action spec (TorchRL's masked ``Categorical``)."""
        spec = self.input_spec["full_action_spec"]
        for group in self.group_map:
            spec[group, "action"].update_mask(out.get((group, "action_mask")))

    # ------------------------------------------------------------------ EnvBase hooks
    def observe(self) -> TensorDict:
        """The observations of the core's current decision point, as the view writes them.

        Training collects them through :meth:`_reset` and :meth:`_step`, and a learner acting on
        a core env (evaluation, a planner's rollouts) reads them here: one path from the core's
        state to a network's inputs. Per group: ``observation`` (with ``local_features``),
        ``action_mask``, ``prior_action`` (with a ``prior``) and the set inputs' ``robots`` and
        ``robot_types`` (with ``set_inputs``); at the root ``state`` and the set inputs'
        ``slots``, ``slot_type``, ``types``.

        Returns:
            A TensorDict of batch ``[B]`` on cpu; every tensor is fresh (never aliases the core).
        """
        core, cpu = self.auction, self.device
        B = core.batch_size
        local = None  # [B, m, F]
        if self.local_features:
            local = torch.from_numpy(encodings.local_features(core, self.features))
        mask = torch.from_numpy(core.action_mask)  # [B, m, K + 1], a view of the core's buffer
        out = TensorDict(
            {"state": torch.from_numpy(encodings.global_features(core, self.features))},
            batch_size=self.batch_size,
            device=cpu,
        )
        prior = None if self.prior is None else prior_index(self.prior(core), core.n_actions)
        tensors = set_input_tensors(core) if self.set_inputs else {}
        for key in ROOT_SET_KEYS if self.set_inputs else ():
            out.set(key, tensors[key])
        for group, cols in self._columns.items():
            n_g = len(self._group_index[group])
            whole = self._whole[group]
            leaves = {} if local is None else {"observation": local if whole else local[:, cols]}
            # the mask is copied: the core overwrites its buffer next tick
            leaves["action_mask"] = mask.clone() if whole else mask[:, cols].clone()
            if prior is not None:
                leaves[PRIOR_KEY] = prior if whole else prior[:, cols]
            for key in GROUP_SET_KEYS if self.set_inputs else ():
                # robot_types is an expanded view of the team's Lambda: copied per group
                leaves[key] = tensors[key][:, cols].clone()
            out.set(group, TensorDict(leaves, batch_size=(B, n_g), device=cpu))
        return out

    def _output(
        self,
        team: torch.Tensor | None,
        robot: torch.Tensor | None,
        done: torch.Tensor,
        invalid: torch.Tensor | None,
    ) -> TensorDict:
        """The TensorDict of a decision point: :meth:`observe`, rewards (None: zero) and flags.

        Args:
            team: ``[B]`` float32 team reward, None after a reset (no reward then).
            robot: ``[B, m]`` float32 individual rewards, None after a reset (zeros).
            done: ``[B]`` bool episode-end flags.
            invalid: ``[B, m]`` bool actions played as waits (``invalid_action="wait"``), None
                after a reset (none).

        Returns:
            A TensorDict of batch ``[B]`` on cpu; every tensor is fresh (never aliases the core).
        """
        B = self.auction.batch_size
        out = self.observe()
        if robot is None:
            robot = torch.zeros(B, self.auction.n_robots)
        if invalid is None and self.invalid_action == "wait":
            invalid = torch.zeros(B, self.auction.n_robots, dtype=torch.bool)
        for group, cols in self._columns.items():
            n_g = len(self._group_index[group])
            leaves = out.get(group)
            group_robot = robot[:, cols].unsqueeze(-1)  # [B, n_g, 1]
            leaves.set("robot_reward", group_robot)
            leaves.set("group_reward", group_robot.sum(1, keepdim=True).expand(B, n_g, 1).clone())
            if invalid is not None:
                leaves.set("invalid_action", invalid[:, cols].unsqueeze(-1))
            if team is not None:
                leaves.set("reward", team.reshape(B, 1, 1).expand(B, n_g, 1).clone())
        done = done.reshape(B, 1)
        out.set("done", done)
        out.set("terminated", torch.zeros_like(done))  # no terminal state, only the horizon
        out.set("truncated", done.clone())
        self._update_masks(out)
        return out

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        mask = None
        if tensordict is not None and "_reset" in tensordict.keys():
            mask = tensordict.get("_reset").reshape(self.auction.batch_size).numpy()
        self.auction.reset(mask)
        return self._output(None, None, torch.from_numpy(self.auction.done.copy()), None)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        core = self.auction
        actions = self._actions  # [B, m]
        for group, idx in self._group_index.items():
            action = tensordict.get((group, "action"))
            if action.dim() == 3:  # one-hot [B, n_g, K + 1]
                action = action.argmax(-1)
            actions[:, idx] = action.reshape(core.batch_size, len(idx)).numpy()
        invalid = None
        if self.invalid_action == "wait":  # spec step 4: an invalid bid is played as a wait
            actions, flags = sanitize_actions(actions, core.action_mask, "wait")
            invalid = torch.from_numpy(flags)
        result = core.step(actions)  # the core validates (ValueError naming copy, robot, reason)
        return self._output(
            torch.from_numpy(result.team_reward.astype(np.float32)),
            torch.from_numpy(result.robot_reward.astype(np.float32)),
            torch.from_numpy(result.done.copy()),
            invalid,
        )

    def _set_seed(self, seed: int | None) -> None:
        """Seed the copies (copy ``b`` gets ``seed + b``); applied at the next reset."""
        if seed is not None:
            self.auction.seed(seed)

"""The shared robot-set network: one set of weights for any team, masked scores over {wait, slot k}.

Inputs are the team-size independent tokens of :func:`mrta_rl.envs.encodings.set_inputs`
(``encodings`` module docstring, "Set inputs"): a token per robot, per slot and per task type.

* **Type tokens** ``[*, n, d]``: a learned embedding of the type (``nn.Embedding(max_task_types,
  d)``) plus an MLP of the type's features (queues, recency, robots covering it).
* **Robot tokens** ``[*, m, d]``: an MLP of the robot's features plus the mean of the type tokens
  of its types ``Lambda_i`` (its multi-hot): robots are told apart by what they can do and what
  state they are in, never by an id, so permuting the robots permutes the outputs.
* **Slot tokens** ``[*, K, d]``: an MLP of the slot's features plus the type token of its task.
* ``layers`` pre-norm blocks: slots attend to the robots (who could take them), robots attend to
  the present slots and, with ``robot_attention="full"``, to each other (memory ``m^2`` per copy
  and head: 160 kB of float32 attention weights per copy and head at 200 robots), or with
  ``"pooled"`` to one team token, the mean of the robot tokens (memory linear in ``m``: the
  setting for teams of a thousand robots); then a feed-forward layer on each token.
* **Heads**: per robot a wait score from its token, per (robot, slot) a pair score
  ``w . relu(A h_i + B s_k)``, computed for the valid pairs of ``action_mask`` only (the others
  are masked anyway); outputs ``[*, m, K + 1]``, column 0 wait, column ``k`` slot ``k``.
  The output layers start at zero, so an untrained network scores every action 0 and the auction
  prior bonus of the Q-learners (``learners/neural/networks.py``) decides alone. Invalid actions
  score :data:`MASKED` (finite, so a softmax or a max over them never gives NaN; waiting is
  always valid, spec step 4).

Its parameter count depends only on its settings (``embed_dim``, ``heads``, ``layers``,
``max_task_types``), not on the team's ``m``, ``K`` or ``n``. A team with more task types than
``max_task_types`` cannot be embedded (:func:`check_task_types`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import TYPE_CHECKING, Annotated, Any, Literal

import torch
from torch import nn
from torch.nn import functional as F

from mrta_rl.config import Choices, ConfigError, Range
from mrta_rl.envs.encodings import ROBOT_TOKEN_SIZE, SLOT_TOKEN_SIZE, TYPE_TOKEN_SIZE
from mrta_rl.envs.torchrl_env import prior_one_hot

if TYPE_CHECKING:
    from mrta_rl.learners.base import TrainingTeam

MASKED = -1e9  # the score of an invalid action: far below any Q-value or logit, and finite
ROBOT_ATTENTION = ("full", "pooled")  # robots attend to each other, or to a pooled team token
SET_INPUT_KEYS = ("robots", "robot_types", "slots", "slot_type", "types")  # forward's order


def check_task_types(n_task_types: int, max_task_types: int, system: str = "the team") -> None:
    """Refuse a team whose task types do not fit the type embedding.

    Args:
        n_task_types: The team's ``n``.
        max_task_types: The network's ``max_task_types``.
        system: The team's name, for the message.

    Raises:
        ConfigError: naming ``learner.max_task_types`` and ``n``.
    """
    if n_task_types > max_task_types:
        raise ConfigError(
            f"learner.max_task_types: {max_task_types} is smaller than the {n_task_types} task "
            f"types of {system}: set learner.max_task_types>={n_task_types}"
        )


def _mlp(n_in: int, d: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(n_in, d), nn.ReLU(), nn.Linear(d, d))


class Attention(nn.Module):
    """Multi-head attention of queries over keys (``scaled_dot_product_attention``)."""

    def __init__(self, d: int, heads: int) -> None:
        """Projections of ``d`` units, ``heads`` heads (``d`` must be a multiple of ``heads``)."""
        super().__init__()
        self.heads = heads
        self.q, self.kv, self.out = nn.Linear(d, d), nn.Linear(d, 2 * d), nn.Linear(d, d)

    def forward(
        self, queries: torch.Tensor, keys: torch.Tensor, key_mask: torch.Tensor | None = None
    ) -> torch.Tensor:
        """``[N, Lq, d]`` queries over ``[N, Lk, d]`` keys; ``key_mask`` ``[N, Lk]`` True = seen.

        Every query must see at least one key (the callers always leave the robots unmasked).
        """
        N, Lq, d = queries.shape
        h = self.heads
        q = self.q(queries).view(N, Lq, h, d // h).transpose(1, 2)  # [N, h, Lq, dh]
        k, v = self.kv(keys).view(N, keys.shape[1], 2, h, d // h).permute(2, 0, 3, 1, 4)
        mask = None if key_mask is None else key_mask[:, None, None, :]
        out = F.scaled_dot_product_attention(q, k, v, attn_mask=mask)
        return self.out(out.transpose(1, 2).reshape(N, Lq, d))


class Block(nn.Module):
    """Slots attend to robots; robots attend to slots and robots (or a team token); feed-forward."""

    def __init__(self, d: int, heads: int, robot_attention: str) -> None:
        """Layers of one block (module docstring)."""
        super().__init__()
        self.robot_attention = robot_attention
        self.norm_s, self.norm_r, self.norm_keys = nn.LayerNorm(d), nn.LayerNorm(d), nn.LayerNorm(d)
        self.slot_attention = Attention(d, heads)
        self.attention = Attention(d, heads)
        self.norm_ff_r, self.norm_ff_s = nn.LayerNorm(d), nn.LayerNorm(d)
        self.ff_r, self.ff_s = _mlp(d, d), _mlp(d, d)

    def forward(
        self, robots: torch.Tensor, slots: torch.Tensor, present: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``robots`` ``[N, m, d]``, ``slots`` ``[N, K, d]``, ``present`` ``[N, K]`` bool."""
        r = self.norm_r(robots)
        slots = slots + self.slot_attention(self.norm_s(slots), r)
        s = self.norm_keys(slots)
        if self.robot_attention == "full":
            others = r
        else:  # one pooled team token: memory linear in the robots
            others = r.mean(1, keepdim=True)
        keys = torch.cat([s, others], 1)
        seen = torch.cat([present, present.new_ones(others.shape[:2])], 1)
        robots = robots + self.attention(r, keys, seen)
        robots = robots + self.ff_r(self.norm_ff_r(robots))
        slots = slots + self.ff_s(self.norm_ff_s(slots))
        return robots, slots


def check_fits(n_task_types: int, system: str, settings: dict) -> None:
    """Refuse a learner's set-network settings that cannot work on a team, naming the key.

    Args:
        n_task_types: The team's task types ``n``.
        system: The team's name, for the message.
        settings: The learner's settings (``max_task_types``, ``embed_dim``, ``heads``).

    Raises:
        ConfigError: ``learner.max_task_types`` below ``n`` (the type embedding has one row per
            type, :func:`check_task_types`), or ``learner.embed_dim`` not a multiple of
            ``learner.heads``.
    """
    check_task_types(n_task_types, int(settings["max_task_types"]), f"system {system}")
    if int(settings["embed_dim"]) % int(settings["heads"]):
        raise ConfigError(
            f"learner.embed_dim: {settings['embed_dim']} must be a multiple of "
            f"learner.heads={settings['heads']}"
        )


class SetNetwork(nn.Module):
    """Masked per-robot scores over {wait, slot k} from set tokens (module docstring).

    Args:
        embed_dim: Token width ``d`` (a multiple of ``heads``).
        heads: Attention heads.
        layers: Attention blocks.
        max_task_types: Rows of the type embedding: the most task types a team may have.
        robot_attention: ``"full"`` (robots attend to each other, ``m^2`` per copy) or
            ``"pooled"`` (to the mean robot token, linear in ``m``).
        device: Parameter device.

    Raises:
        ValueError: if ``embed_dim`` is not a multiple of ``heads`` or ``robot_attention`` unknown.
    """

    def __init__(
        self,
        *,
        embed_dim: int,
        heads: int,
        layers: int,
        max_task_types: int,
        robot_attention: Literal["full", "pooled"],
        device: torch.device | str | None = None,
    ) -> None:
        super().__init__()
        if embed_dim % heads:
            raise ValueError(f"embed_dim={embed_dim} must be a multiple of heads={heads}")
        if robot_attention not in ROBOT_ATTENTION:
            raise ValueError(f"robot_attention must be one of {ROBOT_ATTENTION}")
        d = embed_dim
        self.embed_dim, self.max_task_types = d, max_task_types
        self.robot_in = _mlp(ROBOT_TOKEN_SIZE, d)
        self.slot_in = _mlp(SLOT_TOKEN_SIZE, d)
        self.type_in = _mlp(TYPE_TOKEN_SIZE, d)
        self.type_embedding = nn.Embedding(max_task_types, d)
        self.blocks = nn.ModuleList(Block(d, heads, robot_attention) for _ in range(layers))
        self.norm = nn.LayerNorm(d)
        self.wait_head = nn.Sequential(nn.Linear(d, d), nn.ReLU(), nn.Linear(d, 1))
        self.pair_robot, self.pair_slot = nn.Linear(d, d), nn.Linear(d, d, bias=False)
        self.pair_out = nn.Linear(d, 1)
        with torch.no_grad():  # untrained outputs are 0: the prior bonus alone decides
            for layer in (self.wait_head[-1], self.pair_out):
                layer.weight.zero_()
                layer.bias.zero_()
        nn.init.normal_(self.type_embedding.weight, std=1.0 / math.sqrt(d))
        self.to(device)

    def _tokens(
        self,
        robots: torch.Tensor,
        robot_types: torch.Tensor,
        slots: torch.Tensor,
        slot_type: torch.Tensor,
        types: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Robot and slot tokens after the blocks, flattened: ``[N, m, d]``, ``[N, K, d]``."""
        n = types.shape[-2]
        check_task_types(n, self.max_task_types)
        m, K = robots.shape[-2], slots.shape[-2]
        robots = robots.reshape(-1, m, robots.shape[-1])
        N = robots.shape[0]
        robot_types = robot_types.reshape(N, m, n).to(robots.dtype)
        slots = slots.reshape(N, K, slots.shape[-1])
        slot_type = slot_type.reshape(N, K)
        type_tokens = self.type_embedding.weight[:n] + self.type_in(types.reshape(N, n, -1))
        # the mean type token of each robot's Lambda_i (every robot has a type)
        own = robot_types / robot_types.sum(-1, keepdim=True).clamp(min=1)
        h = self.robot_in(robots) + own @ type_tokens  # [N, m, d]
        slot_tokens = torch.gather(
            type_tokens, 1, slot_type.unsqueeze(-1).expand(N, K, self.embed_dim)
        )
        s = self.slot_in(slots) + slot_tokens  # [N, K, d]
        present = slots[..., 0] > 0  # SLOT_FEATURES[0]: "present"
        for block in self.blocks:
            h, s = block(h, s, present)
        return self.norm(h), self.norm(s)

    def forward(
        self,
        robots: torch.Tensor,
        robot_types: torch.Tensor,
        slots: torch.Tensor,
        slot_type: torch.Tensor,
        types: torch.Tensor,
        action_mask: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Masked scores ``[*, m, K + 1]`` (wait, slot 1..K) of the inputs ``[*, ...]``.

        Args:
            robots: ``[*, m, R]`` float robot features.
            robot_types: ``[*, m, n]`` bool ``Lambda_i``.
            slots: ``[*, K, S]`` float slot features.
            slot_type: ``[*, K]`` int64 slot types (0 when empty).
            types: ``[*, n, T]`` float type features.
            action_mask: ``[*, m, K + 1]`` bool valid actions; None leaves every score unmasked.

        Returns:
            Scores (logits or Q-values); invalid actions at :data:`MASKED`.

        Raises:
            ValueError: if ``n`` exceeds ``max_task_types``.
        """
        lead = robots.shape[:-2]
        h, s = self._tokens(robots, robot_types, slots, slot_type, types)
        N, m, K = h.shape[0], h.shape[1], s.shape[1]
        wait = self.wait_head(h)  # [N, m, 1]
        a, b = self.pair_robot(h), self.pair_slot(s)  # [N, m, d], [N, K, d]
        if action_mask is None:
            bids = self.pair_out(F.relu(a.unsqueeze(2) + b.unsqueeze(1))).squeeze(-1)
            return torch.cat([wait, bids], -1).reshape(*lead, m, K + 1)
        # Only the valid (robot, slot) pairs are scored: an invalid one scores MASKED whatever
        # its value, and most pairs are invalid (a busy robot bids for nothing, a robot bids
        # only for its types' slots of its own auction zone), so the pair tensor shrinks from
        # [N, m, K, d] to [valid pairs, d].
        mask = action_mask.reshape(N, m, K + 1)
        n_idx, r_idx, k_idx = mask[..., 1:].nonzero(as_tuple=True)
        pair = F.relu_(a[n_idx, r_idx] + b[n_idx, k_idx])  # [P, d]
        scores = self.pair_out(pair).squeeze(-1)  # [P]
        bids = wait.new_full((N, m, K), MASKED).index_put((n_idx, r_idx, k_idx), scores)
        out = torch.cat([wait, bids], -1).masked_fill(~mask, MASKED)
        return out.reshape(*lead, m, K + 1)


class SetWithPrior(nn.Module):
    """Per-robot scores ``[*, m, K + 1]``: the set network plus the prior's bonus.

    The Q-values of the Q-learners' ``network=set`` (``learners/neural/q_learning.py``) and the
    logits of the policy-gradient learners' actor (``learners/neural/ppo.py``): the set
    network's output layers start at zero, so an untrained network plays the prior, as
    ``PerRobotQ`` does.
    """

    def __init__(self, *, auction_prior: float, **settings) -> None:
        """Build the set network.

        Args:
            auction_prior: Bonus of the prior's action (Q-units or logits).
            **settings: Keyword settings of :class:`SetNetwork`.
        """
        super().__init__()
        self.net = SetNetwork(**settings)
        self.auction_prior = auction_prior

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        """Masked scores of :class:`SetNetwork`'s inputs and mask, plus the prior's bonus.

        Args:
            *inputs: :meth:`SetNetwork.forward`'s arguments (the set inputs, the action mask),
                then ``prior_action`` ``[*, m]``, the prior's action (-1: none).
        """
        *network_inputs, prior_action = inputs
        values = self.net(*network_inputs)
        prior = prior_one_hot(prior_action, values.shape[-1])
        return values + self.auction_prior * prior.to(values.dtype)


NETWORKS = ("mlp", "set")  # a learner's network: per-robot MLP on local features, or set network
SET_SETTINGS = ("embed_dim", "heads", "layers", "max_task_types", "robot_attention")


class SetNetworkOption:
    """The settings of a torch learner that can play the robot-set network (``network=set``).

    A mixin of the learners whose per-robot network is either the local-feature MLP or the set
    network (QMIX, VDN, IQL, MAPPO, IPPO): the settings are declared here once, and the class
    answers whether they fit a team (:meth:`check_set_network`) and how many weights the set
    network has.
    """

    hp: dict[str, Any]

    @classmethod
    def set_settings(cls, settings: dict[str, Any]) -> dict[str, Any]:
        """The :class:`SetNetwork` keywords among a learner's settings."""
        return {key: settings[key] for key in SET_SETTINGS}

    @classmethod
    def check_set_network(cls, n_task_types: int, system: str, settings: dict[str, Any]) -> int:
        """Check the set network's settings against a team; its trainable weights.

        Raises:
            ConfigError: naming the key: ``learner.max_task_types`` below the team's task
                types, ``learner.embed_dim`` not a multiple of ``learner.heads``, or
                ``learner.prior_in_state`` (the set network has no such input).
        """
        check_fits(n_task_types, system, settings)
        if settings.get("prior_in_state"):
            raise ConfigError("learner.prior_in_state: needs network=mlp (no such set input)")
        net = SetNetwork(**cls.set_settings(settings), device="meta")
        return sum(p.numel() for p in net.parameters())

    @classmethod
    def check_settings(cls, settings: Mapping[str, Any], team: TrainingTeam) -> None:
        """Refuse set settings that cannot fit the team (:meth:`check_set_network`)."""
        super().check_settings(settings, team)  # type: ignore[misc]
        if settings["network"] == "set":
            cls.check_set_network(team.env.n_task_types, team.env.system.name, dict(settings))

    def __init__(
        self,
        *,
        network: Annotated[str, Choices(*NETWORKS)],
        embed_dim: Annotated[int, Range(1)],
        heads: Annotated[int, Range(1)],
        layers: Annotated[int, Range(1)],
        max_task_types: Annotated[int, Range(1)],
        robot_attention: Annotated[str, Choices(*ROBOT_ATTENTION)],
        **settings: Any,
    ) -> None:
        """Check the set network's settings against the team, then build as the learner.

        Args:
            network: ``mlp`` (local features, robot-id one-hot) or ``set`` (the set network).
            embed_dim: ``network=set``: token width (a multiple of ``heads``).
            heads: ``network=set``: attention heads.
            layers: ``network=set``: attention blocks.
            max_task_types: ``network=set``: rows of the task-type embedding, the most task
                types a team may have.
            robot_attention: ``network=set``: ``full`` (robots attend to each other) or
                ``pooled`` (to the mean robot token: memory linear in the robots).
            **settings: Env, generator, partition and the learner's other settings.

        Raises:
            ConfigError: on set settings that cannot fit the team (:meth:`check_set_network`).
        """
        super().__init__(**settings)

    def _set_network(self) -> SetWithPrior:
        """The set network of the settings, with the prior's bonus (``auction_prior``)."""
        return SetWithPrior(
            auction_prior=self.hp["auction_prior"],
            device=self.device,
            **self.set_settings(self.hp),
        )

"""Q-networks of the TorchRL learners: per-robot and joint-action nets, joint-action coding.

The auction prior (see ``common.py``) enters as an input: the env's ``prior_action`` is the
prior rule's action of every robot (computed from the env by ``priors``, with the rules
of ``mrta_rl/rules.py``), expanded here to a one-hot; its bonus is added to the output, and the
output layers start at zero, so an untrained network plays the prior rule.
"""

from __future__ import annotations

import torch
from torch import nn
from torchrl.modules import MLP, MultiAgentMLP

from mrta_rl.envs.torchrl_env import prior_one_hot


def joint_combine(per_robot: torch.Tensor, op: str) -> torch.Tensor:
    """Combine per-robot vectors into joint-action vectors (robot 0 = least significant digit).

    The joint action ``j = sum_r a_r (K + 1)^r`` of a group is the tuple of its robots' actions
    (spec "Observations": the joint action of a group).

    Args:
        per_robot: ``[*, n_g, A]``.
        op: ``"and"`` (joint mask = product of the robots' masks) or ``"add"`` (sum of values).

    Returns:
        ``[*, A^n_g]``.
    """
    out = per_robot[..., 0, :]
    for r in range(1, per_robot.shape[-2]):
        x = per_robot[..., r, :].unsqueeze(-1)  # [*, A, 1]: digit r, more significant
        y = out.unsqueeze(-2)  # [*, 1, A^r]
        out = (x & y if op == "and" else x + y).flatten(-2)
    return out


def joint_decode(joint: torch.Tensor, n_robots: int, n_actions: int) -> torch.Tensor:
    """Per-robot actions of joint actions (inverse of the :func:`joint_combine` order).

    Args:
        joint: ``[*]`` int joint actions.
        n_robots: ``n_g``.
        n_actions: ``A = K + 1``.

    Returns:
        ``[*, n_g]`` int64 actions.
    """
    return (joint.unsqueeze(-1) // _places(n_robots, n_actions, joint.device)) % n_actions


def joint_encode(actions: torch.Tensor, n_actions: int) -> torch.Tensor:
    """Joint actions of per-robot actions (inverse of :func:`joint_decode`).

    Args:
        actions: ``[*, n_g]`` int actions.
        n_actions: ``A = K + 1``.

    Returns:
        ``[*]`` int64 joint actions ``j = sum_r a_r (K + 1)^r``.
    """
    return (actions * _places(actions.shape[-1], n_actions, actions.device)).sum(-1)


def _places(n_robots: int, n_actions: int, device: torch.device) -> torch.Tensor:
    """Place value ``(K + 1)^r`` of robot ``r``'s digit in a joint action, ``[n_g]``."""
    return n_actions ** torch.arange(n_robots, device=device)


# ---------------------------------------------------------------------------------- modules
class PerRobotQ(nn.Module):
    """Per-robot Q-values ``[*, n_g, A]`` from local features, plus the auction prior.

    ``share_params=True`` is one network for all robots, told apart by the robot-id one-hot of
    the local features (VDN/QMIX custom): a TorchRL :class:`MLP` over the last axis, which is
    what :class:`MultiAgentMLP` computes for shared decentralised nets (same initialisation, same
    outputs) without swapping its parameters into a module on every call (``to_module``, the
    largest cost of a collection tick). ``False`` is one independent network per robot (IQL), a
    :class:`MultiAgentMLP` (vectorised over the robots).
    """

    def __init__(
        self,
        n_features: int,
        n_robots: int,
        n_actions: int,
        *,
        share_params: bool,
        hidden: int,
        depth: int,
        auction_prior: float,
        device: torch.device,
        prior_in_state: bool = False,
    ) -> None:
        """Build the MLP (last layer zero, so the untrained Q-values are the prior).

        Args:
            n_features: ``F``.
            n_robots: ``n_g``.
            n_actions: ``K + 1``.
            share_params: One network for all robots (True) or one each.
            hidden: Units per hidden layer.
            depth: Hidden layers.
            auction_prior: Bonus of the prior's action (module docstring).
            device: Parameter device.
            prior_in_state: The prior's one-hot is also an input of the MLP (``F + K + 1``).
        """
        super().__init__()
        layers = {
            "depth": depth,
            "num_cells": hidden,
            "activation_class": nn.ReLU,
            "device": device,
        }
        self.prior_in_state = prior_in_state
        n_features += n_actions if self.prior_in_state else 0
        if share_params:
            self.mlp = MLP(in_features=n_features, out_features=n_actions, **layers)
            # checkpoints written with the shared MultiAgentMLP keep loading
            self._register_load_state_dict_pre_hook(_shared_multiagent_keys)
        else:
            self.mlp = MultiAgentMLP(
                n_features, n_actions, n_robots, centralized=False, share_params=False, **layers
            )
        zero_last_layer(self.mlp)
        self.auction_prior = auction_prior
        self.n_actions = n_actions

    def forward(self, observation: torch.Tensor, prior_action: torch.Tensor) -> torch.Tensor:
        """Q-values ``[*, n_g, A]`` of ``observation`` ``[*, n_g, F]``.

        ``prior_action``: ``[*, n_g]`` the prior rule's action of each robot (-1: none).
        """
        prior = prior_one_hot(prior_action, self.n_actions).to(observation.dtype)
        if self.prior_in_state:
            observation = torch.cat([observation, prior], -1)
        if isinstance(self.mlp, MultiAgentMLP):
            values = stacked_forward(self.mlp, observation)
        else:
            values = self.mlp(observation)
        return values + self.auction_prior * prior


def stacked_forward(mlp: MultiAgentMLP, x: torch.Tensor) -> torch.Tensor:
    """What a ``MultiAgentMLP(share_params=False, centralized=False)`` computes, as batched matmuls.

    Its own forward ``vmap``s a functional call over the robots, swapping each robot's parameters
    into a module (``to_module``) on every call, which costs more than the arithmetic at our sizes;
    here each linear layer is one ``baddbmm`` of the robots' stacked weights ``[n, out, in]``
    (same parameters, same outputs; the TorchRL losses' parameter swaps still apply, since the
    weights are read from ``mlp.params`` at every call).

    Args:
        mlp: The multi-agent MLP (its layers: ``mlp._empty_net``, its weights: ``mlp.params``).
        x: ``[*, n, F]`` inputs, robot axis second to last.

    Returns:
        ``[*, n, out]`` outputs.
    """
    *lead, n, features = x.shape
    h = x.reshape(-1, n, features).transpose(0, 1)  # [n, N, F]: one matmul batch per robot
    for name, layer in mlp._empty_net.named_children():
        if isinstance(layer, nn.Linear):
            weight, bias = mlp.params[name, "weight"], mlp.params[name, "bias"]  # [n, o, i], [n, o]
            h = torch.baddbmm(bias.unsqueeze(1), h, weight.transpose(1, 2))
        else:
            h = layer(h)
    return h.transpose(0, 1).reshape(*lead, n, h.shape[-1])


def _shared_multiagent_keys(state_dict: dict, prefix: str, *args) -> None:
    """Rename a shared ``MultiAgentMLP``'s keys (``mlp.params.0.weight``) to the MLP's."""
    old = f"{prefix}mlp.params."
    for key in [k for k in state_dict if k.startswith(old)]:
        state_dict[f"{prefix}mlp.{key[len(old) :]}"] = state_dict.pop(key)


class JointQ(nn.Module):
    """Joint-action Q-values ``[*, (K + 1)^n_g]`` of one sub-group, from its robots' features."""

    def __init__(
        self,
        n_features: int,
        n_robots: int,
        n_actions: int,
        *,
        hidden: int,
        depth: int,
        auction_prior: float,
        device: torch.device,
    ) -> None:
        """Build the MLP (last layer zero) over the concatenated features of the group.

        Args:
            n_features: ``F`` per robot.
            n_robots: ``n_g``.
            n_actions: ``K + 1``.
            hidden: Units per hidden layer.
            depth: Hidden layers.
            auction_prior: Bonus per robot playing the prior's action (module docstring).
            device: Parameter device.
        """
        super().__init__()
        self.mlp = MLP(
            in_features=n_robots * n_features,
            out_features=n_actions**n_robots,
            depth=depth,
            num_cells=hidden,
            activation_class=nn.ReLU,
            device=device,
        )
        zero_last_layer(self.mlp)
        self.auction_prior = auction_prior
        self.n_actions = n_actions

    def forward(
        self, observation: torch.Tensor, action_mask: torch.Tensor, prior_action: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Joint Q-values and joint mask ``[*, A^n_g]`` (mask = product of the robots' masks).

        ``prior_action``: ``[*, n_g]`` the prior rule's action of each robot (-1: none).
        """
        value = self.mlp(observation.flatten(-2))  # [*, A^n_g]
        per_robot = prior_one_hot(prior_action, self.n_actions).to(value.dtype)
        prior = joint_combine(per_robot, "add")  # robots playing the prior's action, summed
        return value + self.auction_prior * prior, joint_combine(action_mask, "and")


class JointDecode(nn.Module):
    """Joint action ``[*]`` -> the robots' actions ``[*, n_g]`` that the env reads."""

    def __init__(self, n_robots: int, n_actions: int) -> None:
        """Keep the sizes."""
        super().__init__()
        self.n_robots, self.n_actions = n_robots, n_actions

    def forward(self, joint: torch.Tensor) -> torch.Tensor:
        """Decode (see :func:`joint_decode`)."""
        return joint_decode(joint, self.n_robots, self.n_actions)


def zero_last_layer(module: nn.Module) -> None:
    """Zero the output layer, so that the initial Q-values are exactly the auction prior."""
    last = [p for name, p in module.named_parameters() if p.dim() >= 1][-2:]  # weight, bias
    with torch.no_grad():
        for p in last:
            p.zero_()

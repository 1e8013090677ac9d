"""Q-networks of the TorchRL learners: per-robot and joint-action nets, joint-action coding.

The auction prior (see ``common.py``) lives here too: :func:`greedy_bid` marks the plain
auction's action and the output layers start at zero, so an untrained network is the greedy
auction.
"""

from __future__ import annotations

import torch
from torch import nn
from torchrl.modules import MLP, MultiAgentMLP


def greedy_bid(mask: torch.Tensor) -> torch.Tensor:
    """One-hot of the plain auction's action (spec "Fixed policies", greedy).

    Args:
        mask: ``[*, K + 1]`` bool valid actions.

    Returns:
        ``[*, K + 1]`` float: 1 at the lowest-numbered valid bid, all zero if only wait is valid.
    """
    bids = mask[..., 1:]  # [*, K]
    first = bids.to(torch.uint8).argmax(-1) + 1  # argmax returns the first maximum
    onehot = nn.functional.one_hot(first, mask.shape[-1]).to(torch.float32)
    return onehot * bids.any(-1, keepdim=True)


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
    places = n_actions ** torch.arange(n_robots, device=joint.device)  # [n_g]
    return (joint.unsqueeze(-1) // places) % n_actions


# ---------------------------------------------------------------------------------- modules
class PerRobotQ(nn.Module):
    """Per-robot Q-values ``[*, n_g, A]`` from local features, plus the auction prior.

    A TorchRL :class:`MultiAgentMLP` (decentralised inputs); ``share_params=True`` is one network
    for all robots, told apart by the robot-id one-hot of the local features (VDN/QMIX custom),
    ``False`` is one independent network per robot (IQL).
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
    ) -> None:
        """Build the MLP (last layer zero, so the untrained Q-values are the prior).

        Args:
            n_features: ``F``.
            n_robots: ``n_g``.
            n_actions: ``K + 1``.
            share_params: One network for all robots (True) or one each.
            hidden: Units per hidden layer.
            depth: Hidden layers.
            auction_prior: Bonus of the greedy bid (module docstring).
            device: Parameter device.
        """
        super().__init__()
        self.mlp = MultiAgentMLP(
            n_features,
            n_actions,
            n_robots,
            centralized=False,
            share_params=share_params,
            depth=depth,
            num_cells=hidden,
            activation_class=nn.ReLU,
            device=device,
        )
        zero_last_layer(self.mlp)
        self.auction_prior = auction_prior

    def forward(self, observation: torch.Tensor, action_mask: torch.Tensor) -> torch.Tensor:
        """Q-values ``[*, n_g, A]`` of ``observation`` ``[*, n_g, F]``."""
        return self.mlp(observation) + self.auction_prior * greedy_bid(action_mask)


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
            auction_prior: Bonus per robot playing its greedy bid (module docstring).
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

    def forward(
        self, observation: torch.Tensor, action_mask: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Joint Q-values and joint mask ``[*, A^n_g]`` (mask = product of the robots' masks)."""
        value = self.mlp(observation.flatten(-2))  # [*, A^n_g]
        prior = joint_combine(greedy_bid(action_mask), "add")  # greedy bids, summed over robots
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

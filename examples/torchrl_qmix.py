"""TorchRL's own multi-agent QMIX on the auction env (System-II), next to the greedy auction.

The pattern of TorchRL's multi-agent QMIX example, on :class:`AuctionTorchRLEnv` as it comes:
a shared per-robot Q-network (``MultiAgentMLP``) -> ``QValueModule`` and ``EGreedyModule``,
both with ``action_mask_key`` (the argmax and the random draws stay on valid bids), a
``QMixer`` on the global ``state``, ``QMixerLoss`` with a ``SoftUpdate`` target, a
``Collector`` and a ``TensorDictReplayBuffer``. The team reward is read where TorchRL's
multi-agent envs put it, ``env.reward_key`` = ``("agents", "reward")`` (repeated per robot); as
in TorchRL's example it is moved to the root ``"reward"`` for the mixer's TD target.

No auction prior here (the project's learners add one, docs/neural.md), so the short default
budget shows TorchRL's plain QMIX learning from a random start, not beating greedy.

    python examples/torchrl_qmix.py                 # about 2 episodes of 16 copies, a few minutes
    python examples/torchrl_qmix.py --episodes 10   # longer
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch
import yaml
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import EGreedyModule, MultiAgentMLP, QMixer, QValueModule
from torchrl.objectives import SoftUpdate
from torchrl.objectives.multiagent import QMixerLoss

from mrta_rl.envs import AuctionEnv, AuctionParams
from mrta_rl.envs.torchrl_env import AuctionTorchRLEnv
from mrta_rl.systems import build_system

SYSTEM = Path(__file__).resolve().parents[1] / "conf" / "system" / "system2.yaml"
GROUP = "agents"


def make_env(copies: int, horizon: int, seed: int) -> AuctionTorchRLEnv:
    """System-II, ``copies`` copies (copy ``b`` seeded ``seed + b``), one group ``"agents"``."""
    system = build_system(yaml.safe_load(SYSTEM.read_text()))
    core = AuctionEnv(system, AuctionParams(horizon=horizon), copies, seed=seed)
    return AuctionTorchRLEnv(core)


def team_return(env: AuctionTorchRLEnv, policy) -> float:
    """Mean team return of one episode of every copy under ``policy`` (deterministic)."""
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        data = env.rollout(env.auction.params.horizon, policy)
    return float(data["next", *env.reward_key][..., 0, 0].sum(-1).mean())


def greedy_auction(td):
    """The plain auction (spec "Fixed policies", greedy): each robot's lowest valid bid."""
    bids = td[GROUP, "action_mask"][..., 1:]  # [B, m, K]
    first = bids.to(torch.uint8).argmax(-1) + 1
    return td.set((GROUP, "action"), torch.where(bids.any(-1), first, 0))


def main() -> None:
    """Train QMIX for a short budget, then print its evaluation next to greedy."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=2, help="training episodes of all copies")
    parser.add_argument("--copies", type=int, default=16, help="env copies played in parallel")
    parser.add_argument("--horizon", type=int, default=1000, help="ticks per episode")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.manual_seed(args.seed)
    torch.set_num_threads(1)
    env = make_env(args.copies, args.horizon, seed=args.seed * 2**32)
    obs = env.observation_spec[GROUP, "observation"].shape[-1]
    n_agents, n_actions = len(env.group_map[GROUP]), env.auction.n_actions
    net = MultiAgentMLP(
        obs,
        n_actions,
        n_agents,
        centralized=False,
        share_params=True,
        depth=2,
        num_cells=128,
        activation_class=nn.ReLU,
    )
    qnet = TensorDictSequential(
        TensorDictModule(net, in_keys=[(GROUP, "observation")], out_keys=[(GROUP, "action_value")]),
        QValueModule(
            action_space="categorical",
            action_value_key=(GROUP, "action_value"),
            action_mask_key=(GROUP, "action_mask"),
            out_keys=[env.action_key, (GROUP, "action_value"), (GROUP, "chosen_action_value")],
        ),
    )
    frames = args.episodes * args.horizon * args.copies
    egreedy = EGreedyModule(
        env.full_action_spec_unbatched[env.action_key],
        eps_init=0.3,
        eps_end=0.02,
        annealing_num_steps=max(frames // 2, 1),
        action_key=env.action_key,
        action_mask_key=(GROUP, "action_mask"),
    )
    explore = TensorDictSequential(qnet, egreedy)
    mixer = TensorDictModule(
        QMixer(
            state_shape=env.observation_spec["state"].shape[-1:],
            mixing_embed_dim=32,
            n_agents=n_agents,
            device="cpu",
        ),
        in_keys=[(GROUP, "chosen_action_value"), "state"],
        out_keys=["chosen_action_value"],
    )
    loss = QMixerLoss(qnet, mixer, delay_value=True, action_space="categorical")
    loss.set_keys(
        action_value=(GROUP, "action_value"),
        local_value=(GROUP, "chosen_action_value"),
        global_value="chosen_action_value",
        action=env.action_key,
    )
    loss.make_value_estimator(gamma=0.95)
    target = SoftUpdate(loss, tau=0.01)
    optim = torch.optim.Adam(loss.parameters(), lr=5e-4)
    buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(50_000), batch_size=256)
    collector = Collector(env, explore, frames_per_batch=50 * args.copies, total_frames=frames)
    start = time.perf_counter()
    for data in collector:
        # TorchRL's QMIX example: the mixer's TD target reads a root team reward
        data.set(("next", "reward"), data.get(("next", *env.reward_key))[..., 0, :] * 0.1)
        buffer.extend(data.reshape(-1))
        egreedy.step(data.numel())
        if len(buffer) >= 2000:
            for _ in range(10):
                value = loss(buffer.sample())["loss"]
                optim.zero_grad()
                value.backward()
                nn.utils.clip_grad_norm_(loss.parameters(), 10.0)
                optim.step()
                target.step()
    collector.shutdown()
    train_s = time.perf_counter() - start
    eval_env = make_env(8, args.horizon, seed=1_000_000)
    qmix = team_return(eval_env, qnet)
    greedy = team_return(make_env(8, args.horizon, seed=1_000_000), greedy_auction)
    print(f"trained TorchRL QMIX on System-II: {frames} frames in {train_s:.0f} s")
    print("evaluation, 8 episodes (seeds 1000000-1000007), mean team return:")
    print(f"  qmix   {qmix:9.1f}")
    print(f"  greedy {greedy:9.1f}")


if __name__ == "__main__":
    main()

"""Train sb3-contrib's MaskablePPO on System-I and compare it with greedy on the same task streams.

The Gymnasium view (``mrta_rl/envs/gymnasium_env.py``) gives one agent the joint action of all
robots (``MultiDiscrete``) and exposes ``action_masks()``, which MaskablePPO reads. Needs the
``test`` extra (``pip install -e ".[test]"``). Run::

    python examples/sb3_maskable_ppo.py [--steps 25000] [--episodes 5]
"""

from __future__ import annotations

import argparse

import gymnasium as gym
import numpy as np
import torch
from sb3_contrib import MaskablePPO
from stable_baselines3.common.callbacks import BaseCallback
from tqdm import tqdm

import mrta_rl.envs  # noqa: F401  (registers the gym ids)
from mrta_rl.learners.fixed import lowest_valid_bid

EVAL_SEEDS = range(10_000, 10_100)  # evaluation task streams, disjoint from training's


def team_return(env: gym.Env, seed: int, policy) -> float:
    """Team return of one episode of ``policy(obs, mask [m, K + 1]) -> joint action``."""
    obs, info = env.reset(seed=seed)
    total, done = 0.0, False
    while not done:
        obs, reward, terminated, truncated, info = env.step(policy(obs, info["action_mask"]))
        total, done = total + reward, terminated or truncated
    return total


class Progress(BaseCallback):
    """A tqdm bar over training steps (SB3's own bar needs ``rich``)."""

    def _on_training_start(self) -> None:
        self.bar = tqdm(
            total=self.locals["total_timesteps"], desc="MaskablePPO", unit="step", mininterval=2
        )

    def _on_step(self) -> bool:
        self.bar.update(1)
        return True

    def _on_training_end(self) -> None:
        self.bar.close()


def main() -> None:
    """Train, evaluate both policies on the same seeds, print the comparison."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=25_000, help="training env steps (ticks)")
    parser.add_argument("--episodes", type=int, default=5, help="evaluation episodes")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    torch.set_num_threads(1)  # a small MLP: one thread is fastest, and fair on a shared CPU
    env = gym.make("mrta_rl/Auction-System1-v0")
    model = MaskablePPO("MlpPolicy", env, seed=args.seed, verbose=0)
    model.learn(total_timesteps=args.steps, callback=Progress())

    def ppo(obs, mask):
        return model.predict(obs, action_masks=mask.reshape(-1).astype(bool), deterministic=True)[0]

    def greedy(obs, mask):  # spec "Fixed policies": lowest-numbered valid slot, else wait
        return lowest_valid_bid(mask[None, :, 1:].astype(bool))[0]

    seeds = list(EVAL_SEEDS)[: args.episodes]
    rows = {
        name: [team_return(env, s, p) for s in seeds]
        for name, p in [("greedy", greedy), ("MaskablePPO", ppo)]
    }
    print(f"System-I, {args.steps} training steps, evaluation seeds {seeds[0]}..{seeds[-1]}")
    print(f"{'policy':<12} {'team return (mean +- std)':>26}  per seed")
    for name, returns in rows.items():
        mean, std = np.mean(returns), np.std(returns)
        print(f"{name:<12} {mean:>17.1f} +- {std:<6.1f}  {', '.join(f'{r:.0f}' for r in returns)}")
    gap = 100 * (np.mean(rows["MaskablePPO"]) / np.mean(rows["greedy"]) - 1)
    print(f"MaskablePPO vs greedy: {gap:+.1f} %")


if __name__ == "__main__":
    main()

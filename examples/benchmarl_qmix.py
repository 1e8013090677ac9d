"""BenchMARL's QMIX on the auction env (System-II) for a few iterations, in BenchMARL's own venv.

BenchMARL 1.5.2 pins ``torchrl<0.12`` (it installs torchrl 0.11.1 / tensordict 0.11.0), while the
project's own learners use torchrl 0.14, so BenchMARL gets a venv of its own. The env and its
TorchRL view run under both; the task is :class:`mrta_rl.envs.benchmarl_task.AuctionTask` (team
reward in ``("agents", "reward")``, where BenchMARL's algorithms read it). Setup (CPU torch from
the local wheel; check with ``pip install --dry-run`` that no CUDA torch is pulled)::

    python3 -m venv /tmp/bm_venv
    /tmp/bm_venv/bin/pip install torch==2.13.0 benchmarl     # torch 2.13.0+cpu, torchrl 0.11.1
    /tmp/bm_venv/bin/pip install --no-deps -e .              # this project, without its pins
    /tmp/bm_venv/bin/pip install gymnasium                   # mrta_rl.envs registers gym ids
    /tmp/bm_venv/bin/python examples/benchmarl_qmix.py       # a few minutes

(numpy, PyYAML and hydra-core, the rest the env needs, come with BenchMARL.) It prints BenchMARL's
evaluation team return (``eval/agents/reward/episode_reward_mean``: the team reward is repeated
per robot, so the per-robot mean is the team return) next to the greedy auction on the same task
streams (copy ``b`` of the evaluation env is seeded ``seed + b`` in both).
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import numpy as np
from benchmarl.algorithms import QmixConfig
from benchmarl.experiment import Experiment, ExperimentConfig
from benchmarl.models.mlp import MlpConfig

from mrta_rl.envs.benchmarl_task import AuctionTask


def greedy_return(task: AuctionTask, episodes: int, seed: int) -> float:
    """Mean team return of the greedy auction on BenchMARL's evaluation streams."""
    from mrta_rl.learners import GreedyLearner
    from mrta_rl.runners.evaluate import evaluate_policy

    core = task.get_env_fun(episodes, False, seed, "cpu")().auction
    greedy = GreedyLearner(env=core, rng=np.random.default_rng(0))
    return evaluate_policy(greedy, core, episodes, seed=seed).team_return_mean


def main() -> None:
    """Train BenchMARL's QMIX for ``--iters`` iterations, evaluate, print next to greedy."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--iters", type=int, default=3, help="collection/training iterations")
    parser.add_argument("--envs", type=int, default=16, help="env copies collected in parallel")
    parser.add_argument("--ticks", type=int, default=200, help="ticks collected per iteration")
    parser.add_argument("--horizon", type=int, default=1000, help="ticks per episode")
    parser.add_argument("--eval-episodes", type=int, default=8)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    task = AuctionTask(config={"system": "system2", "horizon": args.horizon})
    frames = args.envs * args.ticks
    config = ExperimentConfig.get_from_yaml()
    config.sampling_device = config.train_device = config.buffer_device = "cpu"
    config.off_policy_n_envs_per_worker = args.envs
    config.off_policy_collected_frames_per_batch = frames
    config.off_policy_n_optimizer_steps = 50
    config.off_policy_train_batch_size = 256
    config.off_policy_memory_size = 50_000
    config.max_n_iters = args.iters
    config.max_n_frames = None
    config.evaluation = True
    config.evaluation_interval = frames * args.iters  # one evaluation, at the end
    config.evaluation_episodes = args.eval_episodes
    config.render = False
    config.loggers = ["csv"]
    config.create_json = True
    config.checkpoint_at_end = False
    config.save_folder = tempfile.mkdtemp(prefix="benchmarl_qmix_")
    experiment = Experiment(
        task=task,
        algorithm_config=QmixConfig.get_from_yaml(),
        model_config=MlpConfig.get_from_yaml(),
        seed=args.seed,
        config=config,
    )
    experiment.run()
    scalars = next(Path(experiment.folder_name).rglob("scalars"))  # BenchMARL's csv logger
    values = {}
    for name in ("eval_agents_reward_episode_reward_mean", "collection_agents_reward_reward_mean"):
        path = scalars / f"{name}.csv"
        if path.is_file():
            values[name] = [float(row.split(",")[1]) for row in path.read_text().split()]
    greedy = greedy_return(task, args.eval_episodes, args.seed)
    print(json.dumps({"frames": frames * args.iters, **values}, indent=1))
    qmix = values.get("eval_agents_reward_episode_reward_mean", [float("nan")])[-1]
    print(f"BenchMARL QMIX on System-II, {args.iters} iterations of {frames} frames:")
    print(f"  evaluation team return ({args.eval_episodes} episodes)  qmix {qmix:9.1f}")
    print(f"  greedy auction, same task streams                 greedy {greedy:9.1f}")


if __name__ == "__main__":
    main()

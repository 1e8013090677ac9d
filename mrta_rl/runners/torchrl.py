"""Training loop of the neural learners (kind "neural"): TorchRL Collector, replay, target nets.

The loop plays ``train.episodes`` episodes of ``train.batch_size`` copies (the shared ``train.*``
budget, so ``debug=smoke`` shrinks it to a few hundred frames), like the tabular runner, but
through TorchRL: a ``Collector`` runs the learner's epsilon-greedy policy (``EGreedyModule`` with
action masks) on :class:`~mrta_rl.envs.torchrl_env.AuctionTorchRLEnv`, batches go into a
``TensorDictReplayBuffer``, and the learner's TorchRL loss is optimised on replayed batches with
soft or hard target updates (:meth:`NeuralLearner.train_step`). A frame is one copy-tick, so
``env_ticks`` counts the same thing as in the tabular runner.

Outputs: curve.csv (columns ``env_ticks, episode, team_return_mean``, via ``conf/logger``),
TorchRL logger scalars (loss, epsilon, frames per second; CSV under ``<run dir>/torchrl/`` by
default, TensorBoard with ``logger=tensorboard``), and the returned ``train`` info with the
frames per second of collection and of training.
"""

from __future__ import annotations

import logging
import time
from contextlib import nullcontext
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch
from hydra.utils import instantiate
from omegaconf import DictConfig
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

from mrta_rl.envs.torchrl_env import AuctionTorchRLEnv
from mrta_rl.runners.checkpoint import LoopTime
from mrta_rl.runners.episodes import EpisodeReturns
from mrta_rl.runners.progress import progress_bar
from mrta_rl.runners.replay import (
    REPLAY_FILE,
    read_replay,
    replay_layout,
    restore_replay,
    save_replay,
)

if TYPE_CHECKING:
    from mrta_rl.learners.neural import NeuralLearner
    from mrta_rl.runners.train import RunSetup

logger = logging.getLogger(__name__)

# Small networks and a numpy env: one intra-op thread is fastest, and on a shared machine more
# threads spin against each other (measured: 3.4 ms vs 1.2 ms per env step of 16 copies).
TORCH_THREADS = 1


def train_loop(run: RunSetup, cfg: DictConfig, run_dir: Path) -> dict[str, Any]:
    """Train ``run.learner`` (a :class:`NeuralLearner`) for ``train.episodes`` episodes.

    Args:
        run: The built run (training env and learner).
        cfg: The run config (``seed``, ``train`` and ``logger`` groups).
        run_dir: Output folder of curve.csv and the TorchRL logs.

    Returns:
        ``{"env_ticks", "wall_s", "episodes", "gradient_steps", "collect_s", "train_s",
        "fps_collection", "fps_training", "fps_overall"}``: seconds of the loop, of collection
        and of gradient steps; frames per second of collection (copy-ticks collected per second
        spent collecting), of training (replayed transitions per second spent in gradient steps)
        and overall (copy-ticks per second of the whole loop). A resumed run's seconds include
        those of the processes before it.
    """
    torch.set_num_threads(TORCH_THREADS)
    torch.manual_seed(cfg.seed)  # exploration draws and replay sampling (the runner seeds torch)
    learner: NeuralLearner = run.learner  # type: ignore[assignment]
    hp, device = learner.hp, learner.device
    batch, horizon = run.env.batch_size, run.params.horizon
    ticks_per_batch = min(int(hp["collect_ticks"]), horizon)
    total_frames = int(cfg.train.episodes) * horizon * batch
    # a short run (debug=smoke) still reaches the gradient steps: warm up at most half of it
    warmup = min(int(hp["warmup_frames"]), total_frames // 2)
    # the learners play masked actions only: an invalid one is a bug, so it must raise
    # with prior=hold the env view also writes the rule's action of every robot (common.py)
    # and builds the observations in the learner's features (paper or time_to_free), or the
    # set inputs (network=set)
    env = AuctionTorchRLEnv(
        run.env, group_map=learner.group_map, invalid_action="raise", **learner.view_options
    )
    team_group = next(iter(learner.group_map))
    buffer = TensorDictReplayBuffer(
        storage=LazyTensorStorage(int(hp["buffer_size"]), device=device),
        batch_size=int(hp["batch_size"]),
    )
    # resuming (checkpoints are taken where every copy is between episodes): counters, curve,
    # replay buffer and torch's generator from the checkpoint, checked before anything is
    # built or written (runners/replay.py); the core env replays the resets of the episodes
    # played, which fixes its task streams (auction.py "Counter-based randomness"); the
    # collector's own first reset then starts the next episode
    ckpt = run.checkpoint
    state = (ckpt.restore() if ckpt else None) or {
        "episode": 0,
        "frames": 0,
        "replayed": 0,
        "curve": [],
    }
    frames, episodes, replayed = state["frames"], state["episode"], state["replayed"]
    rows: list[dict[str, Any]] = state["curve"]
    torch_rng = None  # the checkpoint's, set once the collector is built
    if frames:
        layout = replay_layout(env, learner)
        path = ckpt.path / REPLAY_FILE
        transitions, torch_rng = read_replay(path, layout, frames, int(hp["buffer_size"]))
        restore_replay(buffer, transitions, frames)
    for _ in range(episodes):
        run.env.reset()
    returns = EpisodeReturns(batch, team_group, episodes)
    loss_info: dict[str, float] = {}
    clock = LoopTime(state.get("spent"))  # a resumed run's earlier processes included
    if total_frames == 0:
        instantiate(cfg.logger)(run_dir=run_dir).close()
        return {"env_ticks": 0, "wall_s": 0.0, "episodes": 0, "gradient_steps": 0}
    collector = Collector(
        env,
        learner.explore_policy,
        frames_per_batch=ticks_per_batch * batch,
        total_frames=total_frames - frames,
        env_device="cpu",
        policy_device=device,
        storing_device=device,
        auto_register_policy_transforms=False,
    )
    if torch_rng is not None:  # after building the collector, which may draw from torch
        torch.set_rng_state(torch_rng)

    def save_files(folder: Path) -> None:
        save_replay(buffer, folder / REPLAY_FILE)

    with (
        instantiate(cfg.logger)(run_dir=run_dir) as curve,
        progress_bar(
            total=total_frames,
            initial=frames,
            unit="frame",
            unit_scale=True,
            desc=f"train {run.name}",
            enabled=cfg.train.progress_bar,
            log_every_s=cfg.train.get("log_every_s"),
            episode_units=horizon * batch,
        ) as bar,
        ckpt.catch_interrupt() if ckpt else nullcontext(),
    ):
        for row in rows:
            curve.log(row)
        scalars = curve.torchrl_logger  # the run's tracker (logger=csv|tensorboard|wandb|mlflow)
        tick = time.perf_counter()
        for data in collector:  # [B, T]
            clock.add("collect_s", time.perf_counter() - tick)
            n_frames = data.numel()
            finished, boundary = returns.add(data, frames)
            frames += n_frames
            episodes = returns.episodes
            for row in finished:
                curve.log(row)
                rows.append(row)
            buffer.extend(learner.transitions(data))
            learner.anneal(n_frames)
            tick = time.perf_counter()
            if frames >= warmup:
                for _ in range(int(hp["updates_per_collect"])):
                    loss_info = learner.train_step(buffer.sample().to(device))
                    replayed += int(hp["batch_size"])
            clock.add("train_s", time.perf_counter() - tick)
            fps_collection = frames / max(clock.total("collect_s"), 1e-9)
            fps_training = replayed / max(clock.total("train_s"), 1e-9)
            for key, value in {
                **loss_info,
                "train/epsilon": learner.epsilon,
                "fps/collection": fps_collection,
                "fps/training": fps_training,
            }.items():
                scalars.log_scalar(key, value, step=frames)
            bar.update(n_frames)
            bar.set_postfix(
                {
                    "return": returns.recent,
                    "eps": f"{learner.epsilon:.3f}",
                    "fps": f"{fps_collection:.0f}/{fps_training:.0f}",
                },
                refresh=False,
            )
            if ckpt and boundary:  # the batch ends between episodes: resumable here
                loop = {"episode": episodes, "frames": frames, "replayed": replayed, "curve": rows}
                loop["spent"] = clock.spent()
                ckpt.episode_end(loop, last=frames >= total_frames, files=save_files)
            tick = time.perf_counter()
    collector.shutdown()
    wall = clock.wall()
    info = {
        "env_ticks": frames,
        "wall_s": round(wall, 3),
        "episodes": episodes,
        "gradient_steps": learner.gradient_steps,
        "collect_s": round(clock.total("collect_s"), 3),
        "train_s": round(clock.total("train_s"), 3),
        "fps_collection": round(frames / max(clock.total("collect_s"), 1e-9), 1),
        "fps_training": round(replayed / max(clock.total("train_s"), 1e-9), 1),
        "fps_overall": round(frames / max(wall, 1e-9), 1),
    }
    logger.info(
        "trained %d episodes (%d frames, %d gradient steps) in %.1f s; fps collection %.0f, "
        "training %.0f (replayed transitions/s), overall %.0f",
        episodes,
        frames,
        learner.gradient_steps,
        wall,
        info["fps_collection"],
        info["fps_training"],
        info["fps_overall"],
    )
    return info

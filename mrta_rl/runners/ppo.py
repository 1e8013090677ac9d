"""On-policy training loop of ``mappo`` and ``ippo``: Collector batches -> GAE -> PPO epochs.

The loop plays ``train.episodes`` episodes of ``train.batch_size`` copies (``conf/budget/ppo.yaml``)
through TorchRL: a ``Collector`` runs the learner's masked-categorical actor (sampling) on
:class:`~mrta_rl.envs.torchrl_env.AuctionTorchRLEnv` for ``learner.frames_per_batch`` frames (whole
ticks of every copy), and :meth:`~mrta_rl.learners.neural.ppo.PPOLearner.train_batch` computes
``MultiAgentGAE`` on the batch and takes ``epochs`` passes of minibatch PPO steps; the batch is
then dropped (on-policy: nothing is replayed). A frame is one copy-tick, as in every runner.

Outputs: curve.csv (one row per episode, :class:`~mrta_rl.runners.episodes.EpisodeReturns`),
TorchRL logger scalars (losses, entropy, frames per second) and the returned ``train`` info.
Training checkpoints are taken where a batch ends between episodes; they hold the learner
(weights, optimizer) and torch's generator (action sampling, minibatch order), so a resumed run
ends as the uninterrupted one.
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

from mrta_rl.checked_files import read_tensors
from mrta_rl.envs.torchrl_env import AuctionTorchRLEnv
from mrta_rl.learners.neural.common import write_tensors
from mrta_rl.run_layout import RunDirError
from mrta_rl.runners.checkpoint import LoopTime
from mrta_rl.runners.episodes import EpisodeReturns
from mrta_rl.runners.progress import progress_bar
from mrta_rl.runners.torchrl import TORCH_THREADS

if TYPE_CHECKING:
    from mrta_rl.learners.neural.ppo import PPOLearner
    from mrta_rl.runners.train import RunSetup

logger = logging.getLogger(__name__)

RNG_FILE = "torch_rng.pt"  # training checkpoints: torch's generator at the episode boundary
RNG_BYTES = 2**16  # the most bytes of RNG_FILE (the generator's state takes about 5 kB)


def read_rng(path: Path) -> torch.Tensor:
    """Torch's generator state saved in a checkpoint (``weights_only`` loading).

    Raises:
        RunDirError: naming the file, if it is missing, damaged or not a generator state.
    """
    expected = torch.get_rng_state()
    state = read_tensors(path, torch.device("cpu"), RNG_BYTES, "torch's generator state")
    if not isinstance(state, torch.Tensor) or state.shape != expected.shape:
        raise RunDirError(f"{path}: not torch's generator state")
    return state


def train_loop(run: RunSetup, cfg: DictConfig, run_dir: Path) -> dict[str, Any]:
    """Train ``run.learner`` (a :class:`PPOLearner`) for ``train.episodes`` episodes.

    Args:
        run: The built run (training env and learner).
        cfg: The run config (``seed``, ``train`` and ``logger`` groups).
        run_dir: Output folder of curve.csv and the TorchRL logs.

    Returns:
        ``{"env_ticks", "wall_s", "episodes", "gradient_steps", "collect_s", "train_s",
        "fps_collection", "fps_training", "fps_overall"}``: seconds of the loop, of collection
        and of updates; frames per second of collection, of training (frames passed through the
        loss per second spent in updates) and overall. A resumed run's seconds include those of
        the processes before it.
    """
    torch.set_num_threads(TORCH_THREADS)
    torch.manual_seed(cfg.seed)  # action sampling and minibatch order (the runner seeds torch)
    learner: PPOLearner = run.learner  # type: ignore[assignment]
    batch, horizon = run.env.batch_size, run.params.horizon
    total_frames = int(cfg.train.episodes) * horizon * batch
    # the learner plays masked actions only: an invalid one is a bug, so it must raise
    env = AuctionTorchRLEnv(
        run.env,
        group_map=learner.group_map,
        invalid_action="raise",
        prior=learner.rule,
        features=learner.features,
        set_inputs=learner.set_inputs,
    )
    # resuming (checkpoints are taken where every copy is between episodes): counters, curve and
    # torch's generator from the checkpoint, checked before anything is built or written; the
    # core env replays the resets of the episodes played, which fixes its task streams
    ckpt = run.checkpoint
    state = (ckpt.restore() if ckpt else None) or {
        "episode": 0,
        "frames": 0,
        "replayed": 0,
        "curve": [],
    }
    frames, episodes, replayed = state["frames"], state["episode"], state["replayed"]
    rows: list[dict[str, Any]] = state["curve"]
    torch_rng = read_rng(ckpt.path / RNG_FILE) if frames else None
    for _ in range(episodes):
        run.env.reset()
    returns = EpisodeReturns(batch, next(iter(learner.group_map)), episodes)
    losses: dict[str, float] = {}
    clock = LoopTime(state.get("spent"))  # a resumed run's earlier processes included
    if total_frames == 0:
        instantiate(cfg.logger)(run_dir=run_dir).close()
        return {"env_ticks": 0, "wall_s": 0.0, "episodes": 0, "gradient_steps": 0}
    # a run shorter than one batch (a benchmark's warm-up) trains once, on all of it
    per_batch = min(int(learner.hp["frames_per_batch"]), total_frames)
    collector = Collector(
        env,
        learner.actor,
        frames_per_batch=per_batch,
        total_frames=total_frames - frames,
        env_device="cpu",
        policy_device=learner.device,
        storing_device=learner.device,
        auto_register_policy_transforms=False,
    )
    if torch_rng is not None:  # after building the collector, which may draw from torch
        torch.set_rng_state(torch_rng)

    def save_files(folder: Path) -> None:
        write_tensors(torch.get_rng_state(), folder / RNG_FILE)

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
            for row in finished:
                curve.log(row)
                rows.append(row)
            tick = time.perf_counter()
            losses = learner.train_batch(data)
            replayed += n_frames * int(learner.hp["epochs"])
            clock.add("train_s", time.perf_counter() - tick)
            fps_collection = frames / max(clock.total("collect_s"), 1e-9)
            fps_training = replayed / max(clock.total("train_s"), 1e-9)
            for key, value in {
                **losses,
                "fps/collection": fps_collection,
                "fps/training": fps_training,
            }.items():
                scalars.log_scalar(key, value, step=frames)
            bar.update(n_frames)
            bar.set_postfix(
                {"return": returns.recent, "fps": f"{fps_collection:.0f}/{fps_training:.0f}"},
                refresh=False,
            )
            if ckpt and boundary:  # the batch ends between episodes: resumable here
                loop = {
                    "episode": returns.episodes,
                    "frames": frames,
                    "replayed": replayed,
                    "curve": rows,
                    "spent": clock.spent(),
                }
                ckpt.episode_end(loop, last=frames >= total_frames, files=save_files)
            tick = time.perf_counter()
    collector.shutdown()
    wall = clock.wall()
    info = {
        "env_ticks": frames,
        "wall_s": round(wall, 3),
        "episodes": returns.episodes,
        "gradient_steps": learner.gradient_steps,
        "collect_s": round(clock.total("collect_s"), 3),
        "train_s": round(clock.total("train_s"), 3),
        "fps_collection": round(frames / max(clock.total("collect_s"), 1e-9), 1),
        "fps_training": round(replayed / max(clock.total("train_s"), 1e-9), 1),
        "fps_overall": round(frames / max(wall, 1e-9), 1),
    }
    logger.info(
        "trained %d episodes (%d frames, %d gradient steps) in %.1f s; fps collection %.0f, "
        "training %.0f (frames through the loss/s), overall %.0f",
        returns.episodes,
        frames,
        learner.gradient_steps,
        wall,
        info["fps_collection"],
        info["fps_training"],
        info["fps_overall"],
    )
    return info

"""The training loop of every torch learner: TorchRL Collector -> buffer -> gradient steps.

One loop for the Q-learners, the policy-gradient learners and any other
:class:`~mrta_rl.learners.neural.torch_learner.TorchLearner`, as BenchMARL's ``Experiment`` is one
loop for its algorithms. It plays ``train.episodes`` episodes of ``train.batch_size`` copies (the
shared ``train.*`` budget, so ``debug=smoke`` shrinks it to a few hundred frames): a TorchRL
``Collector`` runs the learner's collection policy on
:class:`~mrta_rl.envs.torchrl_env.AuctionTorchRLEnv` for ``frames_per_batch`` frames (whole ticks of
every copy), :meth:`process_batch` turns the batch into the rows the buffer keeps, and
``updates_per_batch`` gradient steps are taken on minibatches sampled from it (after
``warmup_frames``). The learner's regime picks the buffer (``runners/replay.py``): on-policy, one
batch sampled without replacement and then dropped; off-policy, a replay of ``buffer_size``
transitions sampled at random. A frame is one copy-tick, as in every runner.

On a family of teams (``system.family``) a learner whose settings fit any team plays team ``e`` in
training episode ``e``, as on the numpy loop: the learner is bound to the team, and a view and a
collector are built for its episode.

Training checkpoints are taken where a batch ends between episodes; they hold the learner (weights,
optimiser and its own training state), the buffer's rows and torch's generator (exploration,
sampling), so a resumed run ends as the uninterrupted one.

Outputs: curve.csv (one row per episode, :class:`~mrta_rl.runners.episodes.EpisodeReturns`),
TorchRL logger scalars (the loss's diagnostics, epsilon, frames per second) and the returned
``train`` info.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Iterator
from contextlib import nullcontext
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch
from hydra.utils import instantiate
from omegaconf import DictConfig
from tensordict import TensorDictBase

from mrta_rl.cluster.collection import CollectionWorkers
from mrta_rl.envs import AuctionEnv
from mrta_rl.learners.neural.tensor_files import read_weights, write_tensors
from mrta_rl.run_layout import STATE_FILE, RunDirError
from mrta_rl.runners.checkpoint import LoopTime
from mrta_rl.runners.episodes import EpisodeReturns
from mrta_rl.runners.evaluate import evaluate_policy
from mrta_rl.runners.progress import progress_bar
from mrta_rl.runners.replay import ONE_TEAM, REPLAY_FILE, LoopBuffer, read_replay, replay_layout
from mrta_rl.runners.train import family_env
from mrta_rl.splits import split_seed

if TYPE_CHECKING:
    from mrta_rl.learners.neural.torch_learner import TorchLearner
    from mrta_rl.runners.train import RunSetup

logger = logging.getLogger(__name__)

# Small networks and a numpy env: one intra-op thread is fastest, and on a shared machine more
# threads spin against each other (measured: 3.4 ms vs 1.2 ms per env step of 16 copies).
TORCH_THREADS = 1
COUNTERS = ("frames", "replayed")  # this loop's counters in a checkpoint, besides the episode
# train.keep_best: a checkpoint's loop holds best_episode and best_return, its folder the weights
BEST_FILE = "best_weights.pt"


def train_loop(run: RunSetup, cfg: DictConfig, run_dir: Path) -> dict[str, Any]:
    """Train ``run.learner`` (a :class:`TorchLearner`) for ``train.episodes`` episodes.

    Args:
        run: The built run (training env, learner, family of teams if any).
        cfg: The run config (``seed``, ``train`` and ``logger`` groups).
        run_dir: Output folder of curve.csv and the TorchRL logs.

    Returns:
        ``{"env_ticks", "wall_s", "episodes", "gradient_steps", "collect_s", "train_s",
        "fps_collection", "fps_training", "fps_overall"}``: seconds of the loop, of collection
        and of gradient steps; frames per second of collection (copy-ticks collected per second
        spent collecting), of training (transitions through the loss per second spent in
        gradient steps) and overall (copy-ticks per second of the whole loop). A resumed run's
        seconds include those of the processes before it.
    """
    torch.set_num_threads(TORCH_THREADS)
    torch.manual_seed(cfg.seed)  # exploration draws and sampling (the runner seeds torch)
    learner: TorchLearner = run.learner  # type: ignore[assignment]
    batch, horizon = run.env.batch_size, run.params.horizon
    episodes_total = int(cfg.train.episodes)
    total_frames = episodes_total * horizon * batch
    settings = learner.loop_settings(batch, total_frames)
    family = run.family is not None
    validate_every = int(cfg.train.validate_every)
    buffer = LoopBuffer(settings, learner.on_policy, learner.device, horizon * batch)
    # resuming (checkpoints are taken where every copy is between episodes): counters, curve,
    # buffer and torch's generator from the checkpoint, checked before anything is built or
    # written (runners/replay.py); the core env replays the resets of the episodes played,
    # which fixes its task streams (auction.py "Counter-based randomness"); the collector's own
    # first reset then starts the next episode
    ckpt = run.checkpoint
    state = (ckpt.restore() if ckpt else None) or {
        "episode": 0,
        "frames": 0,
        "replayed": 0,
        "curve": [],
    }
    frames, episodes, replayed = state["frames"], state["episode"], state["replayed"]
    best = BestSnapshot(learner, bool(cfg.train.keep_best))
    if state.get("best_episode", 0) != 0:  # a checkpoint's best snapshot so far (checked)
        best.restore(state, ckpt.path)
    rows: list[dict[str, Any]] = state["curve"]
    torch_rng = None  # the checkpoint's, set once the first collector is built
    if frames:
        expected = buffer.expected(frames, episodes, family)

        def layout_of(team: str) -> Any:
            if team == ONE_TEAM:
                return replay_layout(learner.training_view(run.env), learner)
            learner.bind_env(family_env(run, int(team), cfg.seed))
            return replay_layout(learner.training_view(learner.env), learner)

        stored, torch_rng = read_replay(
            ckpt.path / REPLAY_FILE, expected, layout_of, settings.buffer_size
        )
        buffer.restore(stored)
    if not family:
        for _ in range(episodes):
            run.env.reset()
    returns = EpisodeReturns(batch, next(iter(learner.group_map)), episodes)
    # collection on Ray workers: each collects its share of the copies (cluster/collection.py)
    workers = None
    if cfg.train.workers and total_frames > frames:
        workers = CollectionWorkers(
            learner,
            run.env,
            run.partition,
            int(cfg.seed),
            frames // settings.frames_per_batch,
            workers=int(cfg.train.workers),
            address=cfg.train.ray_address,
            log_every_s=cfg.train.log_every_s,
        )
    info: dict[str, float] = {}
    clock = LoopTime(state.get("spent"))  # a resumed run's earlier processes included
    if total_frames == 0:
        instantiate(cfg.logger)(run_dir=run_dir).close()
        return {"env_ticks": 0, "wall_s": 0.0, "episodes": 0, "gradient_steps": 0}

    def collected() -> Iterator[tuple[str, TensorDictBase]]:
        """Collected batches with their team: one collector, or one per team of a family."""
        nonlocal torch_rng
        if workers is not None:  # one team (checked): the workers' collectors, no collector here
            if torch_rng is not None:
                torch.set_rng_state(torch_rng)
                torch_rng = None
            for data in workers.batches(settings.frames_per_batch, total_frames - frames):
                yield ONE_TEAM, data
            return
        if not family:
            teams = [(ONE_TEAM, learner.training_view(run.env), total_frames - frames)]
        else:
            teams = (
                (str(e), None, horizon * batch) for e in range(episodes + 1, episodes_total + 1)
            )
        for team, view, team_frames in teams:
            if view is None:  # a team of its own each episode (systems/family.py)
                env = family_env(run, int(team), cfg.seed)
                learner.bind_env(env)
                view = learner.training_view(env)
            # building a collector may draw from torch (its policy runs once): the one collector
            # of a team is built before the run's first draw, and a family's next one after the
            # checkpoint, so the checkpoint's generator goes in after, or before, building it
            if torch_rng is not None and family:
                torch.set_rng_state(torch_rng)
                torch_rng = None
            collector = learner.collector(view, settings.frames_per_batch, team_frames)
            if torch_rng is not None:
                torch.set_rng_state(torch_rng)
                torch_rng = None
            for data in collector:
                yield team, data
            collector.shutdown()

    with (
        instantiate(cfg.logger)(run_dir=run_dir) as curve,
        progress_bar(
            total=total_frames,
            initial=frames,
            unit="frame",
            unit_scale=True,
            desc=f"train {run.name}",
            enabled=cfg.train.progress_bar,
            log_every_s=cfg.train.log_every_s,
            episode_units=horizon * batch,
        ) as bar,
        ckpt.catch_interrupt() if ckpt else nullcontext(),
        workers or nullcontext(),
    ):
        for row in rows:
            curve.log(row)
        scalars = curve.torchrl_logger  # the run's tracker (logger=csv|tensorboard|wandb|mlflow)
        tick = time.perf_counter()
        for team, data in collected():  # [B, T]
            clock.add("collect_s", time.perf_counter() - tick)
            n_frames = data.numel()
            finished, boundary = returns.add(data, frames)
            frames += n_frames
            episodes = returns.episodes
            for row in finished:
                curve.log(row)
                rows.append(row)
            buffer.extend(learner.process_batch(data), team)
            learner.after_collect(n_frames)
            tick = time.perf_counter()
            if frames >= settings.warmup_frames:
                info = _train(learner, buffer, settings.updates_per_batch)
                replayed += settings.updates_per_batch * settings.minibatch_size
            if learner.on_policy:
                buffer.clear()
            clock.add("train_s", time.perf_counter() - tick)
            # the episodes this batch finished, validated with the weights it trained
            for row in finished if validate_every else ():
                if row["episode"] % validate_every == 0:
                    value = validation_return(run, cfg)
                    scalars.log_scalar("val/team_return", value, step=row["env_ticks"])
                    logger.info("episode %d: validation return %.1f", row["episode"], value)
                    best.offer(row["episode"], value)
            fps_collection = frames / max(clock.total("collect_s"), 1e-9)
            fps_training = replayed / max(clock.total("train_s"), 1e-9)
            epsilon = getattr(learner, "epsilon", None)
            shown = {} if epsilon is None else {"train/epsilon": epsilon}
            for key, value in {
                **info,
                **shown,
                "fps/collection": fps_collection,
                "fps/training": fps_training,
            }.items():
                scalars.log_scalar(key, value, step=frames)
            bar.update(n_frames)
            postfix = {"return": returns.recent}
            if epsilon is not None:
                postfix["eps"] = f"{epsilon:.3f}"
            postfix["fps"] = f"{fps_collection:.0f}/{fps_training:.0f}"
            bar.set_postfix(postfix, refresh=False)
            if ckpt and boundary:  # the batch ends between episodes: resumable here
                loop = {"episode": episodes, "frames": frames, "replayed": replayed, "curve": rows}
                loop |= {"spent": clock.spent(), **best.counters()}

                def files(folder: Path) -> None:
                    buffer.save(folder / REPLAY_FILE)
                    best.save(folder)

                ckpt.episode_end(loop, last=frames >= total_frames, files=files)
            tick = time.perf_counter()
    if family:  # evaluated on the family's evaluation team
        learner.bind_env(run.env)
    best.keep()
    wall = clock.wall()
    out = {
        "env_ticks": frames,
        "wall_s": round(wall, 3),
        "episodes": episodes,
        "gradient_steps": learner.gradient_steps,
        "collect_s": round(clock.total("collect_s"), 3),
        "train_s": round(clock.total("train_s"), 3),
        "fps_collection": round(frames / max(clock.total("collect_s"), 1e-9), 1),
        "fps_training": round(replayed / max(clock.total("train_s"), 1e-9), 1),
        "fps_overall": round(frames / max(wall, 1e-9), 1),
        **learner.train_info(),
        **best.info(),
        **({"workers": workers.summary()} if workers is not None else {}),
    }
    logger.info(
        "trained %d episodes (%d frames, %d gradient steps) in %.1f s; fps collection %.0f, "
        "training %.0f (transitions through the loss/s), overall %.0f",
        episodes,
        frames,
        learner.gradient_steps,
        wall,
        out["fps_collection"],
        out["fps_training"],
        out["fps_overall"],
    )
    return out


class BestSnapshot:
    """The weights of the best validation return so far, kept for the end (``train.keep_best``).

    Args:
        learner: The run's torch learner.
        enabled: ``train.keep_best``; when False, nothing is kept.
    """

    def __init__(self, learner: TorchLearner, enabled: bool) -> None:
        self.learner, self.enabled = learner, enabled
        self.episode, self.value = 0, -math.inf
        self.weights: dict[str, torch.Tensor] | None = None

    def offer(self, episode: int, value: float) -> None:
        """Keep the learner's weights if ``value`` beats the best so far (ties: the earlier)."""
        if self.enabled and value > self.value:
            self.episode, self.value = episode, value
            state = self.learner.networks.state_dict()
            self.weights = {name: tensor.detach().clone() for name, tensor in state.items()}

    def counters(self) -> dict[str, Any]:
        """What a checkpoint's loop holds of it: the episode, and its value when there is one."""
        return {"best_episode": self.episode} | (
            {"best_return": self.value} if self.episode else {}
        )

    def save(self, folder: Path) -> None:
        """Write the kept weights into a checkpoint folder (nothing when none is kept)."""
        if self.weights is not None:
            write_tensors(self.weights, folder / BEST_FILE)

    def restore(self, loop: dict[str, Any], folder: Path) -> None:
        """The best snapshot of a checkpoint, its weights checked against the learner's networks.

        Raises:
            RunDirError: naming the file or the key, if the value or the weights are refused.
        """
        episode, value = loop["best_episode"], loop.get("best_return")
        if not isinstance(episode, int) or not 0 < episode <= loop["episode"]:
            raise RunDirError(
                f"{folder / STATE_FILE}: loop.best_episode: must be an episode played, "
                f"got {episode!r}"
            )
        if (
            not isinstance(value, (int, float))
            or isinstance(value, bool)
            or not math.isfinite(value)
        ):
            raise RunDirError(
                f"{folder / STATE_FILE}: loop.best_return: must be a finite number, got {value!r}"
            )
        self.episode, self.value = episode, float(value)
        self.weights = read_weights(folder / BEST_FILE, self.learner.networks)

    def keep(self) -> None:
        """At the end of training: the learner takes the kept weights (if any)."""
        if self.weights is not None:
            self.learner.networks.load_state_dict(self.weights)
            logger.info(
                "kept the weights of episode %d, the best validation return (%.1f)",
                self.episode,
                self.value,
            )

    def info(self) -> dict[str, float]:
        """The run's ``train`` info: the episode kept and its validation return."""
        if self.weights is None:
            return {}
        return {"best_episode": self.episode, "best_validation_return": round(self.value, 4)}


def validation_return(run: RunSetup, cfg: DictConfig) -> float:
    """The greedy policy's mean team return on ``train.validate_episodes`` validation streams.

    Played on the run's evaluation team (a family's: its evaluation team), on an env of its
    own: the training env, torch's generator and the learner's are left as they were, so a run
    that validates trains as one that does not.
    """
    learner: TorchLearner = run.learner  # type: ignore[assignment]
    episodes = int(cfg.train.validate_episodes)
    training_env = learner.env
    if training_env is not run.env:  # a family's team: the evaluation team's sizes
        learner.bind_env(run.env)
    env = AuctionEnv(run.system, run.params, batch_size=episodes, active_tasks=run.env.active_tasks)
    summary = evaluate_policy(learner, env, episodes, split_seed("validation"))
    if training_env is not run.env:
        learner.bind_env(training_env)
    return float(summary.team_return_mean)


def _train(learner: TorchLearner, buffer: LoopBuffer, updates: int) -> dict[str, float]:
    """``updates`` gradient steps on sampled minibatches; the means of their diagnostics."""
    sums: dict[str, float] = {}
    for _ in range(updates):
        for key, value in learner.train_step(buffer.sample().to(learner.device)).items():
            sums[key] = sums.get(key, 0.0) + value
    return {key: value / updates for key, value in sums.items() if math.isfinite(value)}

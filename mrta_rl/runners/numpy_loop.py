"""Training loop of numpy learners (kinds "tabular", "search"); no training for fixed policies.

The loop is the one of ``mrta_rl.learners.base`` (shared interface 2): encode, act with
exploration, step all ``B`` copies, encode again, update, the learner's calls fused into one
``train_tick`` per tick (``learners/tabular/base.py``; :func:`interface_tick` for a learner
without it); when the copies are done (they share the horizon, so they finish together) read
the stats, reset and call ``end_episode``. One training episode is one horizon of all copies;
curve.csv gets one row per episode.
"""

from __future__ import annotations

import logging
import math
import numbers
from collections import deque
from collections.abc import Callable
from contextlib import nullcontext
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hydra.utils import instantiate
from omegaconf import DictConfig

from mrta_rl.cluster.population import PopulationWorkers
from mrta_rl.runners.checkpoint import LoopTime
from mrta_rl.runners.progress import progress_bar
from mrta_rl.runners.train import family_env

if TYPE_CHECKING:
    from mrta_rl.envs import AuctionEnv, StepResult
    from mrta_rl.learners.base import Learner
    from mrta_rl.runners.train import RunSetup

logger = logging.getLogger(__name__)

RECENT_EPISODES = 10  # the progress bar shows the mean team return over this many episodes
COUNTERS = ("env_ticks",)  # this loop's counters in a checkpoint, besides the episode


def skip_training(run: RunSetup, cfg: DictConfig, run_dir: Path) -> dict[str, Any]:
    """Fixed policies do not train; write an empty curve.csv (header only) for uniform outputs.

    Args:
        run: The built run.
        cfg: The run config (``logger`` group).
        run_dir: Output folder.

    Returns:
        ``{"env_ticks": 0, "wall_s": 0.0, "episodes": 0}``.
    """
    logger.info("train %s: a fixed policy, nothing to train", run.name)  # its progress line
    instantiate(cfg.logger)(run_dir=run_dir).close()
    return {"env_ticks": 0, "wall_s": 0.0, "episodes": 0}


def interface_tick(learner: Learner) -> Callable[[AuctionEnv, StepResult | None], Any]:
    """``TabularLearner.train_tick`` made of the shared interface's calls, one by one.

    For a learner of kind "tabular" with only ``encode`` / ``act`` / ``update``.

    Args:
        learner: Any learner.

    Returns:
        ``tick(env, result)``: encode, update unless ``result`` is None, act unless the episode
        has ended (then None).
    """
    last: list[Any] = []  # the view and actions of the last decision

    def tick(env: AuctionEnv, result: StepResult | None) -> Any:
        view = learner.encode(env)
        if result is not None:
            learner.update(*last, result, view, env.action_mask)
        if env.done.any():
            return None
        last[:] = view, learner.act(view, env.action_mask, explore=True)
        return last[1]

    return tick


def train_loop(run: RunSetup, cfg: DictConfig, run_dir: Path) -> dict[str, Any]:
    """Train ``run.learner`` on ``run.env`` for ``cfg.train.episodes`` episodes.

    Args:
        run: The built run (training env and learner).
        cfg: The run config (``train`` and ``logger`` groups).
        run_dir: Output folder of curve.csv.

    Returns:
        ``{"env_ticks": copy-ticks played, "wall_s": seconds, "episodes": episodes}``; a resumed
        run's seconds include those of the processes before it.
    """
    env, learner = run.env, run.learner
    horizon, batch = run.params.horizon, env.batch_size
    train_tick = getattr(learner, "train_tick", None) or interface_tick(learner)
    recent: deque[float] = deque(maxlen=RECENT_EPISODES)
    # resuming: the checkpoint's counters and curve; the env replays its resets, because every
    # copy starts an episode at each reset and the episode's streams depend only on the seed and
    # the episode count (auction.py "Counter-based randomness")
    ckpt = run.checkpoint
    state = (ckpt.restore() if ckpt else None) or {"episode": 0, "env_ticks": 0, "curve": []}
    rows: list[dict[str, Any]] = state["curve"]
    env_ticks = state["env_ticks"]
    clock = LoopTime(state.get("spent"))
    if run.family is None:
        for _ in range(state["episode"] + 1):
            env.reset()
    # an ES step's members on Ray workers: the same episodes, played elsewhere (cluster/)
    workers = (
        PopulationWorkers(learner, cfg.train.workers, cfg.train.ray_address, cfg.train.log_every_s)
        if cfg.train.workers
        else None
    )
    with (
        workers or nullcontext(),
        instantiate(cfg.logger)(run_dir=run_dir) as curve,
        progress_bar(
            total=cfg.train.episodes * horizon,
            initial=state["episode"] * horizon,
            unit="tick",
            desc=f"train {run.name}",
            enabled=cfg.train.progress_bar,
            log_every_s=cfg.train.log_every_s,
            episode_units=horizon,
        ) as bar,
        ckpt.catch_interrupt() if ckpt else nullcontext(),
    ):
        for row in rows:
            curve.log(row)
            recent.append(row["team_return_mean"])
        for episode in range(state["episode"] + 1, cfg.train.episodes + 1):
            if run.family is not None:  # a team of its own each episode (systems/family.py)
                env = family_env(run, episode, cfg.seed)
                learner.bind_env(env)
                env.reset()
            if workers is not None:
                returns, team_returns = workers.play(env)
                learner.record_returns(returns)
                bar.update(horizon)
            else:
                # encode, eq. (3) and act: one compiled call per tick (TabularLearner.train_tick)
                actions = train_tick(env, None)
                while actions is not None:  # copies share the horizon: all finish together
                    actions = train_tick(env, env.step(actions))
                    bar.update(1)
                team_returns = env.stats.team_return
            env_ticks += horizon * batch  # ticks x copies: transitions per robot
            team_return = float(team_returns.mean())
            env.reset()
            learner.end_episode()
            recent.append(team_return)
            row = {"env_ticks": env_ticks, "episode": episode, "team_return_mean": team_return}
            curve.log(row)
            rows.append(row)
            postfix = {"return": f"{sum(recent) / len(recent):.1f}"}
            epsilon = getattr(learner, "epsilon", None)
            if isinstance(epsilon, numbers.Real) and math.isfinite(epsilon):
                postfix["eps"] = f"{float(epsilon):.3f}"
                curve.torchrl_logger.log_scalar("train/epsilon", float(epsilon), step=env_ticks)
            bar.set_postfix(postfix, refresh=False)
            logger.debug("episode %d: team return %.1f", episode, team_return)
            if ckpt:
                loop = {"episode": episode, "env_ticks": env_ticks, "curve": rows}
                loop["spent"] = clock.spent()
                ckpt.episode_end(loop, last=episode == cfg.train.episodes)
    wall = clock.wall()
    logger.info("trained %d episodes (%d env ticks) in %.1f s", cfg.train.episodes, env_ticks, wall)
    info = {"env_ticks": env_ticks, "wall_s": round(wall, 3), "episodes": int(cfg.train.episodes)}
    return info | ({"workers": workers.summary()} if workers is not None else {})

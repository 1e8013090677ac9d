"""Shared evaluation of every learner kind, the greedy baseline, and the summary text.

Evaluation plays ``eval.episodes`` episodes, ``eval.batch_size`` copies at a time, on an env whose
copy ``b`` is seeded ``s + b``, ``s`` the seed of the split ``eval.split`` (``mrta_rl/splits.py``:
``test`` 1,000,000, the streams the docs report; ``validation`` 2,000,000, the streams choices are
made on); each round starts with a fresh reset, which advances every copy's episode counter
deterministically. Task arrivals depend only on the seed and the episode counter, never on
actions or active task sets, so the learner and the greedy baseline, and every learner and
training seed, are scored on identical task streams. The learner acts with ``explore=False`` and
does not update.

The greedy baseline is the plain auction: it runs on the *unpartitioned* system (every robot bids
with its full task set ``Gamma_i``), even when the learner uses a subG partition's ``Lambda_i``.
"""

from __future__ import annotations

import logging
import math
from typing import TYPE_CHECKING, Any

import numpy as np
from omegaconf import DictConfig, OmegaConf

from mrta_rl.envs import AuctionEnv, EpisodeStats
from mrta_rl.learners import GreedyLearner, Learner
from mrta_rl.metrics import EpisodeSummary, format_percent, summarize
from mrta_rl.partition import Partition
from mrta_rl.splits import DEFAULT_SPLIT, split_seed

if TYPE_CHECKING:
    from mrta_rl.runners.run_setup import RunSetup

logger = logging.getLogger(__name__)


def evaluate_policy(learner: Learner, env: AuctionEnv, episodes: int, seed: int) -> EpisodeSummary:
    """Play ``episodes`` evaluation episodes without exploration or learning.

    Args:
        learner: The policy.
        env: Evaluation env; reseeded here so that copy ``b`` uses ``seed + b``.
        episodes: Episodes in total; rounds of ``env.batch_size`` copies, the last one trimmed.
        seed: Evaluation seed.

    Returns:
        CTR, ITR and team return pooled over the episodes.
    """
    env.reset(seed=seed)
    snapshots: list[EpisodeStats] = []
    played = 0
    while played < episodes:
        view = learner.encode(env)
        while not env.done.any():  # copies share the horizon: all finish at the same tick
            env.step(learner.act(view, env.action_mask, explore=False))
            view = learner.encode(env)
        keep = min(env.batch_size, episodes - played)
        stats = env.stats.copy()
        snapshots.append(
            EpisodeStats(*(getattr(stats, f)[:keep] for f in EpisodeStats.__dataclass_fields__))
        )
        played += keep
        env.reset()
    return summarize(snapshots, env.system.robots, env.system.task_types, env.params)


def evaluate_run(run: RunSetup, cfg: DictConfig) -> dict[str, Any]:
    """Evaluate the run's learner and the greedy baseline on the same evaluation seeds.

    Args:
        run: The built (and trained) run.
        cfg: The run config (``eval`` group, ``seed``).

    Returns:
        ``{"eval": {...}, "baseline_greedy": {...}}``, each as :meth:`EpisodeSummary.to_json`;
        ``eval`` also names the split played (``"split": "test"``) and, for a learner that
        reports one (:meth:`~mrta_rl.learners.Learner.decision_time`), its decision time.
    """
    split = eval_split(cfg)
    seed = split_seed(split)  # validate_config refused an eval.seed other than this one
    batch = min(cfg.eval.batch_size, cfg.eval.episodes)
    env = AuctionEnv(
        run.system, run.params, batch_size=batch, active_tasks=run.active_tasks, seed=seed
    )
    learned = evaluate_policy(run.learner, env, cfg.eval.episodes, seed)
    # the plain auction uses the full task sets Gamma_i (active_tasks=None), see module docstring
    plain_env = AuctionEnv(run.system, run.params, batch_size=batch, seed=seed)
    greedy = GreedyLearner(env=plain_env, rng=np.random.default_rng(cfg.seed))
    baseline = evaluate_policy(greedy, plain_env, cfg.eval.episodes, seed)
    logger.info(
        "eval team return %.1f (greedy %.1f) over %d episodes of the %s split",
        learned.team_return_mean,
        baseline.team_return_mean,
        learned.episodes,
        split,
    )
    # a learner whose decisions cost time (a planner) reports it, measured over this evaluation
    timing = run.learner.decision_time()
    if timing:
        logger.info(
            "decision time %.2f ms per tick (%d ticks, %.1f s in all)",
            timing["ms_per_tick"],
            timing["ticks"],
            timing["total_s"],
        )
    results = {  # both played the split's streams, and say so
        "eval": {
            **learned.to_json(),
            "split": split,
            **({"decision_time": timing} if timing else {}),
        },
        "baseline_greedy": {**baseline.to_json(), "split": split},
    }
    # the split adds up to the team return only if no task type is shared (partition size bound)
    if run.partition is not None and run.partition.types_disjoint():
        for summary in results.values():
            summary["return_by_group"] = return_by_group(summary, run.partition)
    return results


def eval_split(cfg: DictConfig) -> str:
    """The run's ``eval.split``; ``test`` for a run written before the key existed."""
    return str(OmegaConf.select(cfg, "eval.split", default=None) or DEFAULT_SPLIT)


def return_by_group(summary: dict[str, Any], partition: Partition) -> dict[str, dict[str, Any]]:
    """The team return split by subG sub-group: the part earned by the tasks of its types ``T_g``.

    Each task type belongs to exactly one sub-group, so the parts add up to the team return. For
    the greedy baseline (full task sets) it is what the same types earn under the plain auction.

    Args:
        summary: An :meth:`EpisodeSummary.to_json` block with ``return_by_type``.
        partition: The run's partition.

    Returns:
        ``{"G1": {"types": ["T1", ...], "return": float}, ...}``.
    """
    by_type = summary["return_by_type"]
    return {
        group: {"types": types, "return": round(sum(by_type[t] for t in types), 6)}
        for group, types in partition.group_tasks().items()
    }


def format_summary(metrics: dict[str, Any]) -> str:
    """Readable summary of a metrics.json dict: CTR, ITR, team return, learning space, wall time.

    Args:
        metrics: Content of ``metrics.json`` or ``eval_metrics.json``.

    Returns:
        Plain aligned text (``-`` where a CTR is undefined).
    """
    learned, greedy = metrics["eval"], metrics["baseline_greedy"]
    name = metrics["learner"]["name"]
    width = max(len(name), 6)
    lines = [
        f"{name} on {metrics['system']} (seed {metrics['seed']}), {learned['episodes']} evaluation "
        f"episodes of the {learned.get('split', DEFAULT_SPLIT)} split; baseline: greedy auction "
        "on the full task sets",
        "",
        f"{'team return':<12} {name:>{width}} {_mean_std(learned['team_return'])}   "
        f"greedy {_mean_std(greedy['team_return'])}",
        "",
        f"{'CTR %':<6} {name:>{2 * width + 1}} | {'greedy':>13}",
        f"{'type':<6} {'L':>{width}} {'H':>{width}} | {'L':>6} {'H':>6}",
    ]
    pct = format_percent
    for task in [*learned["ctr"], "all"]:
        mine = learned["ctr_overall"] if task == "all" else learned["ctr"][task]
        base = greedy["ctr_overall"] if task == "all" else greedy["ctr"][task]
        lines.append(
            f"{task:<6} {pct(mine['L']):>{width}} {pct(mine['H']):>{width}} | "
            f"{pct(base['L']):>6} {pct(base['H']):>6}"
        )
    if learned.get("return_by_type"):
        lines += [
            "",
            f"{'return':<6} {name:>{width}} | {'greedy':>7}   (per episode, by task type)",
        ]
        for task, value in learned["return_by_type"].items():
            lines.append(f"{task:<6} {value:>{width}.1f} | {greedy['return_by_type'][task]:>7.1f}")
    if learned.get("return_by_group"):
        lines += [
            "",
            f"{'group':<6} {name:>{width}} | {'greedy':>7}   (return of the sub-group's types)",
        ]
        for group, part in learned["return_by_group"].items():
            base = greedy["return_by_group"][group]["return"]
            types = " ".join(part["types"])
            lines.append(f"{group:<6} {part['return']:>{width}.1f} | {base:>7.1f}   {types}")
    lines += ["", f"{'ITR %':<6} {name:>{width}} | {'greedy':>6}"]
    for robot, value in learned["itr"].items():
        lines.append(f"{robot:<6} {pct(value):>{width}} | {pct(greedy['itr'][robot]):>6}")
    space = metrics.get("learning_space") or {}
    lines += [
        "",
        "learning space: "
        + (", ".join(f"{k} {v:,}" for k, v in space.items()) or "- (fixed policy)"),
    ]
    if "train" in metrics:
        info = metrics["train"]
        lines.append(
            f"training: {info['episodes']} episodes, {info['env_ticks']:,} env ticks, "
            f"{info['wall_s']:.1f} s"
        )
        if "workers" in info:  # where it ran: the Ray workers' record (cluster/workers.py)
            workers = info["workers"]
            retries = len(workers.get("retries", ()))
            lines.append(
                f"on {workers['count']} Ray workers ({workers['nodes']} node"
                f"{'' if workers['nodes'] == 1 else 's'}), peak "
                f"{max(workers['peak_rss_mb'], default=0):,.0f} MiB a worker"
                + (f", {retries} retr{'y' if retries == 1 else 'ies'}" if retries else "")
            )
    return "\n".join(lines)


def _mean_std(block: dict[str, float | None]) -> str:
    mean, std = block["mean"], block["std"]
    if mean is None or (isinstance(mean, float) and math.isnan(mean)):
        return "-"
    return f"{mean:.1f} ± {std:.1f}"

"""Episode metrics (spec "Metrics", paper §5.2): CTR, ITR (eq. 9) and team return.

Every learner and runner reports through :func:`summarize`, which reads
:class:`~mrta_rl.envs.EpisodeStats` snapshots (taken when a batch of copies is done) and pools them:

- **CTR** per task type and priority = assigned / (assigned + dropped), in percent, with counts
  summed over all episodes (tasks still queued at the end are neither, so they are left out). A
  type and priority with no decided task has no CTR: NaN here, ``null`` in JSON, ``-`` in tables.
  The overall CTR of a priority pools the counts over all types.
- **ITR** per robot = (horizon - busy ticks) / horizon in percent (paper eq. 9), pooled over
  episodes as total idle ticks / total ticks (the mean of per-episode ITRs when all episodes are
  full horizons).
- **Team return**: mean and population standard deviation (``ddof=0``) over episodes.
- **Return by task type**: the part of the mean team return earned by each type's tasks,
  assign rewards minus drop penalties (spec step 8) from the counts; the types add up to the team
  return. Summed over a subG sub-group's types, it shows where a partition gains or loses.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mrta_rl.envs import AuctionParams, EpisodeStats
from mrta_rl.types import PRIORITIES, Priority, RobotId, TaskType


def concat_stats(snapshots: Sequence[EpisodeStats]) -> EpisodeStats:
    """Stack snapshots of ``B_1, B_2, ...`` copies into one of ``sum B_k`` episodes.

    Args:
        snapshots: Per-batch :class:`EpisodeStats` (``.copy()`` taken when the copies were done).

    Returns:
        One :class:`EpisodeStats` whose leading axis indexes episodes.

    Raises:
        ValueError: if there is no snapshot or their robot / task type counts differ.
    """
    if not snapshots:
        raise ValueError("no episode to summarize")
    shapes = {(s.assigned.shape[1:], s.busy_ticks.shape[1:]) for s in snapshots}
    if len(shapes) != 1:
        raise ValueError(f"snapshots of different systems cannot be pooled: {sorted(shapes)}")
    return EpisodeStats(
        *(
            np.concatenate([getattr(s, f) for s in snapshots])
            for f in EpisodeStats.__dataclass_fields__
        )
    )


def _percent(numerator: np.ndarray, denominator: np.ndarray) -> np.ndarray:
    """100 * num / den, NaN where den == 0 (no decided task / no tick)."""
    num, den = np.asarray(numerator, np.float64), np.asarray(denominator, np.float64)
    out = np.full(np.broadcast(num, den).shape, np.nan)
    np.divide(100.0 * num, den, out=out, where=den > 0)
    return out


def ctr(stats: EpisodeStats) -> np.ndarray:
    """Completion rate per task type and priority (spec "Metrics"), pooled over episodes.

    Args:
        stats: Counters with a leading episode axis.

    Returns:
        ``[n, 2]`` float percent (index 0 = L, 1 = H); NaN where no task was decided.
    """
    assigned, dropped = stats.assigned.sum(axis=0), stats.dropped.sum(axis=0)  # [n, 2]
    return _percent(assigned, assigned + dropped)


def ctr_overall(stats: EpisodeStats) -> np.ndarray:
    """Completion rate per priority, counts pooled over task types and episodes.

    Args:
        stats: Counters with a leading episode axis.

    Returns:
        ``[2]`` float percent (L, H); NaN where no task of that priority was decided.
    """
    assigned, dropped = stats.assigned.sum(axis=(0, 1)), stats.dropped.sum(axis=(0, 1))  # [2]
    return _percent(assigned, assigned + dropped)


def return_by_type(stats: EpisodeStats, params: AuctionParams) -> np.ndarray:
    """Mean return per episode earned by each task type (spec step 8), from the counts.

    Every team reward is an assign reward or a drop penalty of one task, so the types' parts add
    up to the mean team return.

    Args:
        stats: Counters with a leading episode axis.
        params: The rewards and penalties of the run.

    Returns:
        ``[n]`` float mean return per episode.
    """
    assign = np.array([params.reward_assign_low, params.reward_assign_high])  # (L, H)
    penalty = np.array([params.penalty_drop_low, params.penalty_drop_high])
    total = stats.assigned.sum(axis=0) @ assign - stats.dropped.sum(axis=0) @ penalty  # [n]
    return total / stats.assigned.shape[0]


def itr(stats: EpisodeStats) -> np.ndarray:
    """Idle time rate per robot, (horizon - busy ticks) / horizon in percent (paper eq. 9).

    Args:
        stats: Counters with a leading episode axis; ``ticks`` is each episode's horizon.

    Returns:
        ``[m]`` float percent; NaN if no tick was played.
    """
    ticks = stats.ticks.sum()
    return _percent(ticks - stats.busy_ticks.sum(axis=0), np.full(stats.busy_ticks.shape[1], ticks))


@dataclass(frozen=True)
class EpisodeSummary:
    """Pooled metrics of a set of episodes (spec "Metrics").

    Attributes:
        episodes: Number of episodes pooled.
        team_return_mean: Mean team return per episode.
        team_return_std: Population standard deviation of the team return.
        ctr: Task type -> priority -> CTR percent (NaN if nothing was decided).
        ctr_overall: Priority -> CTR percent over all types.
        itr: Robot -> ITR percent (paper eq. 9).
        return_by_type: Task type -> mean return per episode earned by its tasks (empty when
            the rewards were not given).
        team_returns: The team return of every episode, in episode order (evaluation episode
            ``e`` is played on the same task stream by every learner, so runs can be compared
            episode by episode: paired differences).
    """

    episodes: int
    team_return_mean: float
    team_return_std: float
    ctr: dict[TaskType, dict[Priority, float]]
    ctr_overall: dict[Priority, float]
    itr: dict[RobotId, float]
    return_by_type: dict[TaskType, float] = field(default_factory=dict)
    team_returns: tuple[float, ...] = ()

    def to_json(self) -> dict[str, Any]:
        """JSON-ready nested dict (the ``eval`` block of ``metrics.json``); NaN becomes None."""
        return {
            "episodes": self.episodes,
            "team_return": {
                "mean": _json(self.team_return_mean),
                "std": _json(self.team_return_std),
                "per_episode": [_json(v) for v in self.team_returns],
            },
            "ctr": {t: {p: _json(v) for p, v in by_p.items()} for t, by_p in self.ctr.items()},
            "ctr_overall": {p: _json(v) for p, v in self.ctr_overall.items()},
            "itr": {r: _json(v) for r, v in self.itr.items()},
            "return_by_type": {t: _json(v) for t, v in self.return_by_type.items()},
        }


def summarize(
    snapshots: Sequence[EpisodeStats],
    robots: Sequence[RobotId],
    task_types: Sequence[TaskType],
    params: AuctionParams | None = None,
) -> EpisodeSummary:
    """Pool episode snapshots into CTR, ITR, team return and (given the rewards) its parts.

    Args:
        snapshots: :class:`EpisodeStats` copies of finished batches (each ``[B, ...]``).
        robots: Robot ids, in system order (``system.robots``).
        task_types: Task type ids, in system order (``system.task_types``).
        params: The run's rewards and penalties, for the return by task type (else left out).

    Returns:
        The pooled summary.

    Raises:
        ValueError: if there is no episode, or the ids do not match the counters' shapes.
    """
    stats = concat_stats(snapshots)
    n_types, m = stats.assigned.shape[1], stats.busy_ticks.shape[1]
    if (len(task_types), len(robots)) != (n_types, m):
        raise ValueError(
            f"stats have {n_types} task types and {m} robots, got ids for "
            f"{len(task_types)} and {len(robots)}"
        )
    by_type, overall, idle = ctr(stats), ctr_overall(stats), itr(stats)
    return EpisodeSummary(
        episodes=int(stats.team_return.shape[0]),
        team_return_mean=float(stats.team_return.mean()),
        team_return_std=float(stats.team_return.std()),
        ctr={
            task: {p: float(by_type[j, k]) for k, p in enumerate(PRIORITIES)}
            for j, task in enumerate(task_types)
        },
        ctr_overall={p: float(overall[k]) for k, p in enumerate(PRIORITIES)},
        itr={r: float(idle[i]) for i, r in enumerate(robots)},
        return_by_type=(
            {}
            if params is None
            else dict(zip(task_types, map(float, return_by_type(stats, params)), strict=True))
        ),
        team_returns=tuple(float(v) for v in stats.team_return),
    )


def format_percent(value: float | None, digits: int = 1) -> str:
    """A percentage for tables: ``-`` for NaN or None (no decided task)."""
    if value is None or math.isnan(value):
        return "-"
    return f"{value:.{digits}f}"


def _json(value: float) -> float | None:
    """NaN -> None (JSON ``null``); JSON has no NaN."""
    return None if math.isnan(value) else round(value, 6)

"""Aggregate runs over seeds: CTR (paper Tables 5-6), ITR (Tables 7-8), team return, Table 9.

Every metric of a ``(system, learner)`` cell is the mean over its seeds with a 95 % t interval
(:mod:`mrta_rl.reports.stats`). The per-seed values are the evaluation block of each run's
metrics.json (spec "Metrics": CTR pooled over the evaluation episodes of that seed, ITR eq. 9).
Learning space values are exact Python ints (CQL on System-II exceeds 2**63).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mrta_rl.reports.collect import RECORDED_LABELS, RunRecord, natural_key
from mrta_rl.reports.stats import MeanCI, mean_ci
from mrta_rl.types import PRIORITIES

# Paper names and the order of the paper's tables; learners not listed follow alphabetically.
LEARNER_LABELS: dict[str, str] = {
    "cql": "CQL",
    "semi_cql": "semi-CQL",
    "dql": "DQL",
    "subg_cql": "subG-CQL",
    "subg_dqn": "subG-DQN",
    "vdn": "VDN",
    "qmix": "QMIX",
    "iql": "IQL",
    "reserve_es": "reserve-ES",
    "greedy": "greedy",
    "random": "random",
    "high_only": "high-only",
    "subg_reserve": "subG-reserve",
    "subg_greedy": "subG-greedy",
}
SYSTEM_LABELS: dict[str, str] = {"system1": "System-I", "system2": "System-II"}
PRIORITY_LABELS: dict[str, str] = {"L": "low-priority", "H": "high-priority"}


def learner_label(name: str) -> str:
    """Label of a learner (``subg_cql`` -> ``subG-CQL``); unknown names unchanged.

    The label its runs recorded (metrics.json ``learner.label``) comes first, then the paper's.

    A configuration name keeps what sets it apart: ``subg_reserve reserve=1`` ->
    ``subG-reserve reserve=1`` (``reports/collect.py``).
    """
    base, _, variant = name.partition(" ")
    label = RECORDED_LABELS.get(base) or LEARNER_LABELS.get(base, base)
    return f"{label} {variant}" if variant else label


def order_learners(names: Sequence[str]) -> list[str]:
    """Paper order (CQL, semi-CQL, DQL, subG-CQL, neural, fixed), then the rest alphabetically.

    Configurations of one learner follow each other, their numbers ordered by value.
    """
    known = list(LEARNER_LABELS)

    def key(name: str) -> tuple[Any, ...]:
        base = name.partition(" ")[0]
        rank = known.index(base) if base in known else len(known)
        return (rank, base, natural_key(name))

    return sorted(set(names), key=key)


def system_label(name: str) -> str:
    """Paper name of a system (``system1`` -> ``System-I``); unknown names unchanged."""
    return SYSTEM_LABELS.get(name, name)


def order_systems(names: Sequence[str]) -> list[str]:
    """System-I, System-II, then the rest alphabetically."""
    known = [n for n in SYSTEM_LABELS if n in names]
    return known + sorted(set(names) - set(known))


@dataclass(frozen=True)
class CellSummary:
    """Aggregates of one learner on one system over its seeds.

    Attributes:
        learner: Learner name.
        system: System name.
        seeds: The seeds aggregated.
        task_types: Task type ids in system order.
        robots: Robot ids in system order.
        ctr: ``(task type, priority) -> MeanCI`` of the CTR percent; task type ``"all"`` is the
            overall CTR of the priority (counts pooled over types).
        itr: ``robot -> MeanCI`` of the ITR percent; robot ``"mean"`` is the mean over robots.
        team_return: Evaluation team return per episode.
        greedy_return: The greedy baseline's team return on the same evaluation streams.
        return_gain: Paired per-seed difference learner - greedy.
        learning_space: ``key -> per-seed exact ints`` (``analytic``, ``visited``, ``parameters``).
        train_wall_s: Training wall time per seed (seconds).
        train_env_ticks: Training copy-ticks per seed.
        capable_robots: ``task type -> number of robots whose task set contains it``, from the
            run's system config (empty if unknown).
        group_return: ``sub-group -> MeanCI`` of the return earned by its task types, for runs
            on a subG partition (``return_by_group`` of metrics.json); empty otherwise.
        greedy_group_return: The same split of the greedy baseline's return (full task sets).
        group_types: ``sub-group -> its task types``.
    """

    learner: str
    system: str
    seeds: tuple[int, ...]
    task_types: tuple[str, ...]
    robots: tuple[str, ...]
    ctr: dict[tuple[str, str], MeanCI]
    itr: dict[str, MeanCI]
    team_return: MeanCI
    greedy_return: MeanCI
    return_gain: MeanCI
    learning_space: dict[str, tuple[int, ...]]
    train_wall_s: MeanCI
    train_env_ticks: MeanCI
    capable_robots: dict[str, int]
    group_return: dict[str, MeanCI] = field(default_factory=dict)
    greedy_group_return: dict[str, MeanCI] = field(default_factory=dict)
    group_types: dict[str, tuple[str, ...]] = field(default_factory=dict)

    @property
    def overall_itr(self) -> MeanCI:
        """Mean ITR over the robots (per seed, then over seeds)."""
        return self.itr["mean"]


def _capable_robots(config: dict[str, Any]) -> dict[str, int]:
    """Task type -> number of robots able to do it (paper §6.1: more robots, higher CTR)."""
    robots = (config.get("system") or {}).get("robots") or {}
    counts: dict[str, int] = {}
    for tasks in robots.values():
        for task in tasks or []:
            counts[str(task)] = counts.get(str(task), 0) + 1
    return counts


def summarize_cell(runs: Sequence[RunRecord]) -> CellSummary:
    """Aggregate the seeds of one learner on one system.

    Args:
        runs: The runs, all with the same learner and system (at least one).

    Returns:
        The summary.

    Raises:
        ValueError: if ``runs`` is empty or mixes learners/systems.
    """
    if not runs:
        raise ValueError("no run to summarize")
    if len({(r.learner, r.system) for r in runs}) != 1:
        raise ValueError("a cell holds the runs of one learner on one system")
    evals = [r.metrics["eval"] for r in runs]
    task_types = tuple(evals[0]["ctr"])
    robots = tuple(evals[0]["itr"])
    ctr = {
        (task, p): mean_ci(e["ctr"].get(task, {}).get(p) for e in evals)
        for task in task_types
        for p in PRIORITIES
    }
    ctr.update({("all", p): mean_ci(e["ctr_overall"].get(p) for e in evals) for p in PRIORITIES})
    itr = {robot: mean_ci(e["itr"].get(robot) for e in evals) for robot in robots}
    itr["mean"] = mean_ci(
        float(np.nanmean([np.nan if v is None else v for v in e["itr"].values()])) for e in evals
    )
    returns = [e["team_return"]["mean"] for e in evals]
    greedy = [
        (r.metrics.get("baseline_greedy") or {}).get("team_return", {}).get("mean") for r in runs
    ]
    gains = [
        None if g is None or x is None else x - g for x, g in zip(returns, greedy, strict=True)
    ]
    keys = sorted({k for r in runs for k in (r.metrics.get("learning_space") or {})})
    space = {
        key: tuple(
            int(r.metrics["learning_space"][key])
            for r in runs
            if key in (r.metrics.get("learning_space") or {})
        )
        for key in keys
    }
    train = [r.metrics.get("train") or {} for r in runs]
    groups = evals[0].get("return_by_group") or {}
    baselines = [r.metrics.get("baseline_greedy") or {} for r in runs]

    def group_part(block: dict[str, Any], group: str) -> float | None:
        return ((block.get("return_by_group") or {}).get(group) or {}).get("return")

    return CellSummary(
        learner=runs[0].learner,
        system=runs[0].system,
        seeds=tuple(r.seed for r in runs),
        task_types=task_types,
        robots=robots,
        ctr=ctr,
        itr=itr,
        team_return=mean_ci(returns),
        greedy_return=mean_ci(greedy),
        return_gain=mean_ci(gains),
        learning_space=space,
        train_wall_s=mean_ci(t.get("wall_s") for t in train),
        train_env_ticks=mean_ci(t.get("env_ticks") for t in train),
        capable_robots=_capable_robots(runs[0].config),
        group_return={g: mean_ci(group_part(e, g) for e in evals) for g in groups},
        greedy_group_return={g: mean_ci(group_part(b, g) for b in baselines) for g in groups},
        group_types={g: tuple(part["types"]) for g, part in groups.items()},
    )


def summarize_runs(runs: Sequence[RunRecord]) -> dict[tuple[str, str], CellSummary]:
    """One :class:`CellSummary` per ``(system, learner)``, in report order.

    Args:
        runs: Finished runs.

    Returns:
        ``(system, learner) -> summary``, ordered by system then learner (paper order).
    """
    systems = order_systems([r.system for r in runs])
    learners = order_learners([r.learner for r in runs])
    out: dict[tuple[str, str], CellSummary] = {}
    for system in systems:
        for learner in learners:
            cell = [r for r in runs if r.system == system and r.learner == learner]
            if cell:
                out[(system, learner)] = summarize_cell(sorted(cell, key=lambda r: r.seed))
    return out


@dataclass(frozen=True)
class CurveSummary:
    """Learning curve of one learner on one system over seeds.

    Attributes:
        env_ticks: Training copy-ticks at the end of each episode (x axis).
        mean: Mean team return per episode over seeds at each point.
        low: Lower end of the 95 % interval (equal to the mean with one seed).
        high: Upper end of the 95 % interval.
        seeds: Number of seeds.
    """

    env_ticks: np.ndarray
    mean: np.ndarray
    low: np.ndarray
    high: np.ndarray
    seeds: int


def summarize_curve(runs: Sequence[RunRecord]) -> CurveSummary | None:
    """Mean and 95 % band of the training curves of some seeds.

    Seeds of one config log at the same env ticks; if their lengths differ (an interrupted run),
    the common prefix is kept so every point averages the same seeds.

    Args:
        runs: Runs of one learner on one system.

    Returns:
        The summary, or None if no run has a curve (fixed policies do not train).
    """
    curves = [r.curve for r in runs if r.curve]
    if not curves:
        return None
    length = min(len(c) for c in curves)
    ticks = np.array([c[i][0] for c in curves[:1] for i in range(length)], dtype=np.int64)
    values = np.array([[c[i][1] for i in range(length)] for c in curves])  # [seeds, points]
    stats = [mean_ci(values[:, i]) for i in range(length)]
    mean = np.array([s.mean for s in stats])
    half = np.array([0.0 if math.isnan(s.ci95) else s.ci95 for s in stats])
    return CurveSummary(ticks, mean, mean - half, mean + half, len(curves))

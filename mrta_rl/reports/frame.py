"""The runs as one long table (run x config x metric), and its summary over seeds.

Every table of the report is a pivot of these two frames. Values stay Python objects: the
learning space of CQL on System-II exceeds 2**63.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np
import pandas as pd

from mrta_rl.reports.collect import RunRecord
from mrta_rl.reports.stats import MeanCI, mean_ci
from mrta_rl.types import PRIORITIES, natural_key

SYSTEM_LABELS: dict[str, str] = {"system1": "System-I", "system2": "System-II"}
PRIORITY_LABELS: dict[str, str] = {"L": "low-priority", "H": "high-priority"}
RUN_COLUMNS = ("learner", "label", "name", "kind", "system", "seed", "variant", "run_dir")
# metrics that are columns of runs.csv (``<metric>_<item>_<priority>``); the rest is derived
RUNS_CSV_METRICS = ("team_return", "greedy_team_return", "ctr", "itr", "learning_space", "train")
RUNS_CSV_METRICS += ("decision_time",)  # a planner's decision time (ms_per_tick, total_s...)
STATS = ("n", "mean", "ci95", "std", "low", "high")


def system_label(name: str) -> str:
    """Paper name of a system (``system1`` -> ``System-I``); unknown names unchanged."""
    return SYSTEM_LABELS.get(name, name)


def order_learners(names: Iterable[str], order: Sequence[str] = ()) -> list[str]:
    """The learners of ``order`` in it, then the rest alphabetically (configurations by number)."""

    def key(name: str) -> tuple[Any, ...]:
        base = name.partition(" ")[0]
        return (order.index(base) if base in order else len(order), base, natural_key(name))

    return sorted(set(names), key=key)


def order_systems(names: Iterable[str]) -> list[str]:
    """System-I, System-II, then the rest alphabetically."""
    names = set(names)
    known = [n for n in SYSTEM_LABELS if n in names]
    return known + sorted(names - set(known))


def _rows(run: RunRecord) -> Iterable[tuple[Any, ...]]:
    """``(metric, item, priority, value[, types])`` of one run, in the column order of runs.csv."""
    e, greedy = run.metrics["eval"], run.metrics.get("baseline_greedy") or {}
    yield "team_return", "", "", e["team_return"]["mean"]
    yield "greedy_team_return", "", "", (greedy.get("team_return") or {}).get("mean")
    for p in PRIORITIES:
        yield "ctr", "all", p, e["ctr_overall"].get(p)
    for task, by_priority in e["ctr"].items():
        for p in PRIORITIES:
            yield "ctr", task, p, by_priority.get(p)
    for robot, value in e["itr"].items():
        yield "itr", robot, "", value
    for key, value in (run.metrics.get("learning_space") or {}).items():
        yield "learning_space", key, "", int(value)
    train = run.metrics.get("train") or {}
    for key in ("wall_s", "env_ticks", "episodes"):
        yield "train", key, "", train.get(key)
    for key, value in (e.get("decision_time") or {}).items():  # a planner's, in evaluation
        yield "decision_time", key, "", value
    for block, metric in ((e, "group_return"), (greedy, "greedy_group_return")):
        for group, part in (block.get("return_by_group") or {}).items():
            yield metric, group, "", part["return"], " ".join(part["types"])
    robots = (run.config.get("system") or {}).get("robots") or {}
    for task in e["ctr"]:  # paper §6.1: a type more robots can do has a higher CTR
        if robots:
            yield "capable_robots", task, "", sum(task in (t or []) for t in robots.values())


def long_table(runs: Sequence[RunRecord]) -> pd.DataFrame:
    """The long table of the runs (module docstring), runs in the given order."""
    records = []
    for i, run in enumerate(runs):
        learner = run.metrics.get("learner")
        kind = learner.get("kind", "") if isinstance(learner, dict) else ""
        label = f"{run.label} {run.variant}".strip()  # a configuration keeps what sets it apart
        head = (run.learner, label, run.name, kind, run.system, run.seed, run.variant)
        for row in _rows(run):
            records.append((i, *head, str(run.run_dir), *row, *("",) * (5 - len(row))))
    columns = ["run", *RUN_COLUMNS, "metric", "item", "priority", "value", "types"]
    frame = pd.DataFrame.from_records(records, columns=columns)
    # objects, not floats: ints stay ints (exact learning spaces), None stays undefined
    frame["value"] = pd.Series([r[columns.index("value")] for r in records], dtype=object)
    return frame


def runs_wide(frame: pd.DataFrame) -> pd.DataFrame:
    """One row per run with its flat metrics (runs.csv): ``ctr_T1_L``, ``itr_R1``, ..."""
    rows = frame[frame["metric"].isin(RUNS_CSV_METRICS)]
    columns = zip(rows["metric"], rows["item"], rows["priority"], strict=True)
    rows = rows.assign(column=["_".join(part for part in parts if part) for parts in columns])
    # objects, not floats: the values as metrics.json has them; columns in order of appearance
    wide = pd.DataFrame(
        [
            dict(zip(g["column"], g["value"], strict=True))
            for _, g in rows.groupby("run", sort=False)
        ],
        dtype=object,
    )
    runs = frame.drop_duplicates("run")[["learner", "system", "seed", "run_dir"]]
    return pd.concat([runs.reset_index(drop=True), wide], axis=1)


def _derived(frame: pd.DataFrame) -> pd.DataFrame:
    """Per run: the mean ITR over robots, and the paired gain over greedy (learner - greedy)."""
    per_run = frame.drop_duplicates("run").set_index("run")[list(RUN_COLUMNS)]
    itr = frame[frame["metric"] == "itr"].groupby("run", sort=False)["value"]
    mean_itr = itr.agg(lambda v: float(np.nanmean([np.nan if x is None else x for x in v])))

    def value(metric: str) -> pd.Series:
        return frame[frame["metric"] == metric].set_index("run")["value"]

    ret, greedy = value("team_return"), value("greedy_team_return")
    pairs = zip(ret, greedy.loc[ret.index], strict=True)
    gain = [None if g is None or r is None else r - g for r, g in pairs]
    parts = [
        per_run.loc[mean_itr.index].assign(metric="itr", item="mean", value=mean_itr),
        per_run.loc[ret.index].assign(metric="gain", item="", value=gain),
    ]
    return pd.concat(parts).assign(priority="", types="").reset_index()


def summarize(frame: pd.DataFrame, order: Sequence[str] = ()) -> pd.DataFrame:
    """Mean and 95 % t interval over seeds of every metric of every ``(system, learner)`` cell.

    Cells come by system, then by learner as :func:`order_learners` orders them.
    """
    full = pd.concat([frame, _derived(frame)], ignore_index=True)
    systems = order_systems(full["system"])
    learners = order_learners(full["learner"], order)
    pairs = zip(full["system"], full["learner"], strict=True)
    full["rank"] = [(systems.index(s), learners.index(n)) for s, n in pairs]
    full = full.sort_values("rank", kind="stable")
    seeds = full.groupby(["system", "learner"])["run"].nunique()
    records = []
    keys = ["system", "learner", "metric", "item", "priority"]
    for cell, group in full.groupby(keys, sort=False):
        stat = mean_ci(None if v is None else float(v) for v in group["value"])
        first = group.iloc[0]  # its value is exact: the learning space of the first seed
        record = dict(zip(keys, cell, strict=True)) | {"seeds": int(seeds[cell[:2]])}
        record |= {k: first[k] for k in ("label", "name", "types")} | {"first": first["value"]}
        records.append(record | {k: getattr(stat, k) for k in STATS} | {"stat": stat})
    return pd.DataFrame.from_records(records)


def stat(summary: pd.DataFrame, metric: str, item: str = "", priority: str = "") -> MeanCI:
    """The :class:`MeanCI` of one metric value in a summary of one cell (empty if absent)."""
    rows = summary[summary[["metric", "item", "priority"]].eq([metric, item, priority]).all(axis=1)]
    return rows["stat"].iloc[0] if len(rows) else MeanCI(0, math.nan, math.nan, math.nan)


def band(xs: Any, stats: Sequence[MeanCI]) -> pd.DataFrame:
    """A line and its 95 % band, columns ``x, mean, low, high`` (no band where undefined)."""
    mean, half = (np.array([getattr(s, k) for s in stats], dtype=float) for k in ("mean", "half"))
    return pd.DataFrame({"x": xs, "mean": mean, "low": mean - half, "high": mean + half})


def summarize_curve(runs: Sequence[RunRecord]) -> tuple[pd.DataFrame, int] | None:
    """The :func:`band` of the training curves of some seeds over their common prefix, and seeds.

    An interrupted run logs fewer points: the prefix makes every point average the same seeds.
    """
    curves = [r.curve for r in runs if r.curve]
    if not curves:
        return None
    length = min(len(c) for c in curves)
    ticks = np.array([tick for tick, _ in curves[0][:length]], dtype=np.int64)
    return band(ticks, [mean_ci(c[i][1] for c in curves) for i in range(length)]), len(curves)

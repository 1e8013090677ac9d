"""Tables of the report: pivots of the summary (``reports/frame.py``) as CSV and markdown.

The CSV files keep every digit, the number of seeds and the interval ends; markdown shows
``mean ± 95 % CI`` rounded to one decimal. Learning space sizes are exact integers in the CSV (as
text, since CQL on System-II exceeds 2**63) and scientific notation in markdown.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import pandas as pd

from mrta_rl.reports.frame import runs_wide, system_label
from mrta_rl.reports.stats import MeanCI, mean_ci

_NUMERIC = re.compile(r"^\s*([-+]?[\d.,]+(e[-+]?\d+)?( ± [\d.,e+-]+)?( %)?|–|\?)\s*$")
STAT_COLUMNS = {"seeds": "n_seeds", "mean": "mean", "ci95": "ci95", "std": "std"}
STAT_COLUMNS |= {"low": "ci_low", "high": "ci_high"}
TEAM_METRICS = ("team_return", "greedy_team_return", "gain")  # a cell's return, greedy's, the gain
GROUP_COLUMNS = {"item": "group", "types": "task_types", "seeds": "n_seeds"}
GROUP_COLUMNS |= {"mean": "return_mean", "ci95": "return_ci95"}


def markdown_table(header: Sequence[str], rows: Iterable[Sequence[Any]]) -> str:
    """A GitHub markdown table: text left-aligned, numeric columns (but the first) right-aligned."""
    rows = [[str(v).replace("|", "\\|") for v in row] for row in rows]
    numeric = [i > 0 and all(_NUMERIC.match(row[i]) for row in rows) for i in range(len(header))]
    lines = ["| " + " | ".join(str(h).replace("|", "\\|") for h in header) + " |"]
    lines.append("| " + " | ".join("---:" if num else ":---" for num in numeric) + " |")
    return "\n".join(lines + ["| " + " | ".join(row) + " |" for row in rows])


def write_csv(path: Path, table: pd.DataFrame) -> Path:
    """Write a table as CSV (NaN and None empty, CRLF as the csv module); returns ``path``."""
    table.to_csv(path, index=False, na_rep="", lineterminator="\r\n")
    return path


def big_int(value: int) -> str:
    """Exact below a million (``426``, ``12,288``), else scientific (``1.234e+12``)."""
    return f"{value:,}" if abs(value) < 10**6 else f"{value:.3e}"


def _metric(summary: pd.DataFrame, metric: str) -> pd.DataFrame:
    return summary[summary["metric"] == metric]


def _stats(rows: pd.DataFrame, *keys: str) -> pd.DataFrame:
    return rows[["system", "learner", *keys, *STAT_COLUMNS]].rename(columns=STAT_COLUMNS)


def csv_tables(frame: pd.DataFrame, summary: pd.DataFrame) -> dict[str, pd.DataFrame]:
    """The CSV tables by stem: runs, ctr, itr, team_return, group_return, learning_space."""
    ctr = _cell_sorted(_metric(summary, "ctr"))
    cells = _metric(summary, "team_return").set_index(["system", "learner"])

    parts = [cells[["seeds"]].rename(columns={"seeds": "n_seeds"})]
    for metric, prefix in zip(TEAM_METRICS, ("team_return_", "greedy_", "gain_"), strict=True):
        rows = _metric(summary, metric).set_index(["system", "learner"])[["mean", "ci95"]]
        parts.append(rows.reindex(cells.index).add_prefix(prefix))
    team_return = pd.concat(parts, axis=1)
    team_return["gain_percent"] = [
        100.0 * gain / abs(base) if base and not math.isnan(base) else math.nan
        for gain, base in zip(team_return["gain_mean"], team_return["greedy_mean"], strict=True)
    ]
    keys = ["system", "learner", "item"]
    groups = _metric(summary, "group_return")
    greedy_groups = _metric(summary, "greedy_group_return").set_index(keys)["mean"]
    group_return = groups[[*keys, "types", "seeds", "mean", "ci95"]].rename(columns=GROUP_COLUMNS)
    index = pd.MultiIndex.from_frame(groups[keys])
    group_return["greedy_return_mean"] = greedy_groups.reindex(index).to_numpy()
    return {
        "runs": runs_wide(frame),
        "ctr": _stats(ctr, "item", "priority").rename(columns={"item": "task_type"}),
        "itr": _stats(_metric(summary, "itr"), "item").rename(columns={"item": "robot"}),
        "team_return": team_return.reset_index(),
        "group_return": group_return,
        "learning_space": learning_space_table(frame, summary),
    }


def _cell_sorted(rows: pd.DataFrame) -> pd.DataFrame:
    """Rows of each cell together, cells in order of first appearance, ``all`` after the types."""
    cell = list(zip(rows["system"], rows["learner"], strict=True))
    rank = {c: i for i, c in reversed(list(enumerate(cell)))}
    order = sorted(range(len(rows)), key=lambda i: (rank[cell[i]], rows["item"].iloc[i] == "all"))
    return rows.iloc[order]


def learning_space_table(frame: pd.DataFrame, summary: pd.DataFrame) -> pd.DataFrame:
    """Per cell and key (``analytic``, ``visited``, ``parameters``): exact, min, max, mean, ci95."""
    space = frame[frame["metric"] == "learning_space"]
    rows = []
    for system, learner in dict.fromkeys(zip(summary["system"], summary["learner"], strict=True)):
        cell = space[(space["system"] == system) & (space["learner"] == learner)]
        for key in sorted(set(cell["item"])):
            values = [int(v) for v in cell[cell["item"] == key]["value"]]
            stat = mean_ci(values)
            exact = str(values[0]) if len(set(values)) == 1 else ""
            rows.append(
                [system, learner, key, len(values), exact, str(min(values)), str(max(values))]
                + [stat.mean, stat.ci95]
            )
    columns = ["system", "learner", "key", "n_seeds", "exact", "min", "max", "mean", "ci95"]
    return pd.DataFrame(rows, columns=columns)


# ----------------------------------------------------------------- markdown of one system


def _pivot_text(rows: pd.DataFrame, columns: str, digits: int = 1) -> pd.DataFrame:
    """Learners (labels) x ``columns`` of formatted ``mean ± ci95`` cells, in cell order."""
    text = rows.assign(text=[s.format(digits) for s in rows["stat"]])
    table = text.pivot(index="label", columns=columns, values="text")
    return table.loc[list(dict.fromkeys(text["label"])), list(dict.fromkeys(text[columns]))]


def _markdown_pivot(table: pd.DataFrame, first: str) -> str:
    return markdown_table([first, *table.columns], table.reset_index().to_numpy().tolist())


def ctr_markdown(summary: pd.DataFrame, priority: str) -> str:
    """Rows learners, columns task types and ``all``: CTR of one priority on one system."""
    rows = _metric(summary, "ctr")
    rows = _cell_sorted(rows[rows["priority"] == priority])
    items = [f"all {priority}" if t == "all" else f"{t}{priority}" for t in rows["item"]]
    rows = rows.assign(item=items)
    return _markdown_pivot(_pivot_text(rows, "item"), "learner")


MAX_ROBOT_COLUMNS = 20  # a larger team's ITR table shows the mean over its robots only


def itr_markdown(summary: pd.DataFrame) -> str:
    """Rows learners, columns robots and their mean: ITR on one system.

    A team of more than :data:`MAX_ROBOT_COLUMNS` robots gets the mean column only (every robot
    stays in the CSV).
    """
    itr = _metric(summary, "itr")
    if itr["item"].nunique() - 1 > MAX_ROBOT_COLUMNS:
        itr = itr[itr["item"] == "mean"]
    return _markdown_pivot(_pivot_text(itr, "item"), "learner")


def team_return_markdown(summary: pd.DataFrame, table: pd.DataFrame) -> str:
    """Team return, the greedy baseline on the same streams, and the paired gain, per cell."""
    plain = summary[(summary["item"] == "") & (summary["priority"] == "")]
    stats = plain.set_index(["system", "learner", "metric"])["stat"]
    labels = plain.drop_duplicates(["system", "learner"]).set_index(["system", "learner"])["label"]
    rows = [
        [system_label(r.system), labels[r.system, r.learner], r.n_seeds]
        + [stats[r.system, r.learner, m].format() for m in TEAM_METRICS]
        + ["–" if math.isnan(r.gain_percent) else f"{r.gain_percent:+.1f} %"]
        for r in table.itertuples()
    ]
    header = ["system", "learner", "seeds", "team return", "greedy", "learner - greedy"]
    return markdown_table([*header, "vs greedy"], rows)


def group_return_markdown(summary: pd.DataFrame) -> str:
    """Per sub-group, the return its task types earn: each partitioned learner, then greedy."""
    groups = _metric(summary, "group_return")
    if groups.empty:
        return ""
    parts = {
        n: tuple(zip(g["item"], g["types"], strict=True)) for n, g in groups.groupby("learner")
    }
    if len(set(parts.values())) != 1:
        return ""  # runs on different partitions (random teams of a sweep)
    table = _pivot_text(groups, "item")
    table.columns = [f"{g} ({t})" for g, t in next(iter(parts.values()))]
    team = _metric(summary, "team_return").set_index("label")["stat"]
    table["team"] = [team[label].format() for label in table.index]
    first = summary["learner"] == groups["learner"].iloc[0]
    base = _metric(summary[first], "greedy_group_return")["stat"]
    greedy_team = _metric(summary[first], "greedy_team_return")["stat"].iloc[0]
    table.loc["greedy, full team"] = [*(s.format() for s in base), greedy_team.format()]
    return _markdown_pivot(table, "learner")


def learning_space_markdown(frame: pd.DataFrame, summary: pd.DataFrame) -> str:
    """Table 9: analytic dimension, visited entries (and share), or network parameter counts."""
    table = learning_space_table(frame, summary)
    if table.empty:
        return "_No learner reports a learning space (fixed policies only)._"
    keys = sorted(set(table["key"]), key=lambda k: ({"analytic": 0, "visited": 1}.get(k, 2), k))
    share = "analytic" in keys and "visited" in keys
    labels = summary.drop_duplicates(["system", "learner"]).set_index(["system", "learner"])
    labels = labels["label"]
    space = frame[frame["metric"] == "learning_space"]
    rows = []
    for (system, learner), cell in table.groupby(["system", "learner"], sort=False):
        by_key = {r.key: r for r in cell.itertuples()}
        row: list[Any] = [system_label(system), labels[system, learner]]
        for r in (by_key.get(key) for key in keys):
            spread = "" if r is None or math.isnan(r.ci95) else f" ± {r.ci95:.3g}"
            text = r and (big_int(int(r.exact)) if r.exact else f"{r.mean:.4g}{spread}")
            row.append(text or "–")
        if share:
            mine = space[(space["system"] == system) & (space["learner"] == learner)]
            analytic = list(mine[mine["item"] == "analytic"]["value"])
            visited = list(mine[mine["item"] == "visited"]["value"])
            if analytic and visited and analytic[0] > 0:
                pct = mean_ci(100.0 * v / a for v, a in zip(visited, analytic, strict=False))
                row.append(f"{pct.mean:.3g} %")
            else:
                row.append("–")
        rows.append(row)
    return markdown_table(
        ["system", "learner", *keys, *(["visited / analytic"] if share else [])], rows
    )


def training_time_markdown(summary: pd.DataFrame) -> str:
    """Per cell: seeds, training env ticks and wall time per run."""
    ticks = _metric(summary, "train").query("item == 'env_ticks'")
    wall = _metric(summary, "train").query("item == 'wall_s'")
    rows = [
        [system_label(t.system), t.label, t.seeds, t.stat.format(0), w.stat.format(1)]
        for t, w in zip(ticks.itertuples(), wall.itertuples(), strict=True)
    ]
    header = ["system", "learner", "seeds", "training env ticks per run"]
    return markdown_table([*header, "training wall time per run (s)"], rows)


def signed(value: MeanCI) -> str:
    """``"+19.7 ± 5.7"``; ``"+19.7"`` for one value; ``"–"`` for none."""
    spread = f" ± {value.ci95:.1f}" if value.n > 1 else ""
    return "–" if value.n == 0 else f"{value.mean:+.1f}{spread}"

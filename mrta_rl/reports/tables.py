"""Tables of the report as markdown (for report.md) and as CSV rows (exact values for analysis).

Markdown shows ``mean ± 95 % CI`` rounded to one decimal; the CSV files keep every digit, the
number of seeds and the interval ends. Learning space sizes are exact integers in the CSV (as
text, since CQL on System-II exceeds 2**63) and scientific notation in markdown.
"""

from __future__ import annotations

import csv
import math
import re
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

from mrta_rl.reports.aggregate import CellSummary, learner_label, system_label
from mrta_rl.reports.claims import ClaimResult
from mrta_rl.reports.collect import MissingJob, RunRecord
from mrta_rl.reports.stats import MeanCI, mean_ci
from mrta_rl.types import PRIORITIES

_NUMERIC = re.compile(r"^\s*([-+]?[\d.,]+(e[-+]?\d+)?( ± [\d.,e+-]+)?( %)?|–|\?)\s*$")


def markdown_table(
    header: Sequence[str], rows: Iterable[Sequence[Any]], align_first: bool = True
) -> str:
    """A GitHub markdown table (first column left-aligned, the others right-aligned).

    Args:
        header: Column titles.
        rows: Cell values (converted with ``str``; ``|`` escaped).
        align_first: Left-align the first column.

    Returns:
        The table, lines joined by newlines.
    """

    def cell(value: Any) -> str:
        return str(value).replace("|", "\\|")

    rows = [list(row) for row in rows]
    lines = ["| " + " | ".join(cell(h) for h in header) + " |"]
    # numbers right-aligned, text left-aligned (a column is numeric if every cell looks numeric)
    numeric = [
        all(_NUMERIC.match(str(row[i])) for row in rows) and not (i == 0 and align_first)
        for i in range(len(header))
    ]
    marks = ["---:" if num else ":---" for num in numeric]
    lines.append("| " + " | ".join(marks) + " |")
    lines += ["| " + " | ".join(cell(v) for v in row) + " |" for row in rows]
    return "\n".join(lines)


def write_csv(path: Path, header: Sequence[str], rows: Iterable[Sequence[Any]]) -> Path:
    """Write a CSV file (NaN and None as empty cells).

    Args:
        path: Target file.
        header: Column names.
        rows: Values.

    Returns:
        ``path``.
    """

    def clean(value: Any) -> Any:
        if value is None or (isinstance(value, float) and math.isnan(value)):
            return ""
        return value

    with path.open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(header)
        writer.writerows([clean(v) for v in row] for row in rows)
    return path


def _stat_columns(stat: MeanCI) -> list[Any]:
    return [stat.n, stat.mean, stat.ci95, stat.std, stat.low, stat.high]


STAT_HEADER = ["n_seeds", "mean", "ci95", "std", "ci_low", "ci_high"]


def big_int(value: int) -> str:
    """Exact below a million (``426``, ``12,288``), else scientific (``1.234e+12``)."""
    return f"{value:,}" if abs(value) < 10**6 else f"{value:.3e}"


# ----------------------------------------------------------------- CTR (paper Tables 5-6)


def ctr_markdown(cells: Sequence[CellSummary], priority: str) -> str:
    """Rows learners, columns task types and ``all``: CTR of one priority on one system."""
    types = [*cells[0].task_types, "all"]
    header = ["learner", *[f"{t}{priority}" if t != "all" else f"all {priority}" for t in types]]
    rows = [
        [learner_label(c.learner), *[c.ctr[(t, priority)].format() for t in types]] for c in cells
    ]
    return markdown_table(header, rows)


def ctr_rows(summaries: Iterable[CellSummary]) -> list[list[Any]]:
    """CSV rows ``system, learner, task_type, priority, <stats>`` (task type ``all`` = overall)."""
    return [
        [c.system, c.learner, t, p, *_stat_columns(c.ctr[(t, p)])]
        for c in summaries
        for t in [*c.task_types, "all"]
        for p in PRIORITIES
    ]


# ----------------------------------------------------------------- ITR (paper Tables 7-8)


def itr_markdown(cells: Sequence[CellSummary]) -> str:
    """Rows learners, columns robots and their mean: ITR on one system."""
    robots = [*cells[0].robots, "mean"]
    rows = [[learner_label(c.learner), *[c.itr[r].format() for r in robots]] for c in cells]
    return markdown_table(["learner", *robots], rows)


def itr_rows(summaries: Iterable[CellSummary]) -> list[list[Any]]:
    """CSV rows ``system, learner, robot, <stats>`` (robot ``mean`` = mean over robots)."""
    return [
        [c.system, c.learner, r, *_stat_columns(c.itr[r])]
        for c in summaries
        for r in [*c.robots, "mean"]
    ]


# ----------------------------------------------------------------- team return vs greedy


def _gain_percent(cell: CellSummary) -> float:
    base = cell.greedy_return.mean
    return 100.0 * cell.return_gain.mean / abs(base) if base and not math.isnan(base) else math.nan


def team_return_markdown(summaries: Sequence[CellSummary]) -> str:
    """Team return, the greedy baseline on the same streams, and the paired gain, per system."""
    rows = []
    for c in summaries:
        pct = _gain_percent(c)
        rows.append(
            [
                system_label(c.system),
                learner_label(c.learner),
                len(c.seeds),
                c.team_return.format(),
                c.greedy_return.format(),
                c.return_gain.format(),
                "–" if math.isnan(pct) else f"{pct:+.1f} %",
            ]
        )
    header = [
        "system",
        "learner",
        "seeds",
        "team return",
        "greedy",
        "learner - greedy",
        "vs greedy",
    ]
    return markdown_table(header, rows)


def team_return_rows(summaries: Iterable[CellSummary]) -> list[list[Any]]:
    """CSV rows of team return, greedy return and paired gain, with their intervals."""
    return [
        [
            c.system,
            c.learner,
            len(c.seeds),
            c.team_return.mean,
            c.team_return.ci95,
            c.greedy_return.mean,
            c.greedy_return.ci95,
            c.return_gain.mean,
            c.return_gain.ci95,
            _gain_percent(c),
        ]
        for c in summaries
    ]


TEAM_RETURN_HEADER = [
    "system",
    "learner",
    "n_seeds",
    "team_return_mean",
    "team_return_ci95",
    "greedy_mean",
    "greedy_ci95",
    "gain_mean",
    "gain_ci95",
    "gain_percent",
]


# ----------------------------------------------------------------- return by subG sub-group


def group_return_markdown(summaries: Sequence[CellSummary]) -> str:
    """Per sub-group, the return its task types earn: each partitioned learner, then greedy.

    The cells must be of one system and their learners on the same partition (subG learners on
    one system share it). Empty string if no cell ran on a partition.
    """
    cells = [c for c in summaries if c.group_return]
    if not cells or any(c.group_types != cells[0].group_types for c in cells):
        return ""  # no partition, or runs on different partitions (random teams of a sweep)
    groups = cells[0].group_types
    header = ["learner", *(f"{g} ({' '.join(types)})" for g, types in groups.items()), "team"]
    rows = [
        [
            learner_label(c.learner),
            *(c.group_return[g].format() for g in groups),
            c.team_return.format(),
        ]
        for c in cells
    ]
    base = cells[0]
    rows.append(
        [
            "greedy, full team",
            *(base.greedy_group_return[g].format() for g in groups),
            base.greedy_return.format(),
        ]
    )
    return markdown_table(header, rows)


def group_return_rows(summaries: Iterable[CellSummary]) -> list[list[Any]]:
    """CSV rows: system, learner, sub-group, its types, learner's part and greedy's part."""
    return [
        [
            c.system,
            c.learner,
            g,
            " ".join(c.group_types[g]),
            len(c.seeds),
            stat.mean,
            stat.ci95,
            c.greedy_group_return[g].mean,
        ]
        for c in summaries
        for g, stat in c.group_return.items()
    ]


GROUP_RETURN_HEADER = [
    "system",
    "learner",
    "group",
    "task_types",
    "n_seeds",
    "return_mean",
    "return_ci95",
    "greedy_return_mean",
]


# ----------------------------------------------------------------- learning space (Table 9)


def _space_value(values: tuple[int, ...]) -> tuple[str, MeanCI]:
    """Exact value if every seed agrees (the analytic size), and the spread (visited entries)."""
    exact = str(values[0]) if len(set(values)) == 1 else ""
    return exact, mean_ci(values)


def learning_space_markdown(summaries: Sequence[CellSummary]) -> str:
    """Table 9: analytic dimension, visited entries (and share), or network parameter counts."""
    keys = sorted(
        {k for c in summaries for k in c.learning_space},
        key=lambda k: ({"analytic": 0, "visited": 1}.get(k, 2), k),
    )
    rows = []
    for c in summaries:
        if not c.learning_space:
            continue
        row: list[Any] = [system_label(c.system), learner_label(c.learner)]
        for key in keys:
            values = c.learning_space.get(key)
            if not values:
                row.append("–")
                continue
            exact, stat = _space_value(values)
            if exact:
                row.append(big_int(int(exact)))
            else:
                spread = "" if math.isnan(stat.ci95) else f" ± {stat.ci95:.3g}"
                row.append(f"{stat.mean:.4g}{spread}")
        analytic, visited = c.learning_space.get("analytic"), c.learning_space.get("visited")
        if "analytic" in keys and "visited" in keys:
            if analytic and visited and analytic[0] > 0:
                share = mean_ci(100.0 * v / a for v, a in zip(visited, analytic, strict=False))
                row.append(f"{share.mean:.3g} %")
            else:
                row.append("–")
        rows.append(row)
    header = ["system", "learner", *keys]
    if "analytic" in keys and "visited" in keys:
        header.append("visited / analytic")
    if not rows:
        return "_No learner reports a learning space (fixed policies only)._"
    return markdown_table(header, rows)


def learning_space_rows(summaries: Iterable[CellSummary]) -> list[list[Any]]:
    """CSV rows ``system, learner, key, n_seeds, exact, min, max, mean, ci95`` (ints as text)."""
    rows = []
    for c in summaries:
        for key, values in c.learning_space.items():
            exact, stat = _space_value(values)
            rows.append(
                [
                    c.system,
                    c.learner,
                    key,
                    len(values),
                    exact,
                    str(min(values)),
                    str(max(values)),
                    stat.mean,
                    stat.ci95,
                ]
            )
    return rows


LEARNING_SPACE_HEADER = [
    "system",
    "learner",
    "key",
    "n_seeds",
    "exact",
    "min",
    "max",
    "mean",
    "ci95",
]


# ----------------------------------------------------------------- runs, claims, missing


def run_rows(runs: Sequence[RunRecord]) -> tuple[list[str], list[list[Any]]]:
    """One row per run with its flat evaluation metrics (the numbers behind every table).

    Args:
        runs: Finished runs.

    Returns:
        ``(header, rows)``; columns absent for a system (other task types/robots) are empty.
    """
    flat = []
    for r in runs:
        e = r.metrics["eval"]
        row: dict[str, Any] = {
            "learner": r.learner,
            "system": r.system,
            "seed": r.seed,
            "run_dir": str(r.run_dir),
            "team_return": e["team_return"]["mean"],
            "greedy_team_return": (r.metrics.get("baseline_greedy") or {})
            .get("team_return", {})
            .get("mean"),
        }
        row.update({f"ctr_all_{p}": e["ctr_overall"].get(p) for p in PRIORITIES})
        row.update({f"ctr_{t}_{p}": v for t, by_p in e["ctr"].items() for p, v in by_p.items()})
        row.update({f"itr_{robot}": v for robot, v in e["itr"].items()})
        row.update(
            {
                f"learning_space_{k}": str(v)
                for k, v in (r.metrics.get("learning_space") or {}).items()
            }
        )
        train = r.metrics.get("train") or {}
        row.update(
            {
                "train_wall_s": train.get("wall_s"),
                "train_env_ticks": train.get("env_ticks"),
                "train_episodes": train.get("episodes"),
            }
        )
        flat.append(row)
    header: list[str] = []
    for row in flat:
        header += [k for k in row if k not in header]
    return header, [[row.get(k) for k in header] for row in flat]


def claims_markdown(results: Sequence[ClaimResult]) -> str:
    """One row per claim and system: verdict, separation of the intervals, the numbers."""
    rows = [
        [
            r.statement,
            system_label(r.system) if r.system != "all" else "both",
            f"**{r.verdict}**",
            r.separation or "",
            r.evidence,
        ]
        for r in results
    ]
    return markdown_table(["claim (paper)", "system", "verdict", "95% CIs", "numbers"], rows)


def claims_rows(results: Sequence[ClaimResult]) -> list[list[Any]]:
    """CSV rows ``claim, system, verdict, separation, statement, evidence``."""
    return [[r.claim, r.system, r.verdict, r.separation, r.statement, r.evidence] for r in results]


def missing_markdown(missing: Sequence[MissingJob]) -> str:
    """One row per missing job: identity, reason, job dir and overrides."""
    rows = [
        [
            learner_label(m.learner),
            system_label(m.system),
            "?" if m.seed is None else m.seed,
            m.reason,
            f"`{m.job_dir}`" if m.job_dir else "–",
            f"`{' '.join(m.overrides)}`" if m.overrides else "–",
        ]
        for m in missing
    ]
    return markdown_table(["learner", "system", "seed", "reason", "job dir", "overrides"], rows)


def missing_rows(missing: Sequence[MissingJob]) -> list[list[Any]]:
    """CSV rows ``learner, system, seed, reason, job_dir, overrides``."""
    return [
        [m.learner, m.system, m.seed, m.reason, str(m.job_dir or ""), " ".join(m.overrides)]
        for m in missing
    ]

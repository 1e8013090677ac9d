"""Report sections of the studies: swept dimensions and statistics as the field reports them.

* **Swept dimensions** (:data:`DIMENSIONS`): when the runs differ in the team size
  ``system.n_robots`` (``experiment=scaling``) or the task-switch cost ``env.switch_ticks``
  (``experiment=switch_cost``), the report draws each learner's team return relative to greedy
  against it, and for the team size the learning space (log scale), the wall time and the peak
  memory of the runs; the paper's claims are checked at every value. A run refused up front
  (``refused.json`` instead of ``metrics.json``) is shown as ``refused: <reason>``.
* **Statistics as the field reports them** (rliable's, computed with scipy, ``reports/stats.py``):
  interquartile mean of the greedy-normalized team return with 95 % stratified bootstrap
  intervals, probability of improvement between learners, performance profiles.

A *series* is a learner with its partition bound (``subG-CQL (g=4)``); a *task* (the stratum of
the bootstrap) is one robot team under one setting: the system, the values of the swept
dimensions and the team seed ``system.seed``. A run's *score* is its gain over the greedy auction
on the same evaluation task streams, relative to greedy's: ``(R - G) / |G|`` (0 = greedy's
return, 0.1 = 10 % better). A plain ratio ``R / G`` would flip its meaning where greedy's return
is negative, as on large random teams where greedy's robots collide on the same tasks.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from omegaconf import OmegaConf

from mrta_rl.reports import figures
from mrta_rl.reports.claims import claims_along
from mrta_rl.reports.collect import (
    METRICS_FILE,
    REFUSED_FILE,
    RunRecord,
    config_value,
    refusal_reason,
)
from mrta_rl.reports.frame import long_table, order_learners, summarize, system_label
from mrta_rl.reports.stats import (
    BOOTSTRAP_REPS,
    iqm_ci,
    mean_ci,
    performance_profile,
    probability_of_improvement,
)
from mrta_rl.reports.tables import image, markdown_table, write_csv
from mrta_rl.run_files import CONFIG_FILE, read_json

# swept setting (dotted config key) -> (axis label, file stem, log-scale x axis)
DIMENSIONS: dict[str, tuple[str, str, bool]] = {
    "system.n_robots": ("team size (robots)", "team_size", True),
    "env.switch_ticks": ("task-switch setup ticks s", "switch_ticks", False),
}
BOUND_KEY = "partition.max_group_size"
TEAM_SEED_KEY = "system.seed"
PROFILE_POINTS = 101  # thresholds of a performance profile
STUDY_COLUMNS = ["series", "learner", "system", *DIMENSIONS, "team_seed", "seed"]
STUDY_COLUMNS += ["return_vs_greedy", "team_return", "space_analytic", "space_visited"]
STUDY_COLUMNS += ["parameters", "wall_s", "peak_rss_mb", "refused"]
FIELD_STATS_HEADER = ["statistic", "x", "y", "value", "ci_low", "ci_high", "n_runs"]


def _point(
    label: str,
    learner: str,
    system: str,
    seed: int,
    config: dict[str, Any],
    metrics: dict[str, Any],
    refused: str,
) -> dict[str, Any]:
    ret = ((metrics.get("eval") or {}).get("team_return") or {}).get("mean")
    greedy = ((metrics.get("baseline_greedy") or {}).get("team_return") or {}).get("mean")
    greedy = None if greedy is None else float(greedy)
    resources = metrics.get("resources") or {}
    wall = resources.get("wall_s", (metrics.get("train") or {}).get("wall_s"))
    space = {k: int(v) for k, v in (metrics.get("learning_space") or {}).items()}
    bound = config_value(config, BOUND_KEY)
    settings = {k: config_value(config, k) for k in DIMENSIONS}
    random_team = "n_robots" in (config.get("system") or {})
    team_seed = config_value(config, TEAM_SEED_KEY) if random_team else None
    return {
        "series": label + (f" (g={bound})" if bound is not None else ""),
        "learner": learner,
        "system": system,
        **settings,
        "team_seed": team_seed,
        "seed": seed,
        "return_vs_greedy": (float(ret) - greedy) / abs(greedy)
        if ret is not None and greedy
        else math.nan,
        "team_return": math.nan if ret is None else float(ret),
        "space_analytic": str(space["analytic"]) if "analytic" in space else "",
        "space_visited": space.get("visited", ""),
        "parameters": space.get("parameters", ""),
        "wall_s": math.nan if wall is None else float(wall),
        "peak_rss_mb": float(resources.get("peak_rss_mb", math.nan)),
        "refused": refused,
        "task": (system, tuple(sorted(settings.items())), team_seed),  # the bootstrap stratum
    }


def study_points(runs: Sequence[RunRecord], inputs: Sequence[Path]) -> pd.DataFrame:
    """Every finished run and every refused run below the inputs, one row each.

    A refused run is a dir with ``refused.json`` (``{"learner", "system", "seed", "reason"}``)
    and no metrics.json; its swept values come from its ``.hydra/config.yaml``.
    """
    points = [_point(r.label, r.name, r.system, r.seed, r.config, r.metrics, "") for r in runs]
    found = {p.parent.resolve() for path in inputs for p in Path(path).rglob(REFUSED_FILE)}
    found |= {Path(p).resolve() for p in inputs if (Path(p) / REFUSED_FILE).is_file()}
    for run_dir in sorted(found):
        if (run_dir / METRICS_FILE).is_file():
            continue
        record = read_json(run_dir / REFUSED_FILE)
        path = run_dir / CONFIG_FILE
        config = OmegaConf.to_container(OmegaConf.load(path)) if path.is_file() else {}
        learner, seed = (
            str(record.get("learner", "?")),
            int(record.get("seed", config.get("seed", 0))),
        )
        system, reason = str(record.get("system", "?")), refusal_reason(run_dir)
        points.append(_point(learner, learner, system, seed, config, {}, reason or ""))
    # objects, not floats: the CSV keeps ints as ints and an absent setting empty
    return pd.DataFrame(points, columns=[*STUDY_COLUMNS, "task"], dtype=object)


def swept_dimensions(points: pd.DataFrame) -> list[str]:
    """The :data:`DIMENSIONS` that take at least two values among the points."""
    return [k for k in DIMENSIONS if points[k].dropna().nunique() >= 2]


def order_series(points: pd.DataFrame) -> list[str]:
    """Series in the paper's learner order, bounds after the unbounded learner."""
    learners = order_learners(points["learner"])
    rank = {}
    for series, learner in zip(points["series"], points["learner"], strict=True):
        rank[series] = min(rank.get(series, len(learners)), learners.index(learner))
    return sorted(rank, key=lambda s: (rank[s], s))


def _line(points: pd.DataFrame, dim: str, column: str) -> pd.DataFrame | None:
    """Mean and 95 % interval of ``column`` per value of ``dim`` (None without any value)."""
    rows = []
    for x, group in points.dropna(subset=[dim]).groupby(dim):
        stat = mean_ci(group[column])
        if stat.n:
            half = 0.0 if math.isnan(stat.ci95) else stat.ci95
            rows.append((float(x), stat.mean, stat.mean - half, stat.mean + half))
    return pd.DataFrame(rows, columns=["x", "mean", "low", "high"]) if rows else None


def dimension_table(points: pd.DataFrame, dim: str, system: str) -> str:
    """Markdown: series x values of ``dim``, cells ``score mean ± CI`` or ``refused: reason``."""
    mine = points[points["system"] == system]
    xs = sorted(mine[dim].dropna().unique())
    rows = []
    for series in order_series(mine):
        row = [series]
        for x in xs:
            cell = mine[(mine["series"] == series) & (mine[dim] == x)]
            refused = sorted(set(cell["refused"]) - {""})
            finished = cell[cell["refused"] == ""]["return_vs_greedy"]
            text = mean_ci(finished).format(3) if len(finished) else refused[0] if refused else "–"
            if len(finished) and refused:
                text += f" ({len(refused)} {refused[0]})"
            row.append(text)
        rows.append(row)
    return markdown_table([f"learner \\ {DIMENSIONS[dim][0]}", *map(str, xs)], rows)


def dimension_figures(points: pd.DataFrame, dim: str, out: Path, colors: dict) -> dict[str, Path]:
    """The figures of one swept dimension (see module docstring), by file stem."""
    label, stem, log_x = DIMENSIONS[dim]
    finished = points[points["refused"] == ""].copy()
    series = order_series(finished)

    def panel(rows: pd.DataFrame, column: str, suffix: str = "") -> dict[str, pd.DataFrame]:
        lines = {s + suffix: _line(rows[rows["series"] == s], dim, column) for s in series}
        return {s: line for s, line in lines.items() if line is not None}

    returns = [
        figures.SweepPanel(
            f"{system_label(system)}: team return relative to greedy",
            panel(finished[finished["system"] == system], "return_vs_greedy"),
            label,
            "(R - greedy) / |greedy| (mean, 95% CI)",
            log_x=log_x,
            reference=0.0,
        )
        for system in dict.fromkeys(finished["system"])
    ]
    written = {f"{stem}_return": figures.sweep_figure(returns, out / f"{stem}_return.png", colors)}
    if dim != "system.n_robots":
        return written
    for key, column in (("analytic", "space_analytic"), ("visited", "space_visited")):
        finished[f"log_{key}"] = [
            math.log10(int(v)) if v != "" and int(v) > 0 else math.nan for v in finished[column]
        ]
    finished["log_parameters"] = [
        math.log10(int(v)) if v != "" and int(v) > 0 else math.nan for v in finished["parameters"]
    ]
    space = panel(finished, "log_analytic")
    space |= panel(finished, "log_visited", " (visited)") | panel(
        finished, "log_parameters", " (parameters)"
    )
    title = "learning space: analytic dimension, entries visited, network parameters"
    written[f"{stem}_space"] = figures.sweep_figure(
        [figures.SweepPanel(title, space, label, "log10 of the size", log_x=log_x)],
        out / f"{stem}_space.png",
        colors,
    )
    costs = [
        figures.SweepPanel(title, panel(finished, key), label, unit, log_x=log_x, log_y=True)
        for title, key, unit in (
            ("wall time per run", "wall_s", "seconds"),
            ("peak memory per run", "peak_rss_mb", "peak RSS (MiB)"),
        )
    ]
    written[f"{stem}_cost"] = figures.sweep_figure(costs, out / f"{stem}_cost.png", colors)
    return written


def dimension_claims(runs: Sequence[RunRecord], dim: str) -> str:
    """Markdown: for each claim and system, the values of ``dim`` where it holds or not.

    Runs with a partition bound are left out: the claims are about the paper's subG-CQL. The
    runs of a learner at one value (team seeds and run seeds) make one cell.
    """
    by_value: dict[Any, list[RunRecord]] = {}
    for run in runs:
        value = config_value(run.config, dim)
        if value is not None and config_value(run.config, BOUND_KEY) is None:
            plain = dataclasses.replace(run, learner=run.name, variant="")
            by_value.setdefault(value, []).append(plain)
    along = claims_along({v: summarize(long_table(by_value[v])) for v in by_value})
    rows = [
        [r.claim, system_label(r.system)]
        + [
            ", ".join(map(str, getattr(r, k))) or "none"
            for k in ("holds_at", "fails_at", "not_evaluable_at")
        ]
        for r in along.itertuples()
    ]
    header = ["claim", "system", f"holds at {DIMENSIONS[dim][0]}", "does not hold at"]
    return markdown_table([*header, "not evaluable at"], rows)


def field_statistics(points: pd.DataFrame) -> pd.DataFrame:
    """IQM per series, then P(X > Y) per ordered pair of series over the tasks both ran."""
    scored = points[(points["refused"] == "") & points["return_vs_greedy"].notna()]
    names = order_series(points[points["refused"] == ""])
    by_series = {
        s: scored[scored["series"] == s].groupby("task", sort=False)["return_vs_greedy"].agg(list)
        for s in names
    }
    rows = [("iqm", s, "", iqm_ci(by_series[s].tolist())) for s in names]
    for x in names:
        for y in names:
            if x != y:
                common = [t for t in by_series[x].index if t in by_series[y].index]
                estimate = probability_of_improvement(
                    [by_series[x][t] for t in common], [by_series[y][t] for t in common]
                )
                rows.append(("probability_of_improvement", x, y, estimate))
    return pd.DataFrame(
        [(k, x, y, e.value, e.low, e.high, e.n, e) for k, x, y, e in rows],
        columns=[*FIELD_STATS_HEADER, "estimate"],
    )


def field_statistics_markdown(stats: pd.DataFrame, points: pd.DataFrame) -> str:
    """The IQM table and the probability-of-improvement matrix."""
    iqm = stats[stats["statistic"] == "iqm"]
    finished = points[points["refused"] == ""]
    rows = [
        [s, finished[finished["series"] == s]["task"].nunique(), e.n, e.format(3)]
        for s, e in zip(iqm["x"], iqm["estimate"], strict=True)
    ]
    header = ["learner", "tasks", "runs", "IQM of (R - greedy) / |greedy| [95% CI]"]
    md = [markdown_table(header, rows), ""]
    names = list(iqm["x"])
    if len(names) >= 2:
        pairs = stats[stats["statistic"] != "iqm"].set_index(["x", "y"])["estimate"]
        matrix = [[x, *("–" if x == y else pairs[x, y].format(2) for y in names)] for x in names]
        md += [
            "Probability of improvement P(row > column) [95% CI]: the chance that a run of the "
            "row learner scores higher than a run of the column learner on the same task "
            "(ties count one half), averaged over the tasks both ran.",
            "",
            markdown_table(["P(row > column)", *names], matrix),
            "",
        ]
    return "\n".join(md)


def profile_figure(points: pd.DataFrame, path: Path, colors: dict) -> Path | None:
    """Performance profiles of every series (None if no finished run has a score)."""
    scored = points[(points["refused"] == "") & points["return_vs_greedy"].notna()]
    if scored.empty:
        return None
    low, high = scored["return_vs_greedy"].min(), scored["return_vs_greedy"].max()
    tau = np.linspace(low - 0.01, high + 0.01, PROFILE_POINTS)
    profiles = {
        s: performance_profile(rows.groupby("task", sort=False)["return_vs_greedy"].agg(list), tau)
        for s in order_series(scored)
        if not (rows := scored[scored["series"] == s]).empty
    }
    return figures.profile_figure(profiles, path, colors)


def study_sections(
    runs: Sequence[RunRecord], inputs: Sequence[Path], out: Path
) -> tuple[str, dict[str, Path]]:
    """The field-statistics section and one section per swept dimension, with files."""
    points = study_points(runs, inputs)
    colors = figures.learner_colors(order_series(points))
    colors |= {f"{n} ({k})": c for n, c in list(colors.items()) for k in ("visited", "parameters")}
    stats = field_statistics(points)
    files = {"field_stats": write_csv(out / "field_stats.csv", stats[FIELD_STATS_HEADER])}
    profile = profile_figure(points, out / "performance_profile.png", colors)
    if profile is not None:
        files["performance_profile"] = profile
    md = [
        "## Statistics as the field reports them (IQM, probability of improvement)",
        "",
        "Score of a run = (R - G) / |G|, its evaluation team return R relative to greedy's G on "
        "the same task streams (0 = greedy, 0.1 = 10 % better). "
        "IQM = interquartile mean over the runs of all tasks (a task = a system under one "
        "setting and team seed); 95 % stratified bootstrap intervals (runs resampled within each "
        f"task, {BOOTSTRAP_REPS} resamples, percentile method; Agarwal et al. 2021, as rliable). "
        "Exact values: `field_stats.csv`.",
        "",
        field_statistics_markdown(stats, points),
        image(profile, "Performance profiles"),
        "",
    ]
    dims = swept_dimensions(points)
    if dims:
        files["study"] = write_csv(out / "study.csv", points[STUDY_COLUMNS])
    for dim in dims:
        label, stem, _ = DIMENSIONS[dim]
        written = dimension_figures(points, dim, out, colors)
        files.update(written)
        md += [
            f"## Against the {label} (`{dim}`)",
            "",
            "Team return relative to greedy (mean ± 95 % t interval over team seeds and run "
            "seeds); `refused: ...` = refused up front, with the reason. Every run: `study.csv`.",
            "",
        ]
        for system in dict.fromkeys(points["system"]):
            md += [f"{system_label(system)}:", "", dimension_table(points, dim, system), ""]
        md += [image(written.get(f"{stem}_return"), f"Team return against the {label}"), ""]
        if f"{stem}_space" in written:
            md += [
                "Learning space (log scale; solid: analytic dimension, dashed: entries visited, "
                "dotted: network parameters), wall time and peak memory (RSS) per run:",
                "",
                image(written[f"{stem}_space"], "Learning space against the team size"),
                "",
                image(written[f"{stem}_cost"], "Wall time and memory against the team size"),
                "",
            ]
        md += [
            f"Claims of the paper at each value of `{dim}` (runs without a partition bound):",
            "",
            dimension_claims(runs, dim),
            "",
        ]
    return "\n".join(md), files

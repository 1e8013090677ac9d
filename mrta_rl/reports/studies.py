"""Report sections of the studies (issues 11 and 12): swept dimensions and field statistics.

* **Swept dimensions** (:data:`DIMENSIONS`): when the runs of a report differ in a setting such as
  the team size ``system.n_robots`` (``experiment=scaling``) or the task-switch cost
  ``env.switch_ticks`` (``experiment=switch_cost``), the report draws each learner's team return
  relative to greedy against it, and for the team size the learning space (log scale), the wall
  time and the peak memory of the runs; the paper's claims are checked at every value
  (:func:`mrta_rl.reports.claims.claims_along`). A run refused up front (``refused.json`` instead
  of ``metrics.json``) is shown as ``refused: <reason>``.
* **Statistics as the field reports them** (rliable's, computed with scipy, see
  :mod:`mrta_rl.reports.stats`): interquartile mean of the greedy-normalized team return with 95 %
  stratified bootstrap intervals, probability of improvement between learners, performance
  profiles.

A *series* is a learner with its partition bound (``subG-CQL (g=4)``); a *task* (the stratum of
the bootstrap) is one robot team under one setting: the system, the values of the swept
dimensions and the team seed ``system.seed``. A run's *score* is its gain over the greedy auction
on the same evaluation task streams, relative to greedy's: ``(R - G) / |G|`` (0 = greedy's
return, 0.1 = 10 % better). A plain ratio ``R / G`` would flip its meaning where greedy's return
is negative, as on large random teams where greedy's robots collide on the same tasks.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import OmegaConf

from mrta_rl.reports import figures, tables
from mrta_rl.reports.aggregate import learner_label, order_learners, summarize_runs, system_label
from mrta_rl.reports.claims import claims_along
from mrta_rl.reports.collect import METRICS_FILE, REFUSED_FILE, RunRecord, refusal_reason
from mrta_rl.reports.stats import (
    BOOTSTRAP_REPS,
    Estimate,
    iqm_ci,
    mean_ci,
    performance_profile,
    probability_of_improvement,
)

# swept setting (dotted config key) -> (axis label, file stem, log-scale x axis)
DIMENSIONS: dict[str, tuple[str, str, bool]] = {
    "system.n_robots": ("team size (robots)", "team_size", True),
    "env.switch_ticks": ("task-switch setup ticks s", "switch_ticks", False),
}
BOUND_KEY = "partition.max_group_size"
TEAM_SEED_KEY = "system.seed"
PROFILE_POINTS = 101  # thresholds of a performance profile


def config_value(config: dict[str, Any], dotted: str) -> Any:
    """A run config's value at a dotted key (``system.n_robots``), None if absent."""
    return OmegaConf.select(OmegaConf.create(config), dotted, default=None) if config else None


@dataclass(frozen=True)
class StudyPoint:
    """One run (or refused run) seen by the study sections.

    Attributes:
        series: Learner label with its partition bound, e.g. ``subG-CQL (g=4)``.
        learner: Learner name.
        system: System name.
        seed: Run seed.
        settings: Swept dimension -> value in this run.
        team_seed: ``system.seed`` of a random team (None for a table system).
        score: ``(R - G) / |G|``, team return relative to greedy's (NaN if refused or G = 0).
        team_return: Evaluation team return per episode (NaN if refused).
        learning_space: ``analytic`` / ``visited`` / ``parameters`` of metrics.json.
        wall_s: Wall time of the run (``resources.wall_s``, else ``train.wall_s``).
        peak_rss_mb: Peak resident memory of the run in MiB (NaN if not measured).
        refused: ``refused: <reason>`` for a refused run, else None.
    """

    series: str
    learner: str
    system: str
    seed: int
    settings: dict[str, Any]
    team_seed: Any
    score: float
    team_return: float
    learning_space: dict[str, int]
    wall_s: float
    peak_rss_mb: float
    refused: str | None = None

    @property
    def task(self) -> tuple[Any, ...]:
        """The bootstrap stratum: system, swept values, team seed."""
        return (self.system, tuple(sorted(self.settings.items())), self.team_seed)


def series_name(learner: str, config: dict[str, Any]) -> str:
    """``subG-CQL`` or ``subG-CQL (g=4)`` when the run bounds the partition."""
    bound = config_value(config, BOUND_KEY)
    return learner_label(learner) + (f" (g={bound})" if bound is not None else "")


def _point(
    learner: str,
    system: str,
    seed: int,
    config: dict[str, Any],
    metrics: dict[str, Any] | None,
    refused: str | None,
) -> StudyPoint:
    metrics = metrics or {}
    ret = ((metrics.get("eval") or {}).get("team_return") or {}).get("mean")
    greedy = ((metrics.get("baseline_greedy") or {}).get("team_return") or {}).get("mean")
    greedy = None if greedy is None else float(greedy)
    resources = metrics.get("resources") or {}
    wall = resources.get("wall_s", (metrics.get("train") or {}).get("wall_s"))
    return StudyPoint(
        series=series_name(learner, config),
        learner=learner,
        system=system,
        seed=seed,
        settings={k: config_value(config, k) for k in DIMENSIONS},
        team_seed=config_value(config, TEAM_SEED_KEY)
        if "n_robots" in (config.get("system") or {})
        else None,
        score=(float(ret) - greedy) / abs(greedy) if ret is not None and greedy else math.nan,
        team_return=math.nan if ret is None else float(ret),
        learning_space={k: int(v) for k, v in (metrics.get("learning_space") or {}).items()},
        wall_s=math.nan if wall is None else float(wall),
        peak_rss_mb=float(resources.get("peak_rss_mb", math.nan)),
        refused=refused,
    )


def _load_yaml(path: Path) -> Any:
    return OmegaConf.to_container(OmegaConf.load(path), resolve=False) if path.is_file() else None


def refused_points(inputs: Sequence[Path]) -> list[StudyPoint]:
    """Runs refused up front below the inputs: dirs with ``refused.json`` and no metrics.json.

    ``refused.json`` holds ``{"learner", "system", "seed", "reason"}``; the swept values come from
    the run's ``.hydra/config.yaml``.
    """
    found = sorted(
        {p.parent.resolve() for path in inputs for p in Path(path).rglob(REFUSED_FILE)}
        | {Path(p).resolve() for p in inputs if (Path(p) / REFUSED_FILE).is_file()}
    )
    points = []
    for run_dir in found:
        if (run_dir / METRICS_FILE).is_file():
            continue
        record = json.loads((run_dir / REFUSED_FILE).read_text())
        config = _load_yaml(run_dir / ".hydra" / "config.yaml") or {}
        points.append(
            _point(
                str(record.get("learner", "?")),
                str(record.get("system", "?")),
                int(record.get("seed", config.get("seed", 0))),
                config,
                None,
                refusal_reason(run_dir),
            )
        )
    return points


def base_learner(run: RunRecord) -> str:
    """The learner's yaml stem (``RunRecord.learner`` also names the settings that differ)."""
    return str(run.metrics["learner"]["name"])


def study_points(runs: Sequence[RunRecord], inputs: Sequence[Path]) -> list[StudyPoint]:
    """Every finished run and every refused run as a :class:`StudyPoint`."""
    points = [_point(base_learner(r), r.system, r.seed, r.config, r.metrics, None) for r in runs]
    return points + refused_points(inputs)


def swept_dimensions(points: Sequence[StudyPoint]) -> list[str]:
    """The :data:`DIMENSIONS` that take at least two values among the points."""
    return [
        key
        for key in DIMENSIONS
        if len({p.settings[key] for p in points if p.settings[key] is not None}) >= 2
    ]


def order_series(points: Sequence[StudyPoint]) -> list[str]:
    """Series in the paper's learner order, bounds after the unbounded learner."""
    learners = order_learners([p.learner for p in points])
    return sorted(
        dict.fromkeys(p.series for p in points),
        key=lambda s: (
            next(
                k
                for k, n in enumerate(learners)
                if any(p.series == s and p.learner == n for p in points)
            ),
            s,
        ),
    )


# --- swept dimensions --------------------------------------------------------------------------


@dataclass(frozen=True)
class Line:
    """One series of a sweep figure: x values and the mean with its 95 % interval."""

    x: list[float]
    mean: list[float]
    low: list[float]
    high: list[float]


def _line(points: Sequence[StudyPoint], dim: str, value: Any) -> Line | None:
    xs = sorted({p.settings[dim] for p in points if p.settings[dim] is not None})
    stats = [(x, mean_ci(value(p) for p in points if p.settings[dim] == x)) for x in xs]
    stats = [(x, s) for x, s in stats if s.n]
    if not stats:
        return None
    half = [0.0 if math.isnan(s.ci95) else s.ci95 for _, s in stats]
    return Line(
        [float(x) for x, _ in stats],
        [s.mean for _, s in stats],
        [s.mean - h for (_, s), h in zip(stats, half, strict=True)],
        [s.mean + h for (_, s), h in zip(stats, half, strict=True)],
    )


def _log10(value: int) -> float:
    return math.log10(value) if value > 0 else math.nan  # exact for Python ints beyond 1e308


def dimension_table(points: Sequence[StudyPoint], dim: str, system: str) -> str:
    """Markdown: series x values of ``dim``, cells ``score mean ± CI`` or ``refused: reason``."""
    mine = [p for p in points if p.system == system]
    xs = sorted({p.settings[dim] for p in mine if p.settings[dim] is not None})
    rows = []
    for series in order_series(mine):
        row = [series]
        for x in xs:
            cell = [p for p in mine if p.series == series and p.settings[dim] == x]
            refused = sorted({p.refused for p in cell if p.refused})
            finished = [p.score for p in cell if not p.refused]
            if finished:
                text = mean_ci(finished).format(3)
                if refused:
                    text += f" ({len(refused)} {refused[0]})"
            else:
                text = refused[0] if refused else "–"
            row.append(text)
        rows.append(row)
    label = DIMENSIONS[dim][0]
    return tables.markdown_table([f"learner \\ {label}", *[str(x) for x in xs]], rows)


def dimension_rows(points: Sequence[StudyPoint]) -> list[list[Any]]:
    """CSV rows, one per run: series, learner, system, settings, scores, costs, refusal."""
    rows = []
    for p in points:
        space = p.learning_space
        rows.append(
            [
                p.series,
                p.learner,
                p.system,
                *[p.settings[k] for k in DIMENSIONS],
                p.team_seed,
                p.seed,
                p.score,
                p.team_return,
                str(space["analytic"]) if "analytic" in space else "",
                space.get("visited", ""),
                space.get("parameters", ""),
                p.wall_s,
                p.peak_rss_mb,
                p.refused or "",
            ]
        )
    return rows


DIMENSION_HEADER = [
    "series",
    "learner",
    "system",
    *DIMENSIONS,
    "team_seed",
    "seed",
    "return_vs_greedy",
    "team_return",
    "space_analytic",
    "space_visited",
    "parameters",
    "wall_s",
    "peak_rss_mb",
    "refused",
]


def dimension_figures(
    points: Sequence[StudyPoint], dim: str, out: Path, colors: dict[str, Any]
) -> dict[str, Path]:
    """The figures of one swept dimension (see module docstring), by file stem."""
    label, stem, log_x = DIMENSIONS[dim]
    finished = [p for p in points if not p.refused]
    systems = list(dict.fromkeys(p.system for p in finished))
    series = order_series(finished)
    written: dict[str, Path] = {}

    def panel(rows: Sequence[StudyPoint], value: Any) -> dict[str, Line]:
        return {
            s: line
            for s in series
            if (line := _line([p for p in rows if p.series == s], dim, value)) is not None
        }

    returns = [
        figures.SweepPanel(
            f"{system_label(system)}: team return relative to greedy",
            panel([p for p in finished if p.system == system], lambda p: p.score),
            label,
            "(R - greedy) / |greedy| (mean, 95% CI)",
            log_x=log_x,
            reference=0.0,
        )
        for system in systems
    ]
    written[f"{stem}_return"] = figures.sweep_figure(returns, out / f"{stem}_return.png", colors)
    if dim != "system.n_robots":
        return written

    def space(key: str) -> Any:
        return lambda p: _log10(p.learning_space[key]) if key in p.learning_space else None

    space_lines = panel(finished, space("analytic"))
    space_lines.update(
        {f"{s} (visited)": line for s, line in panel(finished, space("visited")).items()}
    )
    space_lines.update(
        {f"{s} (parameters)": line for s, line in panel(finished, space("parameters")).items()}
    )
    written[f"{stem}_space"] = figures.sweep_figure(
        [
            figures.SweepPanel(
                "learning space: analytic dimension, entries visited, network parameters",
                space_lines,
                label,
                "log10 of the size",
                log_x=log_x,
            )
        ],
        out / f"{stem}_space.png",
        colors,
    )
    costs = (
        ("wall time per run", "wall_s", "seconds"),
        ("peak memory per run", "peak_rss_mb", "peak RSS (MiB)"),
    )
    written[f"{stem}_cost"] = figures.sweep_figure(
        [
            figures.SweepPanel(
                title,
                panel(finished, lambda p, key=key: getattr(p, key)),
                label,
                unit,
                log_x=log_x,
                log_y=True,
            )
            for title, key, unit in costs
        ],
        out / f"{stem}_cost.png",
        colors,
    )
    return written


def dimension_claims(runs: Sequence[RunRecord], dim: str) -> str:
    """Markdown: for each claim and system, the values of ``dim`` where it holds or not.

    Runs with a partition bound are left out: the claims are about the paper's subG-CQL.
    """
    by_value: dict[Any, list[RunRecord]] = {}
    for run in runs:
        value = config_value(run.config, dim)
        if value is not None and config_value(run.config, BOUND_KEY) is None:
            # one cell per learner at this value: its team seeds and run seeds together
            plain = dataclasses.replace(run, learner=base_learner(run), variant="")
            by_value.setdefault(value, []).append(plain)
    along = claims_along({v: summarize_runs(by_value[v]) for v in sorted(by_value)})
    rows = [
        [
            claim.claim,
            system_label(claim.system),
            ", ".join(str(v) for v in claim.holds_at) or "none",
            ", ".join(str(v) for v in claim.fails_at) or "none",
            ", ".join(str(v) for v in claim.not_evaluable_at) or "none",
        ]
        for claim in along
    ]
    label = DIMENSIONS[dim][0]
    header = ["claim", "system", f"holds at {label}", "does not hold at", "not evaluable at"]
    return tables.markdown_table(header, rows)


# --- statistics as the field reports them ------------------------------------------------------


def scores_by_task(points: Sequence[StudyPoint], series: str) -> dict[tuple[Any, ...], list[float]]:
    """Task -> scores of the series' finished runs on it."""
    out: dict[tuple[Any, ...], list[float]] = {}
    for p in points:
        if p.series == series and not p.refused and not math.isnan(p.score):
            out.setdefault(p.task, []).append(p.score)
    return out


def field_statistics(
    points: Sequence[StudyPoint],
) -> tuple[dict[str, Estimate], dict[tuple[str, str], Estimate]]:
    """IQM per series and probability of improvement per ordered pair of series.

    Returns:
        ``(series -> IQM estimate, (X, Y) -> P(X > Y) estimate over their common tasks)``.
    """
    finished = [p for p in points if not p.refused]
    names = order_series(finished)
    by_series = {s: scores_by_task(finished, s) for s in names}
    iqm = {s: iqm_ci(by_series[s].values()) for s in names}
    improvement = {}
    for x in names:
        for y in names:
            if x == y:
                continue
            common = [t for t in by_series[x] if t in by_series[y]]
            improvement[x, y] = probability_of_improvement(
                [by_series[x][t] for t in common], [by_series[y][t] for t in common]
            )
    return iqm, improvement


def field_statistics_markdown(
    iqm: dict[str, Estimate],
    improvement: dict[tuple[str, str], Estimate],
    points: Sequence[StudyPoint],
) -> str:
    """The IQM table and the probability-of-improvement matrix."""
    finished = [p for p in points if not p.refused]
    rows = [
        [s, len({p.task for p in finished if p.series == s}), est.n, est.format(3)]
        for s, est in iqm.items()
    ]
    md = [
        tables.markdown_table(
            ["learner", "tasks", "runs", "IQM of (R - greedy) / |greedy| [95% CI]"], rows
        ),
        "",
    ]
    names = list(iqm)
    if len(names) >= 2:
        matrix = [
            [x, *["–" if x == y else improvement[x, y].format(2) for y in names]] for x in names
        ]
        md += [
            "Probability of improvement P(row > column) [95% CI]: the chance that a run of the "
            "row learner scores higher than a run of the column learner on the same task "
            "(ties count one half), averaged over the tasks both ran.",
            "",
            tables.markdown_table(["P(row > column)", *names], matrix),
            "",
        ]
    return "\n".join(md)


def field_statistics_rows(
    iqm: dict[str, Estimate], improvement: dict[tuple[str, str], Estimate]
) -> list[list[Any]]:
    """CSV rows ``statistic, x, y, value, ci_low, ci_high, n_runs``."""
    rows: list[list[Any]] = [["iqm", s, "", e.value, e.low, e.high, e.n] for s, e in iqm.items()]
    rows += [
        ["probability_of_improvement", x, y, e.value, e.low, e.high, e.n]
        for (x, y), e in improvement.items()
    ]
    return rows


FIELD_STATS_HEADER = ["statistic", "x", "y", "value", "ci_low", "ci_high", "n_runs"]


def profile_figure(points: Sequence[StudyPoint], path: Path, colors: dict[str, Any]) -> Path | None:
    """Performance profiles of every series (None if no finished run has a score)."""
    finished = [p for p in points if not p.refused and not math.isnan(p.score)]
    if not finished:
        return None
    scores = np.array([p.score for p in finished])
    tau = np.linspace(scores.min() - 0.01, scores.max() + 0.01, PROFILE_POINTS)
    profiles = {
        s: performance_profile(scores_by_task(finished, s).values(), tau)
        for s in order_series(finished)
    }
    return figures.profile_figure(profiles, path, colors)


def series_colors(points: Sequence[StudyPoint]) -> dict[str, Any]:
    """A stable color per series (and its visited/parameters lines)."""
    names = order_series(points)
    base = figures.learner_colors(names)
    out = dict(base)
    for name, color in base.items():
        out[f"{name} (visited)"] = color
        out[f"{name} (parameters)"] = color
    return out


# --- the sections of report.md -----------------------------------------------------------------


@dataclass
class StudyOutput:
    """What :func:`study_sections` wrote: markdown, CSV and PNG files by stem."""

    markdown: str
    csvs: dict[str, Path]
    figures: dict[str, Path]


def _image(path: Path | None, alt: str) -> str:
    return f"![{alt}]({path.name})" if path else f"_No figure: {alt.lower()} (nothing to draw)._"


def study_sections(runs: Sequence[RunRecord], inputs: Sequence[Path], out: Path) -> StudyOutput:
    """The field-statistics section and one section per swept dimension, with files.

    Args:
        runs: Finished runs of the report.
        inputs: The report's inputs (searched for refused runs).
        out: Output folder.

    Returns:
        Markdown (to append to report.md) and the files written.
    """
    points = study_points(runs, inputs)
    colors = series_colors(points)
    result = StudyOutput("", {}, {})
    iqm, improvement = field_statistics(points)
    result.csvs["field_stats"] = tables.write_csv(
        out / "field_stats.csv", FIELD_STATS_HEADER, field_statistics_rows(iqm, improvement)
    )
    profile = profile_figure(points, out / "performance_profile.png", colors)
    if profile is not None:
        result.figures["performance_profile"] = profile
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
        field_statistics_markdown(iqm, improvement, points),
        _image(profile, "Performance profiles"),
        "",
    ]
    dims = swept_dimensions(points)
    if dims:
        result.csvs["study"] = tables.write_csv(
            out / "study.csv", DIMENSION_HEADER, dimension_rows(points)
        )
    for dim in dims:
        label, stem, _ = DIMENSIONS[dim]
        written = dimension_figures(points, dim, out, colors)
        result.figures.update(written)
        md += [
            f"## Against the {label} (`{dim}`)",
            "",
            "Team return relative to greedy (mean ± 95 % t interval over team seeds and run "
            "seeds); `refused: ...` = refused up front, with the reason. Every run: `study.csv`.",
            "",
        ]
        for system in dict.fromkeys(p.system for p in points):
            md += [f"{system_label(system)}:", "", dimension_table(points, dim, system), ""]
        md += [_image(written.get(f"{stem}_return"), f"Team return against the {label}"), ""]
        if f"{stem}_space" in written:
            md += [
                "Learning space (log scale; solid: analytic dimension, dashed: entries visited, "
                "dotted: network parameters), wall time and peak memory (RSS) per run:",
                "",
                _image(written[f"{stem}_space"], "Learning space against the team size"),
                "",
                _image(written[f"{stem}_cost"], "Wall time and memory against the team size"),
                "",
            ]
        md += [
            f"Claims of the paper at each value of `{dim}` (runs without a partition bound):",
            "",
            dimension_claims(runs, dim),
            "",
        ]
    result.markdown = "\n".join(md)
    return result

"""Build the experiment report: collect runs, aggregate over seeds, write report.md, CSVs, PNGs.

``build_report([sweep_dir])`` is the single entry point of ``scripts/report.py``. Output files
(flat, in ``out_dir``):

* ``report.md``: the tables (paper Tables 5-9 analogues, team return vs greedy), the figures
  (linked), the check of the paper's Section 6 claims and the list of missing jobs;
* ``runs.csv`` (one row per run), ``ctr.csv``, ``itr.csv``, ``team_return.csv``,
  ``learning_space.csv``, ``claims.csv``, ``missing.csv``, ``field_stats.csv`` (IQM and
  probability of improvement), ``study.csv`` (runs of a swept dimension);
* ``ctr_<system>_L.png``, ``ctr_<system>_H.png`` (paper Figures 1-4), ``itr_<system>.png``
  (Figures 5-6), ``curve_<system>.png`` (learning curves, for learners that train) and
  ``team_return.png``, ``performance_profile.png`` and, for a swept team size or task-switch
  cost, ``team_size_*.png`` / ``switch_ticks_return.png`` (see ``reports/studies.py``).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from mrta_rl.reports import figures, studies, tables, yardsticks
from mrta_rl.reports.aggregate import (
    CellSummary,
    learner_label,
    order_learners,
    summarize_curve,
    summarize_runs,
    system_label,
)
from mrta_rl.reports.claims import FAILS, HOLDS, NOT_EVALUABLE, check_claims
from mrta_rl.reports.collect import (
    Collection,
    ReportInputError,
    RunRecord,
    collect_runs,
    named_streams,
)

logger = logging.getLogger(__name__)

REPORT_FILE = "report.md"
# run config keys shown in the report's setup section (dotted paths of conf/config.yaml)
SETUP_KEYS = ("env.horizon", "train.episodes", "train.batch_size", "eval.episodes", "eval.split")


@dataclass
class ReportFiles:
    """What :func:`build_report` wrote.

    Attributes:
        out_dir: The output folder.
        report: Path of report.md.
        csvs: CSV files by stem.
        figures: PNG files by stem.
        collection: The runs and missing jobs the report was made from.
    """

    out_dir: Path
    report: Path
    csvs: dict[str, Path] = field(default_factory=dict)
    figures: dict[str, Path] = field(default_factory=dict)
    collection: Collection | None = None


def default_out_dir(inputs: Sequence[Path | str]) -> Path:
    """``<input>/report`` for one input, else ``<common parent of the inputs>/report``."""
    paths = [Path(p).resolve() for p in inputs]
    if len(paths) == 1:
        return paths[0] / "report"
    return Path(os.path.commonpath([str(p) for p in paths])) / "report"


def _config_value(config: dict[str, Any], dotted: str) -> Any:
    return OmegaConf.select(OmegaConf.create(config), dotted, default=None) if config else None


def _setup_markdown(runs: Sequence[RunRecord]) -> str:
    """Run settings (distinct values over runs) and each learner's hyperparameters."""
    rows = []
    for key in SETUP_KEYS:
        values = sorted({str(_config_value(named_streams(r.config), key)) for r in runs})
        note = "" if len(values) == 1 else " (differs between runs!)"
        shown = ", ".join("spec default" if v == "None" else v for v in values)
        rows.append([f"`{key}`", shown + note])
    lines = [tables.markdown_table(["setting", "value"], rows), ""]
    learner_rows = []
    for name in order_learners([r.learner for r in runs]):
        settings = set()
        for r in runs:
            if r.learner == name:
                cfg = r.config.get("learner") or {}
                settings.add(", ".join(f"{k}={v}" for k, v in cfg.items() if not k.startswith("_")))
        learner_rows.append([learner_label(name), " / ".join(sorted(settings)) or "–"])
    lines.append(tables.markdown_table(["learner", "hyperparameters (conf/learner)"], learner_rows))
    return "\n".join(lines)


def _training_time_markdown(summaries: Sequence[CellSummary]) -> str:
    rows = [
        [
            system_label(c.system),
            learner_label(c.learner),
            len(c.seeds),
            c.train_env_ticks.format(0),
            c.train_wall_s.format(1),
        ]
        for c in summaries
    ]
    return tables.markdown_table(
        [
            "system",
            "learner",
            "seeds",
            "training env ticks per run",
            "training wall time per run (s)",
        ],
        rows,
    )


def build_report(inputs: Iterable[Path | str], out_dir: Path | str | None = None) -> ReportFiles:
    """Collect the runs under ``inputs`` and write the report, CSVs and figures to ``out_dir``.

    Args:
        inputs: A multirun dir, run dirs, or folders holding run dirs.
        out_dir: Output folder; default :func:`default_out_dir`.

    Returns:
        The files written.

    Raises:
        ReportInputError: if an input does not exist or no finished run is found.
        RunDirError: if a run's metrics.json is damaged.
    """
    inputs = [Path(p) for p in inputs]
    collection = collect_runs(inputs)
    if not collection.runs:
        missing = f"; {len(collection.missing)} expected jobs missing" if collection.missing else ""
        raise ReportInputError(
            f"no finished run (metrics.json) under {[str(p) for p in inputs]}{missing}"
        )
    # the yardstick runs are checked (re-evaluations, same task streams) before anything is written
    yardsticks.collect_policies([*collection.runs, *collection.duplicates])
    out = Path(out_dir) if out_dir is not None else default_out_dir(inputs)
    out.mkdir(parents=True, exist_ok=True)
    files = ReportFiles(out_dir=out, report=out / REPORT_FILE, collection=collection)

    summaries = summarize_runs(collection.runs)
    cells = list(summaries.values())
    systems = list(dict.fromkeys(system for system, _ in summaries))
    by_system = {s: [c for c in cells if c.system == s] for s in systems}
    colors = figures.learner_colors(order_learners([c.learner for c in cells]))
    claims = check_claims(summaries)

    header, rows = tables.run_rows(collection.runs)
    csv_specs = {
        "runs": (header, rows),
        "ctr": (
            ["system", "learner", "task_type", "priority", *tables.STAT_HEADER],
            tables.ctr_rows(cells),
        ),
        "itr": (["system", "learner", "robot", *tables.STAT_HEADER], tables.itr_rows(cells)),
        "team_return": (tables.TEAM_RETURN_HEADER, tables.team_return_rows(cells)),
        "group_return": (tables.GROUP_RETURN_HEADER, tables.group_return_rows(cells)),
        "learning_space": (tables.LEARNING_SPACE_HEADER, tables.learning_space_rows(cells)),
        "claims": (
            ["claim", "system", "verdict", "separation", "statement", "evidence"],
            tables.claims_rows(claims),
        ),
        "missing": (
            ["learner", "system", "seed", "reason", "job_dir", "overrides"],
            tables.missing_rows(collection.missing),
        ),
    }
    for stem, (head, body) in csv_specs.items():
        files.csvs[stem] = tables.write_csv(out / f"{stem}.csv", head, body)

    for system, system_cells in by_system.items():
        for p in ("L", "H"):
            stem = f"ctr_{system}_{p}"
            files.figures[stem] = figures.ctr_figure(system_cells, p, _png(out, stem), colors)
        files.figures[f"itr_{system}"] = figures.itr_figure(
            system_cells, _png(out, f"itr_{system}"), colors
        )
        curves = {
            c.learner: curve
            for c in system_cells
            if (
                curve := summarize_curve(
                    [r for r in collection.runs if r.system == system and r.learner == c.learner]
                )
            )
        }
        if curves:
            greedy = next((c.greedy_return for c in system_cells if c.greedy_return.n), None)
            files.figures[f"curve_{system}"] = figures.curve_figure(
                curves, greedy, system, _png(out, f"curve_{system}"), colors
            )
    files.figures["team_return"] = figures.team_return_figure(
        by_system, out / "team_return.png", colors
    )

    # "Learning against the rules": every run counts, the settings of a rule grid included
    rules_md, rules_files = yardsticks.write_section(
        [*collection.runs, *collection.duplicates], out
    )
    for stem, path in rules_files.items():
        (files.figures if path.suffix == ".png" else files.csvs)[stem] = path
    study = studies.study_sections(collection.runs, inputs, out)
    files.csvs.update(study.csvs)
    files.figures.update(study.figures)
    markdown = _report_markdown(collection, cells, by_system, claims, files, rules_md)
    files.report.write_text(markdown + "\n" + study.markdown + "\n")
    logger.info(
        "wrote %s (%d runs, %d missing)",
        files.report,
        len(collection.runs),
        len(collection.missing),
    )
    return files


def _png(out: Path, stem: str) -> Path:
    """The figure file of a stem; a system in a config subfolder (``sub/nested``) stays in out."""
    return out / f"{stem.replace('/', '_')}.png"


def _image(files: ReportFiles, stem: str, alt: str) -> str:
    path = files.figures.get(stem)
    return f"![{alt}]({path.name})" if path else f"_No figure: {alt.lower()} (nothing to draw)._"


def _report_markdown(
    collection: Collection,
    cells: list[CellSummary],
    by_system: dict[str, list[CellSummary]],
    claims: list,
    files: ReportFiles,
    rules_md: str = "",
) -> str:
    runs, missing = collection.runs, collection.missing
    verdicts = [c.verdict for c in claims]
    md = [
        "# Experiment report",
        "",
        "Inputs: " + ", ".join(f"`{p}`" for p in collection.inputs),
        "",
        f"**{len(runs)} finished runs** of {collection.expected_jobs} expected "
        f"(expected grid from {collection.sweep_source}); **{len(missing)} missing**"
        + (
            f"; {len(collection.duplicates)} duplicate runs ignored"
            if collection.duplicates
            else ""
        )
        + ". Every number is the mean over training seeds ± the half-width of its 95 % t "
        "confidence interval (no interval with one seed); CTR and ITR are in percent, evaluated "
        "with exploration off on the same evaluation task streams for every learner and seed. "
        "Exact values: the CSV files next to this report (`runs.csv` holds every run).",
        "",
    ]
    if collection.duplicates:
        kept = {r.key: r.run_dir for r in runs}
        md += [
            "## Duplicate runs left out",
            "",
            "Each of these runs has the configuration and seed of a run the report keeps (a seed "
            "counts once); only identical settings make a duplicate.",
            "",
            "| configuration | system | seed | left out | kept |",
            "| :--- | :--- | ---: | :--- | :--- |",
            *(
                f"| {r.learner} | {r.system} | {r.seed} | `{r.run_dir}` | `{kept.get(r.key)}` |"
                for r in collection.duplicates
            ),
            "",
        ]
    if missing:
        md += [
            "## Missing jobs",
            "",
            "These jobs of the expected grid left no `metrics.json`; their cells below average "
            "fewer seeds (or are absent).",
            "",
            tables.missing_markdown(missing),
            "",
        ]
    md += [
        "## Setup",
        "",
        _setup_markdown(runs),
        "",
        "## Team return against the greedy auction",
        "",
        "Evaluation team return per episode; `greedy` is the plain auction on the full task "
        "sets, evaluated on the same task streams (paired per seed for the difference).",
        "",
        tables.team_return_markdown(cells),
        "",
        _image(files, "team_return", "Team return"),
        "",
    ]
    group_tables = {
        system: table
        for system, system_cells in by_system.items()
        if (table := tables.group_return_markdown(system_cells))
    }
    if group_tables:
        md += [
            "### Team return by subG sub-group",
            "",
            "Every reward is a task's and each task type belongs to one sub-group, so the team "
            "return splits exactly into the parts its sub-groups' task types earn; the last row "
            "is what the same types earn under the plain auction on the full team.",
            "",
        ]
        for system, table in group_tables.items():
            md += [f"{system_label(system)}:", "", table, ""]
    if rules_md:
        md += [rules_md, ""]
    md += [
        "## Completed task ratio (paper Tables 5-6, Figures 1-4)",
        "",
        "CTR (%) = assigned / (assigned + dropped) per task type and priority; `all` pools the "
        "counts over types.",
        "",
    ]
    for system, system_cells in by_system.items():
        label = system_label(system)
        for p, word in (("L", "low"), ("H", "high")):
            md += [
                f"### {label}: {word}-priority tasks",
                "",
                tables.ctr_markdown(system_cells, p),
                "",
                _image(files, f"ctr_{system}_{p}", f"{label} CTR {word}-priority"),
                "",
            ]
    md += [
        "## Idle time ratio (paper Tables 7-8, Figures 5-6)",
        "",
        "ITR (%) = (horizon - busy ticks) / horizon per robot (paper eq. 9); lower is better.",
        "",
    ]
    for system, system_cells in by_system.items():
        label = system_label(system)
        md += [
            f"### {label}",
            "",
            tables.itr_markdown(system_cells),
            "",
            _image(files, f"itr_{system}", f"{label} ITR"),
            "",
        ]
    md += [
        "## Learning space (paper Table 9)",
        "",
        "`analytic`: learning space dimension of the learner's encoding (paper eqs. 10-16, exact "
        "integer in `learning_space.csv`); `visited`: table entries updated at least once "
        "(mean ± CI over seeds); `parameters`: weights of a network learner.",
        "",
        tables.learning_space_markdown(cells),
        "",
    ]
    md += [
        "## Learning curves",
        "",
        "Training team return per episode (with exploration) against training env ticks "
        "(ticks x parallel copies); line = mean over seeds, band = 95 % CI. The dashed line is "
        "the greedy auction's evaluation return.",
        "",
    ]
    for system in by_system:
        md += [_image(files, f"curve_{system}", f"{system_label(system)} learning curves"), ""]
    md += [
        "## Claims of the paper (Section 6)",
        "",
        f"{verdicts.count(HOLDS)} hold, {verdicts.count(FAILS)} do not hold, "
        f"{verdicts.count(NOT_EVALUABLE)} not evaluable (a learner they compare is missing). "
        "Verdicts compare means over seeds; `clear` = the compared 95 % intervals are "
        "disjoint, `CIs overlap` = the ordering may be noise.",
        "",
        tables.claims_markdown(claims),
        "",
    ]
    total_wall = sum((r.metrics.get("train") or {}).get("wall_s", 0.0) for r in runs)
    md += [
        "## Training time",
        "",
        _training_time_markdown(cells),
        "",
        f"Sum of the training wall times of all runs: {total_wall:.1f} s "
        "(evaluation not included).",
        "",
    ]
    return "\n".join(md)

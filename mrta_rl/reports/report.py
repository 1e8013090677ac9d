"""Build the experiment report: collect runs, aggregate over seeds, write report.md, CSVs, PNGs."""

from __future__ import annotations

import logging
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd

from mrta_rl.reports import collect, experiments, figures, frame, marl_eval, tables
from mrta_rl.reports.claims import FAILS, HOLDS, NOT_EVALUABLE, check_claims, claims_table
from mrta_rl.reports.collect import Collection, RunRecord
from mrta_rl.reports.frame import long_table, summarize, system_label
from mrta_rl.reports.study import Prose, study_of
from mrta_rl.reports.tables import markdown_table

logger = logging.getLogger(__name__)

REPORT_FILE = "report.md"
# run config keys shown in the report's setup section (dotted paths of conf/config.yaml)
LEARNER_SETTINGS = "hyperparameters (conf/learner)"
SETUP_KEYS = ("env.horizon", "train.episodes", "train.batch_size", "eval.episodes", "eval.split")


@dataclass
class ReportFiles:
    """What :func:`build_report` wrote."""

    out_dir: Path
    report: Path
    csvs: dict[str, Path] = field(default_factory=dict)
    figures: dict[str, Path] = field(default_factory=dict)
    collection: Collection | None = None
    marl_eval: Path | None = None


def default_out_dir(inputs: Sequence[Path | str]) -> Path:
    """``<input>/report`` for one input, else ``<common parent of the inputs>/report``."""
    paths = [Path(p).resolve() for p in inputs]
    return (paths[0] if len(paths) == 1 else Path(os.path.commonpath(paths))) / "report"


def _setup_markdown(runs: Sequence[RunRecord], summary: pd.DataFrame) -> str:
    """Run settings (distinct values over runs) and each learner's hyperparameters."""
    rows = []
    for key in SETUP_KEYS:
        values = sorted(
            {str(collect.config_value(collect.named_streams(r.config), key)) for r in runs}
        )
        note = "" if len(values) == 1 else " (differs between runs!)"
        values = ", ".join(v.replace("None", "spec default") for v in values)
        rows.append([f"`{key}`", values + note])
    settings: dict[str, set[str]] = {}
    for r in runs:
        cfg = r.config.get("learner") or {}
        text = ", ".join(f"{k}={v}" for k, v in cfg.items() if not k.startswith("_"))
        settings.setdefault(r.learner, set()).add(text)
    labels = dict(zip(summary["learner"], summary["label"], strict=True))
    learners = [[label, " / ".join(sorted(settings[n])) or "–"] for n, label in labels.items()]
    learners_table = markdown_table(["learner", LEARNER_SETTINGS], learners)
    return markdown_table(["setting", "value"], rows) + "\n\n" + learners_table


def build_report(inputs: Iterable[Path | str], out_dir: Path | str | None = None) -> ReportFiles:
    """Collect the runs under ``inputs`` and write the report, CSVs and figures to ``out_dir``.

    What the report makes of the runs (row order, claims, yardsticks, swept settings) is their
    study (:func:`~mrta_rl.reports.study.study_of`), its prose ``conf/report/report.md``.
    """
    inputs = [Path(p) for p in inputs]
    collection = collect.collect_runs(inputs)
    if not collection.runs:
        missing = f"; {len(collection.missing)} expected jobs missing" if collection.missing else ""
        if collection.unreadable:
            first = collection.unreadable[0].reason
            more = len(collection.unreadable) - 1
            missing += f"; left out: {first}" + (f" and {more} more" if more else "")
        raise collect.ReportInputError(
            f"no finished run (metrics.json) under {[str(p) for p in inputs]}{missing}"
        )
    study, prose = study_of(collection.runs), Prose.shipped()
    # the yardstick runs are checked (re-evaluations, same task streams) before anything is written
    experiments.collect_policies(collection.runs + collection.duplicates, study)
    out = Path(out_dir) if out_dir is not None else default_out_dir(inputs)
    out.mkdir(parents=True, exist_ok=True)
    files = ReportFiles(out_dir=out, report=out / REPORT_FILE, collection=collection)

    long = long_table(collection.runs)
    summary = summarize(long, study.learners)
    claims = check_claims(summary, study)
    csvs = tables.csv_tables(long, summary)
    csvs["claims"] = claims_table(claims)
    csvs["missing"] = pd.DataFrame(
        [
            [m.learner, m.system, m.seed, m.reason, str(m.job_dir or ""), " ".join(m.overrides)]
            for m in collection.missing
        ],
        columns=["learner", "system", "seed", "reason", "job_dir", "overrides"],
    )
    for stem, table in csvs.items():
        files.csvs[stem] = tables.write_csv(out / f"{stem}.csv", table)

    colors = figures.learner_colors(list(dict.fromkeys(summary["learner"])))
    for system, rows in summary.groupby("system", sort=False):
        bars = {f"ctr_{system}_{p}": ("ctr", rows[rows["priority"] == p]) for p in "LH"}
        for stem, (metric, part) in (bars | {f"itr_{system}": ("itr", rows)}).items():
            files.figures[stem] = figures.grouped_bars(part, metric, _png(out, stem), colors)
        lines, line_colors = {}, {}
        for learner, label in dict(zip(rows["learner"], rows["label"], strict=True)).items():
            mine = [r for r in collection.runs if r.system == system and r.learner == learner]
            if (curve := frame.summarize_curve(mine)) is not None:
                line, seeds = curve
                name = f"{label} ({seeds} seed{'s' if seeds != 1 else ''})"
                if seeds != len(mine):  # the tables count every run; say why this is fewer
                    name = f"{label} ({seeds} of {len(mine)} seeds have a curve)"
                line_colors[name], lines[name] = colors[learner], line
        if lines:
            greedy = [s for s in rows[rows["metric"] == "greedy_team_return"]["stat"] if s.n]
            title = f"{system_label(system)}: learning curves (mean and 95% CI band over seeds)"
            xlabel = "training env ticks (ticks x parallel copies)"
            hline = (greedy[0].mean, "greedy (evaluation)") if greedy else None
            panel = figures.Panel(title, lines, xlabel, "team return per episode", hline=hline)
            png, stem = _png(out, f"curve_{system}"), f"curve_{system}"
            files.figures[stem] = figures.line_figure([panel], png, line_colors, (7.5, 4.6))
    png = out / "team_return.png"
    files.figures["team_return"] = figures.team_return_figure(summary, png, colors)

    # "Learning against the rules": every run counts, the settings of a rule grid included
    every_run = [*collection.runs, *collection.duplicates]
    rules_md, rules_files = experiments.write_section(every_run, out, study, prose)
    study_md, study_files = experiments.study_sections(collection.runs, inputs, out, study, prose)
    for stem, path in {**rules_files, **study_files}.items():
        (files.figures if path.suffix == ".png" else files.csvs)[stem] = path
    files.marl_eval = marl_eval.write_marl_eval(collection.runs, out)
    markdown = _report_markdown(collection, long, csvs, summary, claims, files, prose, rules_md)
    files.report.write_text(markdown + "\n" + study_md + "\n")
    counts = len(collection.runs), len(collection.missing), len(collection.unreadable)
    logger.info("wrote %s (%d runs, %d missing, %d left out)", files.report, *counts)
    return files


def _png(out: Path, stem: str) -> Path:
    """The figure file of a stem; a system in a config subfolder (``sub/nested``) stays in out."""
    return out / f"{stem.replace('/', '_')}.png"


def _report_markdown(
    collection: Collection,
    long: pd.DataFrame,
    csvs: dict[str, pd.DataFrame],
    summary: pd.DataFrame,
    claims: list,
    files: ReportFiles,
    prose: Prose,
    rules_md: str = "",
) -> str:
    runs, missing, duplicates = collection.runs, collection.missing, collection.duplicates
    unreadable, fig = collection.unreadable, files.figures.get
    systems = {s: rows for s, rows in summary.groupby("system", sort=False)}
    if collection.sweep_source:
        jobs, source = collection.expected_jobs, collection.sweep_source
        expected = prose.text("expected", jobs=jobs, source=source, missing=len(missing))
    else:  # run dirs expect no other runs
        expected = prose.text("no_grid")
    md = prose.section(
        "head",
        inputs=", ".join(f"`{p}`" for p in collection.inputs),
        runs=len(runs),
        expected=expected,
        left_out=prose.text("left_out_count", count=len(unreadable)) if unreadable else "",
        duplicates=prose.text("duplicates_count", count=len(duplicates)) if duplicates else "",
    )
    if unreadable:
        rows = [[f"`{u.run_dir}`", u.reason] for u in unreadable]
        md += prose.section("left_out", table=markdown_table(["run dir", "reason"], rows))
    if duplicates:
        kept = {r.key: r.run_dir for r in runs}
        rows = [
            [r.learner, r.system, r.seed, f"`{r.run_dir}`", f"`{kept.get(r.key)}`"]
            for r in duplicates
        ]
        header = ["configuration", "system", "seed", "left out", "kept"]
        md += prose.section("duplicates", table=markdown_table(header, rows))
    if missing:
        rows = [
            [m.learner, system_label(m.system), "?" if m.seed is None else m.seed, m.reason]
            + [f"`{v}`" if v else "–" for v in (m.job_dir, " ".join(m.overrides))]
            for m in missing
        ]
        header = ["learner", "system", "seed", "reason", "job dir", "overrides"]
        md += prose.section("missing", table=markdown_table(header, rows))
    md += prose.section("setup", table=_setup_markdown(runs, summary))
    table = tables.team_return_markdown(summary, csvs["team_return"])
    figure = prose.image(fig("team_return"), "Team return")
    md += prose.section("team_return", table=table, figure=figure)
    groups = {s: t for s, rows in systems.items() if (t := tables.group_return_markdown(rows))}
    if groups:
        blocks = "\n\n".join(f"{system_label(s)}:\n\n{t}" for s, t in groups.items())
        md += prose.section("group_return", tables=blocks)
    if rules_md:
        md += [rules_md, ""]
    md += prose.section("ctr")
    for system, rows in systems.items():
        label = system_label(system)
        for p, word in frame.PRIORITY_LABELS.items():
            figure = prose.image(fig(f"ctr_{system}_{p}"), f"{label} CTR {word}")
            table = tables.ctr_markdown(rows, p)
            md += prose.section(
                "ctr_system", system=label, priority=word, table=table, figure=figure
            )
    md += prose.section("itr")
    for system, rows in systems.items():
        label = system_label(system)
        figure = prose.image(fig(f"itr_{system}"), f"{label} ITR")
        md += prose.section(
            "itr_system", system=label, table=tables.itr_markdown(rows), figure=figure
        )
    md += prose.section("learning_space", table=tables.learning_space_markdown(long, summary))
    curves = (prose.image(fig(f"curve_{s}"), f"{system_label(s)} learning curves") for s in systems)
    md += prose.section("curves", figures="\n\n".join(curves))
    verdicts = [c.verdict for c in claims]
    claim_rows = [
        [r.statement, system_label(r.system) if r.system != "all" else "both", f"**{r.verdict}**"]
        + [r.separation or "", r.evidence]
        for r in claims
    ]
    header = ["claim (paper)", "system", "verdict", "95% CIs", "numbers"]
    counts = {k: verdicts.count(v) for k, v in (("holds", HOLDS), ("fails", FAILS))}
    md += prose.section(
        "claims",
        **counts,
        unknown=verdicts.count(NOT_EVALUABLE),
        table=markdown_table(header, claim_rows),
    )
    total_wall = sum((r.metrics.get("train") or {}).get("wall_s", 0.0) for r in runs)
    md += prose.section(
        "training_time", table=tables.training_time_markdown(summary), seconds=f"{total_wall:.1f}"
    )
    return "\n".join(md)

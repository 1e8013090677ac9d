"""Experiment reports: collect the runs of a sweep into one long table, summarise, tabulate, plot.

``build_report(inputs, out_dir)`` turns a Hydra multirun dir (or run dirs) into ``report.md``,
CSV files, PNG figures and the marl-eval JSON: the analogues of paper Tables 5-9 and Figures 1-6,
learning curves, team return against the greedy auction, and a check of the claims of paper
Section 6. The package reads run dirs only: it imports no runner, learner or torch.
"""

from __future__ import annotations

from mrta_rl.reports.collect import Collection, MissingJob, RunRecord, collect_runs
from mrta_rl.reports.frame import long_table, summarize
from mrta_rl.reports.report import ReportFiles, build_report, default_out_dir
from mrta_rl.reports.stats import MeanCI, mean_ci, t_quantile

__all__ = [
    "Collection",
    "MeanCI",
    "MissingJob",
    "ReportFiles",
    "RunRecord",
    "build_report",
    "collect_runs",
    "default_out_dir",
    "long_table",
    "mean_ci",
    "summarize",
    "t_quantile",
]

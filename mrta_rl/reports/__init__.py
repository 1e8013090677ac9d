"""Experiment reports: a sweep's run dirs in, report.md, CSVs, PNGs and marl-eval JSON out.

The package reads run dirs only: it imports no runner, learner or torch.
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

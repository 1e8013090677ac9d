"""Experiment reports (issue 5): collect runs of a sweep, aggregate over seeds, tables, figures.

``build_report(inputs, out_dir)`` turns a Hydra multirun dir (or run dirs) into ``report.md``,
CSV files and PNG figures: the analogues of paper Tables 5-9 and Figures 1-6, learning curves,
team return against the greedy auction, and a check of the claims of paper Section 6.
"""

from __future__ import annotations

from mrta_rl.reports.aggregate import CellSummary, summarize_curve, summarize_runs
from mrta_rl.reports.claims import ClaimResult, check_claims
from mrta_rl.reports.collect import Collection, MissingJob, RunRecord, collect_runs
from mrta_rl.reports.report import ReportFiles, build_report, default_out_dir
from mrta_rl.reports.stats import MeanCI, mean_ci, t_quantile

__all__ = [
    "CellSummary",
    "ClaimResult",
    "Collection",
    "MeanCI",
    "MissingJob",
    "ReportFiles",
    "RunRecord",
    "build_report",
    "check_claims",
    "collect_runs",
    "default_out_dir",
    "mean_ci",
    "summarize_curve",
    "summarize_runs",
    "t_quantile",
]

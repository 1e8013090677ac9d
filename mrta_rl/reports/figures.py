"""Figures of the report: analogues of paper Figures 1-6 and the learning curves (matplotlib).

* CTR per task type for low- and high-priority tasks per system (paper Figures 1-4): grouped
  bars, one group per task type plus the overall CTR, one bar per learner, 95 % CI error bars.
* ITR per robot per system (paper Figures 5-6): the same layout over robots.
* Learning curves: training team return per episode against training env ticks, the mean over
  seeds with its 95 % band, and the greedy baseline's evaluation return as a reference line.
* Team return of every learner per system next to the greedy baseline.
* Studies (issue 11): a value per learner against a swept parameter (team size, task-switch
  cost), and performance profiles of the greedy-normalized return (issue 12).

Figures are built on :class:`matplotlib.figure.Figure` directly (no pyplot state, no GUI
backend), so the report can be made in a headless process or a parallel job.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure
from matplotlib.ticker import NullFormatter

from mrta_rl.reports.aggregate import (
    PRIORITY_LABELS,
    CellSummary,
    CurveSummary,
    learner_label,
    system_label,
)
from mrta_rl.reports.stats import MeanCI

DPI = 120
BAR_GROUP_WIDTH = 0.8  # share of a group's slot taken by its bars


def learner_colors(learners: Sequence[str]) -> dict[str, tuple[float, float, float, float]]:
    """A stable color per learner (tab10 in report order)."""
    from matplotlib import colormaps

    cmap = colormaps["tab10"]
    return {name: cmap(i % 10) for i, name in enumerate(learners)}


def _err(values: Sequence[MeanCI]) -> tuple[np.ndarray, np.ndarray]:
    means = np.array([v.mean for v in values], dtype=float)
    errs = np.array([0.0 if math.isnan(v.ci95) else v.ci95 for v in values], dtype=float)
    return means, errs


def _seed_note(cells: Sequence[CellSummary]) -> str:
    counts = sorted({len(c.seeds) for c in cells})
    seeds = "/".join(str(c) for c in counts)
    return f"mean ± 95% CI over {seeds} seed{'s' if counts != [1] else ''}"


def grouped_bars(
    cells: Sequence[CellSummary],
    groups: Sequence[str],
    value: str,
    title: str,
    xlabel: str,
    ylabel: str,
    path: Path,
    colors: dict[str, tuple[float, float, float, float]],
) -> Path:
    """Grouped bar chart with CI error bars, one bar per learner in each group.

    Args:
        cells: Summaries of one system, one per learner (bar order).
        groups: Group labels on the x axis (task types or robots, plus an aggregate).
        value: ``"ctr_L"``, ``"ctr_H"`` or ``"itr"``: which :class:`CellSummary` values to draw.
        title: Figure title.
        xlabel: X axis label.
        ylabel: Y axis label (with unit).
        path: PNG to write.
        colors: Learner -> color.

    Returns:
        ``path``.
    """
    fig = Figure(figsize=(min(14.0, max(7.0, 1.0 + 0.3 * len(groups) * len(cells))), 5.0), dpi=DPI)
    ax = fig.add_subplot()
    x = np.arange(len(groups))
    width = BAR_GROUP_WIDTH / max(len(cells), 1)
    for k, cell in enumerate(cells):
        if value == "itr":
            stats = [cell.itr[g] for g in groups]
        else:
            priority = value.split("_")[1]
            stats = [cell.ctr[(g, priority)] for g in groups]
        means, errs = _err(stats)
        # a percentage lies in [0, 100]: clip the interval drawn there (the CSV keeps it whole)
        yerr = np.stack(
            [np.minimum(errs, np.nan_to_num(means)), np.minimum(errs, 100.0 - np.nan_to_num(means))]
        )
        offset = (k - (len(cells) - 1) / 2) * width
        ax.bar(
            x + offset,
            np.nan_to_num(means),
            width,
            yerr=np.maximum(yerr, 0.0),
            capsize=2,
            color=colors[cell.learner],
            label=learner_label(cell.learner),
            error_kw={"elinewidth": 0.8},
        )
    ax.set_xticks(x, [g if g not in ("all", "mean") else f"{g}*" for g in groups])
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_ylim(0, 105)
    ax.set_title(title, fontsize=11)
    ax.grid(axis="y", alpha=0.3)
    ax.set_axisbelow(True)
    ax.legend(
        title="learner",
        fontsize=8,
        title_fontsize=8,
        ncol=min(len(cells), 4),
        loc="upper center",
        bbox_to_anchor=(0.5, -0.16),
        frameon=False,
    )
    fig.tight_layout()
    fig.savefig(path)
    return path


def ctr_figure(
    cells: Sequence[CellSummary],
    priority: str,
    path: Path,
    colors: dict[str, tuple[float, float, float, float]],
) -> Path:
    """Paper Figures 1-4: CTR of one priority per task type, one system.

    Args:
        cells: Summaries of one system.
        priority: ``"L"`` or ``"H"``.
        path: PNG to write.
        colors: Learner -> color.

    Returns:
        ``path``.
    """
    system = system_label(cells[0].system)
    groups = [*cells[0].task_types, "all"]
    return grouped_bars(
        cells,
        groups,
        f"ctr_{priority}",
        f"{system}: CTR of {PRIORITY_LABELS[priority]} tasks ({_seed_note(cells)})",
        "task type (* all = counts pooled over types)",
        "completed task ratio CTR (%)",
        path,
        colors,
    )


def itr_figure(
    cells: Sequence[CellSummary], path: Path, colors: dict[str, tuple[float, float, float, float]]
) -> Path:
    """Paper Figures 5-6: ITR per robot, one system.

    Args:
        cells: Summaries of one system.
        path: PNG to write.
        colors: Learner -> color.

    Returns:
        ``path``.
    """
    system = system_label(cells[0].system)
    return grouped_bars(
        cells,
        [*cells[0].robots, "mean"],
        "itr",
        f"{system}: idle time ratio per robot ({_seed_note(cells)})",
        "robot (* mean = mean over robots)",
        "idle time ratio ITR (% of ticks)",
        path,
        colors,
    )


def curve_figure(
    curves: dict[str, CurveSummary],
    greedy: MeanCI | None,
    system: str,
    path: Path,
    colors: dict[str, tuple[float, float, float, float]],
) -> Path:
    """Learning curves of one system: team return per training episode vs env ticks.

    Args:
        curves: Learner -> curve summary (learners that train).
        greedy: The greedy baseline's evaluation team return on this system (reference line).
        system: System name.
        path: PNG to write.
        colors: Learner -> color.

    Returns:
        ``path``.
    """
    fig = Figure(figsize=(7.5, 4.6), dpi=DPI)
    ax = fig.add_subplot()
    for name, curve in curves.items():
        color = colors[name]
        label = f"{learner_label(name)} ({curve.seeds} seed{'s' if curve.seeds != 1 else ''})"
        _line_with_band(ax, curve.env_ticks, curve, color, label, alpha=0.2)
    if greedy is not None and greedy.n:
        ax.axhline(greedy.mean, color="black", ls="--", lw=1, label="greedy (evaluation)")
    ax.set_xlabel("training env ticks (ticks x parallel copies)")
    ax.set_ylabel("team return per episode")
    ax.set_title(
        f"{system_label(system)}: learning curves (mean and 95% CI band over seeds)", fontsize=11
    )
    ax.grid(alpha=0.3)
    ax.ticklabel_format(axis="x", style="sci", scilimits=(0, 4))
    ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    fig.savefig(path)
    return path


def team_return_figure(
    cells_by_system: dict[str, list[CellSummary]],
    path: Path,
    colors: dict[str, tuple[float, float, float, float]],
) -> Path:
    """Evaluation team return per learner, one panel per system, greedy as a dashed line.

    Args:
        cells_by_system: System -> its summaries.
        path: PNG to write.
        colors: Learner -> color.

    Returns:
        ``path``.
    """
    n = len(cells_by_system)
    fig = Figure(figsize=(max(6.0, 4.2 * n), 4.6), dpi=DPI)
    axes = fig.subplots(1, n, squeeze=False)[0]
    for ax, (system, cells) in zip(axes, cells_by_system.items(), strict=True):
        means, errs = _err([c.team_return for c in cells])
        x = np.arange(len(cells))
        ax.bar(
            x,
            np.nan_to_num(means),
            0.7,
            yerr=errs,
            capsize=3,
            color=[colors[c.learner] for c in cells],
        )
        greedy = next((c.greedy_return for c in cells if c.greedy_return.n), None)
        if greedy is not None:
            ax.axhline(greedy.mean, color="black", ls="--", lw=1, label="greedy baseline")
            ax.legend(fontsize=8, loc="lower right")
        ax.set_xticks(x, [learner_label(c.learner) for c in cells], rotation=30, ha="right")
        ax.set_ylabel("team return per evaluation episode")
        ax.set_xlabel("learner")
        ax.set_title(f"{system_label(system)} ({_seed_note(cells)})", fontsize=10)
        ax.grid(axis="y", alpha=0.3)
        ax.set_axisbelow(True)
    fig.tight_layout()
    fig.savefig(path)
    return path


def _line_with_band(
    ax: Any,
    x: Any,
    data: Any,
    color: Any,
    label: str,
    *,
    value: str = "mean",
    style: str = "-",
    marker: str | None = None,
    alpha: float = 0.15,
) -> None:
    """A line (``data.<value>``) and its interval band (``data.low`` to ``data.high``)."""
    ax.plot(x, getattr(data, value), style, marker=marker, ms=3, color=color, label=label, lw=1.5)
    low, high = np.asarray(data.low, dtype=float), np.asarray(data.high, dtype=float)
    if not np.isnan(low).all():
        ax.fill_between(x, low, high, color=color, alpha=alpha, lw=0)


@dataclass(frozen=True)
class SweepPanel:
    """One panel of a sweep figure: a value per series against a swept parameter.

    Attributes:
        title: Panel title.
        lines: Series -> line (an object with ``x``, ``mean``, ``low``, ``high`` lists). A series
            named ``"... (visited)"`` is drawn dashed, ``"... (parameters)"`` dotted.
        xlabel: X axis label.
        ylabel: Y axis label.
        log_x: Log-scale x axis (team sizes 10 to 200).
        log_y: Log-scale y axis.
        reference: A horizontal reference line (0.0 = greedy's return), or None.
    """

    title: str
    lines: dict[str, Any]
    xlabel: str
    ylabel: str
    log_x: bool = False
    log_y: bool = False
    reference: float | None = None


def _line_style(name: str) -> str:
    if name.endswith("(visited)"):
        return "--"
    if name.endswith("(parameters)"):
        return ":"
    return "-"


def sweep_figure(
    panels: Sequence[SweepPanel], path: Path, colors: dict[str, tuple[float, float, float, float]]
) -> Path:
    """Lines with 95 % bands against a swept parameter (team size, switch cost), one panel each.

    Args:
        panels: The panels, side by side.
        path: PNG to write.
        colors: Series -> color.

    Returns:
        ``path``.
    """
    fig = Figure(figsize=(max(6.5, 5.2 * len(panels)), 4.8), dpi=DPI)
    axes = fig.subplots(1, len(panels), squeeze=False)[0]
    for ax, panel in zip(axes, panels, strict=True):
        for name, line in panel.lines.items():
            _line_with_band(
                ax,
                line.x,
                line,
                colors.get(name, "gray"),
                name,
                style=_line_style(name),
                marker="o",
            )
        if panel.reference is not None:
            ax.axhline(panel.reference, color="black", ls="--", lw=1, label="greedy")
        if panel.log_x:
            ax.set_xscale("log")
            xs = sorted({x for line in panel.lines.values() for x in line.x})
            if xs:
                ax.set_xticks(xs, [f"{x:g}" for x in xs])
                ax.xaxis.set_minor_formatter(NullFormatter())  # only the swept values labelled
        if panel.log_y:
            ax.set_yscale("log")
        ax.set_xlabel(panel.xlabel)
        ax.set_ylabel(panel.ylabel)
        ax.set_title(panel.title, fontsize=10)
        ax.grid(alpha=0.3)
        if panel.lines:
            ax.legend(fontsize=7, loc="best")
    fig.tight_layout()
    fig.savefig(path)
    return path


def profile_figure(
    profiles: dict[str, Any], path: Path, colors: dict[str, tuple[float, float, float, float]]
) -> Path:
    """Performance profiles: fraction of runs with a score above tau, 95 % bootstrap band.

    Args:
        profiles: Series -> :class:`~mrta_rl.reports.stats.Profile`.
        path: PNG to write.
        colors: Series -> color.

    Returns:
        ``path``.
    """
    fig = Figure(figsize=(7.5, 4.6), dpi=DPI)
    ax = fig.add_subplot()
    for name, profile in profiles.items():
        _line_with_band(ax, profile.tau, profile, colors.get(name, "gray"), name, value="fraction")
    ax.axvline(0.0, color="black", ls="--", lw=1, label="greedy's return")
    ax.set_xlabel("team return relative to greedy's, (R - G) / |G| (tau)")
    ax.set_ylabel("fraction of runs with score > tau")
    ax.set_ylim(-0.02, 1.02)
    ax.set_title("Performance profiles (95% stratified bootstrap bands)", fontsize=11)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="best")
    fig.tight_layout()
    fig.savefig(path)
    return path

"""Figures of the report, drawn from the summary table with pandas and matplotlib.

* CTR per task type for low- and high-priority tasks per system (paper Figures 1-4) and ITR per
  robot (Figures 5-6): grouped bars, one bar per learner, 95 % CI error bars.
* Learning curves: training team return against training env ticks, mean and 95 % band.
* Team return of every learner per system next to the greedy baseline.
* Lines with 95 % bands against a swept parameter, performance profiles, and horizontal bars of
  paired differences (the studies and the yardsticks).

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
import pandas as pd
from matplotlib.figure import Figure
from matplotlib.ticker import NullFormatter

from mrta_rl.reports.frame import PRIORITY_LABELS, CurveSummary, system_label
from mrta_rl.reports.stats import MeanCI

DPI = 120
Colors = dict[str, Any]


def learner_colors(names: Sequence[str]) -> Colors:
    """A stable color per learner or series (tab10 in report order)."""
    from matplotlib import colormaps

    return {name: colormaps["tab10"](i % 10) for i, name in enumerate(names)}


def _save(fig: Figure, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=DPI)
    return path


def _half(stats: Sequence[MeanCI]) -> np.ndarray:
    return np.array([0.0 if math.isnan(s.ci95) else s.ci95 for s in stats], dtype=float)


def _seed_note(summary: pd.DataFrame) -> str:
    counts = sorted(set(summary["seeds"]))
    return f"mean ± 95% CI over {'/'.join(map(str, counts))} seed{'s' if counts != [1] else ''}"


def grouped_bars(
    summary: pd.DataFrame,
    metric: str,
    title: str,
    xlabel: str,
    ylabel: str,
    path: Path,
    colors: Colors,
) -> Path:
    """Bars of a percentage per item (task type, robot), one per learner, 95 % CI error bars."""
    rows = summary[summary["metric"] == metric]
    means = rows.pivot(index="item", columns="learner", values="mean")
    learners, items = list(dict.fromkeys(rows["learner"])), list(dict.fromkeys(rows["item"]))
    means = means.loc[items, learners].astype(float).fillna(0.0)
    half = rows.pivot(index="item", columns="learner", values="ci95").loc[items, learners]
    half = half.astype(float).fillna(0.0)
    # a percentage lies in [0, 100]: clip the interval drawn there (the CSV keeps it whole)
    err = np.stack([np.minimum(half, means), np.minimum(half, 100.0 - means)], axis=1)
    width = min(14.0, max(7.0, 1.0 + 0.3 * len(items) * len(learners)))
    fig = Figure(figsize=(width, 5.0))
    ax = fig.add_subplot()
    labels = dict(zip(rows["learner"], rows["label"], strict=True))
    means.rename(columns=labels).plot.bar(
        ax=ax,
        width=0.8,
        yerr=np.maximum(err, 0.0).transpose(2, 1, 0),
        capsize=2,
        color=[colors[n] for n in learners],
        error_kw={"elinewidth": 0.8},
        rot=0,
    )
    ax.set_xticks(range(len(items)), [f"{i}*" if i in ("all", "mean") else i for i in items])
    ax.set(xlabel=xlabel, ylabel=ylabel, ylim=(0, 105))
    ax.set_title(title, fontsize=11)
    ax.grid(axis="y", alpha=0.3)
    ax.set_axisbelow(True)
    ax.legend(
        title="learner",
        fontsize=8,
        title_fontsize=8,
        ncol=min(len(learners), 4),
        loc="upper center",
        bbox_to_anchor=(0.5, -0.16),
        frameon=False,
    )
    return _save(fig, path)


def ctr_figure(summary: pd.DataFrame, priority: str, path: Path, colors: Colors) -> Path:
    """Paper Figures 1-4: CTR of one priority per task type, one system."""
    rows = summary[summary["priority"] == priority]
    rows = rows.sort_values("item", key=lambda s: s == "all", kind="stable")
    system = system_label(rows["system"].iloc[0])
    title = f"{system}: CTR of {PRIORITY_LABELS[priority]} tasks ({_seed_note(rows)})"
    xlabel = "task type (* all = counts pooled over types)"
    return grouped_bars(rows, "ctr", title, xlabel, "completed task ratio CTR (%)", path, colors)


def itr_figure(summary: pd.DataFrame, path: Path, colors: Colors) -> Path:
    """Paper Figures 5-6: ITR per robot, one system."""
    title = f"{system_label(summary['system'].iloc[0])}: idle time ratio per robot"
    return grouped_bars(
        summary,
        "itr",
        f"{title} ({_seed_note(summary)})",
        "robot (* mean = mean over robots)",
        "idle time ratio ITR (% of ticks)",
        path,
        colors,
    )


def line_with_band(
    ax: Any,
    x: Any,
    mean: Any,
    low: Any,
    high: Any,
    color: Any,
    label: str,
    style: str = "-",
    marker: str | None = None,
    alpha: float = 0.15,
) -> None:
    """A line and its interval band (no band where the interval is undefined)."""
    ax.plot(x, mean, style, marker=marker, ms=3, color=color, label=label, lw=1.5)
    low, high = np.asarray(low, dtype=float), np.asarray(high, dtype=float)
    if not np.isnan(low).all():
        ax.fill_between(x, low, high, color=color, alpha=alpha, lw=0)


def curve_figure(
    curves: dict[str, tuple[str, CurveSummary]],
    greedy: MeanCI | None,
    system: str,
    path: Path,
    colors: Colors,
) -> Path:
    """Learning curves of one system: team return per training episode against env ticks."""
    fig = Figure(figsize=(7.5, 4.6))
    ax = fig.add_subplot()
    for name, (label, c) in curves.items():
        text = f"{label} ({c.seeds} seed{'s' if c.seeds != 1 else ''})"
        line_with_band(ax, c.env_ticks, c.mean, c.low, c.high, colors[name], text, alpha=0.2)
    if greedy is not None and greedy.n:
        ax.axhline(greedy.mean, color="black", ls="--", lw=1, label="greedy (evaluation)")
    ax.set(xlabel="training env ticks (ticks x parallel copies)", ylabel="team return per episode")
    ax.set_title(
        f"{system_label(system)}: learning curves (mean and 95% CI band over seeds)", fontsize=11
    )
    ax.grid(alpha=0.3)
    ax.ticklabel_format(axis="x", style="sci", scilimits=(0, 4))
    ax.legend(fontsize=8, loc="lower right")
    return _save(fig, path)


def team_return_figure(summary: pd.DataFrame, path: Path, colors: Colors) -> Path:
    """Evaluation team return per learner, one panel per system, greedy as a dashed line."""
    systems = list(dict.fromkeys(summary["system"]))
    fig = Figure(figsize=(max(6.0, 4.2 * len(systems)), 4.6))
    for ax, system in zip(fig.subplots(1, len(systems), squeeze=False)[0], systems, strict=True):
        rows = summary[summary["system"] == system]
        ret = rows[rows["metric"] == "team_return"]
        x = np.arange(len(ret))
        ax.bar(
            x,
            ret["mean"].fillna(0.0),
            0.7,
            yerr=_half(ret["stat"]),
            capsize=3,
            color=[colors[n] for n in ret["learner"]],
        )
        greedy = [s for s in rows[rows["metric"] == "greedy_team_return"]["stat"] if s.n]
        if greedy:
            ax.axhline(greedy[0].mean, color="black", ls="--", lw=1, label="greedy baseline")
            ax.legend(fontsize=8, loc="lower right")
        ax.set_xticks(x, ret["label"], rotation=30, ha="right")
        ax.set(ylabel="team return per evaluation episode", xlabel="learner")
        ax.set_title(f"{system_label(system)} ({_seed_note(rows)})", fontsize=10)
        ax.grid(axis="y", alpha=0.3)
        ax.set_axisbelow(True)
    return _save(fig, path)


@dataclass(frozen=True)
class SweepPanel:
    """One panel of a sweep figure: per series a table ``x, mean, low, high``.

    A series named ``... (visited)`` is drawn dashed, ``... (parameters)`` dotted; ``reference``
    is a horizontal line (0.0: greedy's return).
    """

    title: str
    lines: dict[str, pd.DataFrame]
    xlabel: str
    ylabel: str
    log_x: bool = False
    log_y: bool = False
    reference: float | None = None


def sweep_figure(panels: Sequence[SweepPanel], path: Path, colors: Colors) -> Path:
    """Lines with 95 % bands against a swept parameter (team size, switch cost), one panel each."""
    fig = Figure(figsize=(max(6.5, 5.2 * len(panels)), 4.8))
    for ax, panel in zip(fig.subplots(1, len(panels), squeeze=False)[0], panels, strict=True):
        for name, line in panel.lines.items():
            style = (
                "--"
                if name.endswith("(visited)")
                else ":"
                if name.endswith("(parameters)")
                else "-"
            )
            line_with_band(
                ax,
                line["x"],
                line["mean"],
                line["low"],
                line["high"],
                colors.get(name, "gray"),
                name,
                style=style,
                marker="o",
            )
        if panel.reference is not None:
            ax.axhline(panel.reference, color="black", ls="--", lw=1, label="greedy")
        if panel.log_x:
            ax.set_xscale("log")
            xs = sorted({x for line in panel.lines.values() for x in line["x"]})
            if xs:
                ax.set_xticks(xs, [f"{x:g}" for x in xs])
                ax.xaxis.set_minor_formatter(NullFormatter())  # only the swept values labelled
        if panel.log_y:
            ax.set_yscale("log")
        ax.set(xlabel=panel.xlabel, ylabel=panel.ylabel)
        ax.set_title(panel.title, fontsize=10)
        ax.grid(alpha=0.3)
        if panel.lines:
            ax.legend(fontsize=7, loc="best")
    return _save(fig, path)


def profile_figure(profiles: dict[str, Any], path: Path, colors: Colors) -> Path:
    """Performance profiles: fraction of runs with a score above tau, 95 % bootstrap band."""
    fig = Figure(figsize=(7.5, 4.6))
    ax = fig.add_subplot()
    for name, p in profiles.items():
        line_with_band(ax, p.tau, p.fraction, p.low, p.high, colors.get(name, "gray"), name)
    ax.axvline(0.0, color="black", ls="--", lw=1, label="greedy's return")
    ax.set(
        xlabel="team return relative to greedy's, (R - G) / |G| (tau)",
        ylabel="fraction of runs with score > tau",
        ylim=(-0.02, 1.02),
    )
    ax.set_title("Performance profiles (95% stratified bootstrap bands)", fontsize=11)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="best")
    return _save(fig, path)


def difference_bars(
    panels: Sequence[tuple[str, str, list[tuple[str, MeanCI]]]], path: Path
) -> Path:
    """Horizontal bars of paired differences with 95 % intervals, one panel each.

    Green: the interval is above zero, red: below, gray: it holds zero.
    """
    height = max(len(items) for _, _, items in panels) * 0.45 + 1.4
    # long labels (``semi-CQL [state=slots ...]``) need room: about 0.065 inch a character
    label_inches = 0.065 * max(len(name) for _, _, items in panels for name, _ in items)
    fig = Figure(figsize=((3.6 + label_inches) * len(panels), height))
    for k, (title, xlabel, items) in enumerate(panels):
        ax = fig.add_subplot(1, len(panels), k + 1)
        y = np.arange(len(items))[::-1]
        diffs = [d for _, d in items]
        color = [
            "tab:green" if d.low > 0 else "tab:red" if d.high < 0 else "tab:gray" for d in diffs
        ]
        ax.barh(y, [d.mean for d in diffs], xerr=_half(diffs), color=color, alpha=0.8, capsize=3)
        ax.axvline(0.0, color="black", linewidth=0.8)
        ax.set_yticks(y, [n for n, _ in items], fontsize=8)
        ax.set_xlabel(xlabel)
        ax.set_title(title, fontsize=9)
    return _save(fig, path)

"""Figures of the report: grouped bars, lines with 95 % bands, bars of paired differences.

Figures are built on :class:`matplotlib.figure.Figure` directly (no pyplot state, no GUI
backend), so a report can be made in a headless process or a parallel job.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from matplotlib.figure import Figure
from matplotlib.ticker import NullFormatter

from mrta_rl.reports.frame import PRIORITY_LABELS, system_label
from mrta_rl.reports.stats import MeanCI

DPI = 120
Colors = dict[str, Any]
BAR_STYLE = {"width": 0.8, "capsize": 2, "rot": 0, "error_kw": {"elinewidth": 0.8}}
LEGEND_BELOW = {"fontsize": 8, "title_fontsize": 8, "loc": "upper center", "frameon": False}
LEGEND_BELOW |= {"bbox_to_anchor": (0.5, -0.16)}


def learner_colors(names: Sequence[str]) -> Colors:
    """A stable color per learner or series (tab10 in report order)."""
    from matplotlib import colormaps

    return {name: colormaps["tab10"](i % 10) for i, name in enumerate(names)}


def _panels(n: int, width: float, height: float, per_panel: float) -> tuple[Figure, list]:
    fig = Figure(figsize=(max(width, per_panel * n), height))
    return fig, list(fig.subplots(1, n, squeeze=False)[0])


def _save(fig: Figure, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=DPI)
    return path


def _seed_note(summary: pd.DataFrame) -> str:
    counts = sorted(set(summary["seeds"]))
    return f"mean ± 95% CI over {'/'.join(map(str, counts))} seed{'s' if counts != [1] else ''}"


def grouped_bars(rows: pd.DataFrame, metric: str, path: Path, colors: Colors) -> Path:
    """Paper Figures 1-6: CTR per task type or ITR per robot of one system, bars per learner."""
    rows = rows[rows["metric"] == metric]
    system = system_label(rows["system"].iloc[0])
    if metric == "ctr":
        rows = rows.sort_values("item", key=lambda s: s == "all", kind="stable")
        title = f"{system}: CTR of {PRIORITY_LABELS[rows['priority'].iloc[0]]} tasks"
        xlabel = "task type (* all = counts pooled over types)"
        ylabel = "completed task ratio CTR (%)"
    else:
        title = f"{system}: idle time ratio per robot"
        xlabel, ylabel = "robot (* mean = mean over robots)", "idle time ratio ITR (% of ticks)"
    learners, items = list(dict.fromkeys(rows["learner"])), list(dict.fromkeys(rows["item"]))
    means, half = (
        rows.pivot(index="item", columns="learner", values=v).loc[items, learners].astype(float)
        for v in ("mean", "ci95")
    )
    means, half = means.fillna(0.0), half.fillna(0.0)
    # a percentage lies in [0, 100]: clip the interval drawn there (the CSV keeps it whole)
    err = np.stack([np.minimum(half, means), np.minimum(half, 100.0 - means)], axis=1)
    fig = Figure(figsize=(min(14.0, max(7.0, 1.0 + 0.3 * len(items) * len(learners))), 5.0))
    ax = fig.add_subplot()
    labels = dict(zip(rows["learner"], rows["label"], strict=True))
    yerr, color = np.maximum(err, 0.0).transpose(2, 1, 0), [colors[n] for n in learners]
    means.rename(columns=labels).plot.bar(ax=ax, yerr=yerr, color=color, **BAR_STYLE)
    ax.set_xticks(range(len(items)), [f"{i}*" if i in ("all", "mean") else i for i in items])
    ax.set(xlabel=xlabel, ylabel=ylabel, ylim=(0, 105))
    ax.set_title(f"{title} ({_seed_note(rows)})", fontsize=11)
    ax.grid(axis="y", alpha=0.3)
    ax.set_axisbelow(True)
    ax.legend(title="learner", ncol=min(len(learners), 4), **LEGEND_BELOW)
    return _save(fig, path)


def team_return_figure(summary: pd.DataFrame, path: Path, colors: Colors) -> Path:
    """Evaluation team return per learner, one panel per system, greedy as a dashed line."""
    systems = list(dict.fromkeys(summary["system"]))
    fig, axes = _panels(len(systems), 6.0, 4.6, 4.2)
    for ax, system in zip(axes, systems, strict=True):
        rows = summary[summary["system"] == system]
        ret = rows[rows["metric"] == "team_return"]
        x = np.arange(len(ret))
        colors_, half = [colors[n] for n in ret["learner"]], [s.half for s in ret["stat"]]
        ax.bar(x, ret["mean"].fillna(0.0), 0.7, yerr=half, capsize=3, color=colors_)
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
class Panel:
    """One panel of lines with 95 % bands: per series a table ``x, mean, low, high``."""

    title: str
    lines: dict[str, pd.DataFrame]
    xlabel: str
    ylabel: str
    log_x: bool = False
    log_y: bool = False
    hline: tuple[float, str] | None = None
    vline: tuple[float, str] | None = None
    ylim: tuple[float, float] | None = None


def line_figure(panels: Sequence[Panel], path: Path, colors: Colors, size=(6.5, 4.8)) -> Path:
    """Lines with 95 % bands (learning curves, sweeps, performance profiles), a panel each."""
    fig, axes = _panels(len(panels), size[0], size[1], 5.2)
    for ax, panel in zip(axes, panels, strict=True):
        for name, line in panel.lines.items():
            style = {"(visited)": "--", "(parameters)": ":"}.get(name.rpartition(" ")[2], "-")
            color = colors.get(name, "gray")
            ax.plot(line["x"], line["mean"], style, marker="o", ms=3, color=color, label=name)
            low, high = (np.asarray(line[k], dtype=float) for k in ("low", "high"))
            if not np.isnan(low).all():  # no band where the interval is undefined
                ax.fill_between(line["x"], low, high, color=color, alpha=0.15, lw=0)
        for ref, draw in ((panel.hline, ax.axhline), (panel.vline, ax.axvline)):
            if ref is not None:
                draw(ref[0], color="black", ls="--", lw=1, label=ref[1])
        if panel.log_x:
            ax.set_xscale("log")
            xs = sorted({x for line in panel.lines.values() for x in line["x"]})
            if xs:
                ax.set_xticks(xs, [f"{x:g}" for x in xs])
                ax.xaxis.set_minor_formatter(NullFormatter())  # only the swept values labelled
        if panel.log_y:
            ax.set_yscale("log")
        ax.set(xlabel=panel.xlabel, ylabel=panel.ylabel, ylim=panel.ylim)
        ax.set_title(panel.title, fontsize=10)
        ax.grid(alpha=0.3)
        if panel.lines:
            ax.legend(fontsize=7, loc="best")
    return _save(fig, path)


def difference_bars(
    panels: Sequence[tuple[str, str, list[tuple[str, MeanCI]]]], path: Path
) -> Path:
    """Horizontal bars of paired differences with 95 % intervals: green above zero, red below."""
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
        means, half = [d.mean for d in diffs], [d.half for d in diffs]
        ax.barh(y, means, xerr=half, color=color, alpha=0.8, capsize=3)
        ax.axvline(0.0, color="black", linewidth=0.8)
        ax.set_yticks(y, [n for n, _ in items], fontsize=8)
        ax.set_xlabel(xlabel)
        ax.set_title(title, fontsize=9)
    return _save(fig, path)

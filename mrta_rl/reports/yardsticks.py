"""Report section "Learning against the rules": every learner next to the rules it must beat.

For each system it sets, on the same evaluation episodes (every run plays evaluation episode
``e`` on the same task stream, ``runners/evaluate.py``):

* each learner's **trained** policy and its **untrained** starting policy (a run with
  ``train.episodes=0``: the prior or initial network alone), per state encoding (``features``);
* **greedy**, the plain auction (the baseline every run evaluates);
* the **best team_reserve** setting found among the runs (``experiment=team_reserve_grid``) and
  the **rollout** planner, the yardsticks of issue 10.

Differences are *paired*: per evaluation episode ``e``, ``d_e`` = (policy's return on ``e``,
averaged over its training seeds) - (yardstick's return on ``e``, averaged likewise), and the
95 % t interval is over the episodes (``reports/stats.py``). The interval measures the
evaluation-stream noise, which the pairing removes from the comparison; the spread over training
seeds is reported next to it (the learner's own interval over seeds). Runs need the
per-episode returns (``team_return.per_episode`` in ``metrics.json``); older runs without them
are left out of the paired columns.

A run re-evaluated with ``scripts/evaluate.py`` (for instance on more episodes:
``episodes=100``) is scored on that re-evaluation: its ``eval_metrics.json`` replaces the
evaluation and greedy blocks of ``metrics.json`` (the training block stays). Greedy is taken from
the run of the system with the most evaluation episodes; policies evaluated on another number of
episodes than a yardstick show no paired difference with it ("–").

A second table, "Does training beat its own start?", gives per trained learner its untrained
return, the trained mean over seeds, and trained - untrained twice: paired over the evaluation
episodes and over the training seeds (each seed's mean minus the untrained mean), with the verdict
of issue 10's acceptance 2 (the paired interval above zero).
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mrta_rl.config import UserError
from mrta_rl.reports.aggregate import learner_label, system_label
from mrta_rl.reports.collect import RunRecord, configuration_variants
from mrta_rl.reports.stats import MeanCI, mean_ci
from mrta_rl.reports.tables import markdown_table, write_csv
from mrta_rl.run_files import EVAL_METRICS_FILE

TITLE = "Learning against the rules"
RULES = ("team_reserve", "rollout")  # the yardstick rules of issue 10 (fixed learners)
GREEDY = "greedy"
BEST_RESERVE = "team_reserve (best)"
RESERVE_KEYS = ("reserve", "hold_level", "hold_scope", "grouping", "order")
CSV_HEADER = ["system", "policy", "seeds", "mean", "ci95_seeds", "versus", "diff", "diff_ci95"]
START_HEADER = [
    "system",
    "policy",
    "episodes",
    "untrained",
    "seeds",
    "trained",
    "trained_ci95",
    "paired_diff",
    "paired_ci95",
    "seeds_diff",
    "seeds_ci95",
    "met",
]
EVALUATION_BLOCKS = ("eval", "baseline_greedy")  # what a re-evaluation replaces


@dataclass
class Policy:
    """One evaluated policy of one system: its runs' per-episode returns.

    Attributes:
        name: Display name (learner, ``[untrained]``, ``[features]``, rule settings).
        learner: Learner name (yaml stem).
        kind: ``"trained"``, ``"untrained"``, ``"rule"`` or ``"greedy"``.
        returns: One array of per-episode returns per run (training seed).
        means: Mean evaluation return of each run.
        note: Extra text (e.g. a team_reserve setting).
        features: The learner's state encoding (``"paper"`` for rules).
    """

    name: str
    learner: str
    kind: str
    returns: list[np.ndarray]
    means: list[float]
    note: str = ""
    features: str = "paper"

    @property
    def per_episode(self) -> np.ndarray | None:
        """Per-episode returns averaged over the runs, or None if a run lacks them."""
        if not self.returns or any(len(r) == 0 for r in self.returns):
            return None
        if len({len(r) for r in self.returns}) != 1:
            return None
        return np.mean(self.returns, axis=0)

    @property
    def over_seeds(self) -> MeanCI:
        """Mean evaluation return over the runs with its 95 % t interval."""
        return mean_ci(self.means)


def paired_difference(a: np.ndarray | None, b: np.ndarray | None) -> MeanCI:
    """Mean of ``a - b`` over evaluation episodes with its 95 % t interval (NaN if unpaired)."""
    if a is None or b is None or len(a) != len(b) or len(a) == 0:
        return MeanCI(0, math.nan, math.nan, math.nan)
    return mean_ci((a - b).tolist())


def _per_episode(block: dict[str, Any]) -> np.ndarray:
    values = (block.get("team_return") or {}).get("per_episode") or []
    return np.array([math.nan if v is None else v for v in values], float)


def with_reevaluation(run: RunRecord) -> RunRecord:
    """The run scored on its re-evaluation (``eval_metrics.json``) if it has one (module docstring).

    Raises:
        ValueError: if ``eval_metrics.json`` is not a re-evaluation (names the file and the key).
    """
    path = Path(run.run_dir) / EVAL_METRICS_FILE
    if not path.is_file():
        return run
    again = json.loads(path.read_text())
    missing = [k for k in EVALUATION_BLOCKS if k not in again]
    if missing:
        raise ValueError(f"{path}: not a re-evaluation of scripts/evaluate.py, no {missing}")
    metrics = {**run.metrics, **{k: again[k] for k in EVALUATION_BLOCKS}}
    return dataclasses.replace(run, metrics=metrics)


def _episodes(block: dict[str, Any]) -> int:
    return len((block.get("team_return") or {}).get("per_episode") or [])


def _kind(run: RunRecord) -> str:
    """``"rule"`` (a fixed policy: no learning space), ``"untrained"`` or ``"trained"``."""
    if not run.metrics.get("learning_space"):
        return "rule"
    return "trained" if (run.metrics.get("train") or {}).get("episodes", 0) > 0 else "untrained"


def _base(run: RunRecord) -> str:
    """The learner's yaml stem (``run.learner`` also names what sets its configuration apart)."""
    return str(run.metrics["learner"]["name"])


def _features(run: RunRecord) -> str:
    return str((run.config.get("learner") or {}).get("features", "paper"))


def _reserve_setting(run: RunRecord) -> str:
    cfg = run.config.get("learner") or {}
    return ", ".join(f"{k}={cfg[k]}" for k in RESERVE_KEYS if k in cfg)


def _check_same_streams(runs: Sequence[RunRecord], greedy: dict[str, RunRecord]) -> None:
    """Refuse runs of as many episodes as the reference greedy but other task streams.

    Every run also plays greedy (deterministic) on its evaluation episodes, so two runs were
    evaluated on the same task streams exactly when their greedy returns agree episode by
    episode. Another ``eval.seed`` or ``eval.batch_size`` (a second round of copies continues
    each copy's stream) changes them; pairing such runs episode by episode would be silently
    wrong.

    Raises:
        UserError: naming the two run dirs (printed without traceback by the scripts).
    """
    for run in runs:
        reference = greedy[run.system]
        ours = _per_episode(run.metrics["baseline_greedy"])
        theirs = _per_episode(reference.metrics["baseline_greedy"])
        if len(ours) == len(theirs) and not np.array_equal(ours, theirs, equal_nan=True):
            raise UserError(
                f"{run.run_dir} and {reference.run_dir} were evaluated on different task streams "
                f"({len(ours)} episodes each, but their greedy baselines differ): evaluate both "
                "with the same eval.seed and eval.batch_size (scripts/evaluate.py episodes=N "
                "batch_size=N)"
            )


def collect_policies(runs: Sequence[RunRecord]) -> dict[str, list[Policy]]:
    """Group the runs into policies per system (module docstring); ``{}`` if nothing to compare.

    The section applies when the runs hold a yardstick rule or an untrained learner.

    Args:
        runs: Every finished run (duplicates of a ``(learner, system, seed)`` included: the
            settings of a team_reserve grid are told apart by their config).

    Returns:
        ``{system: [greedy, best team_reserve, rollout, learners...]}``.
    """
    if not any(_base(r) in RULES or _kind(r) == "untrained" for r in runs):
        return {}
    runs = [with_reevaluation(r) for r in runs]
    # trained configurations are told apart among the trained runs only: the settings in which
    # an untrained run differs (train.episodes, learning rates...) do not change its policy
    trained = [r for r in runs if _kind(r) == "trained"]
    trained_variant = dict(
        zip(
            (id(r) for r in trained),
            configuration_variants([dataclasses.replace(r, learner=_base(r)) for r in trained]),
            strict=True,
        )
    )
    groups: dict[tuple[str, str, str, str], list[RunRecord]] = defaultdict(list)
    greedy: dict[str, RunRecord] = {}
    for run in runs:  # greedy of the run with the most evaluation episodes (the first on ties)
        known = greedy.get(run.system)
        if known is None or _episodes(run.metrics["baseline_greedy"]) > _episodes(
            known.metrics["baseline_greedy"]
        ):
            greedy[run.system] = run
        learner = _base(run)
        if learner == GREEDY:
            continue
        kind = _kind(run)
        if kind == "rule":
            variant = _reserve_setting(run) if learner == "team_reserve" else ""
        elif kind == "trained":  # the encoding first, then any other setting that differs
            # eval.* settings do not make a policy: each run is scored on its (re-)evaluation
            # and other task streams are refused (_check_same_streams)
            rest = [
                t
                for t in trained_variant[id(run)].split()
                if not t.startswith(("features=", "eval."))
            ]
            features = _features(run)
            variant = " ".join([features] * (features != "paper") + rest) or "paper"
        else:
            variant = _features(run)
        groups[(run.system, learner, kind, variant)].append(run)
    _check_same_streams(runs, greedy)
    out: dict[str, list[Policy]] = {}
    for system, base in greedy.items():
        block = base.metrics["baseline_greedy"]
        policies = [
            Policy(
                GREEDY,
                GREEDY,
                "greedy",
                [_per_episode(block)],
                [block["team_return"]["mean"]],
            )
        ]
        reserve = [
            (variant, members)
            for (s, learner, _, variant), members in groups.items()
            if s == system and learner == "team_reserve"
        ]
        if reserve:
            variant, members = max(reserve, key=lambda vm: np.mean([_mean(r) for r in vm[1]]))
            policies.append(_policy(BEST_RESERVE, "team_reserve", "rule", members, variant))
        for (s, learner, kind, variant), members in sorted(groups.items(), key=_order):
            if s != system or learner == "team_reserve":
                continue
            name = learner_label(learner)
            if kind != "rule":
                name += " untrained" if kind == "untrained" else ""
                name += f" [{variant}]" if variant != "paper" else ""
            features = _features(members[0]) if kind != "rule" else "paper"
            policies.append(_policy(name, learner, kind, members, features=features))
        out[system] = policies
    return out


def _order(item: tuple[tuple[str, str, str, str], list[RunRecord]]) -> tuple:
    (system, learner, kind, variant), _ = item
    rank = {"rule": 0, "untrained": 1, "trained": 2}[kind]
    return (system, rank == 0 and learner != "rollout", learner, variant, rank)


def _mean(run: RunRecord) -> float:
    return float(run.metrics["eval"]["team_return"]["mean"])


def _policy(
    name: str, learner: str, kind: str, runs: list[RunRecord], note: str = "", features="paper"
) -> Policy:
    returns = [_per_episode(r.metrics["eval"]) for r in runs]
    return Policy(name, learner, kind, returns, [_mean(r) for r in runs], note, features)


def _yardsticks(policies: list[Policy]) -> list[Policy]:
    return [p for p in policies if p.kind in ("greedy", "rule")]


def _starting(policy: Policy, policies: list[Policy]) -> Policy | None:
    """The untrained policy of a trained one: same learner, same features if run, else any.

    An untrained learner plays its prior (tabular) or its initial network's bias (neural),
    which does not read the extra features, so one untrained run serves every encoding.
    """
    if policy.kind != "trained":
        return None
    starts = [p for p in policies if p.kind == "untrained" and p.learner == policy.learner]
    same = [p for p in starts if p.features == policy.features]
    return (same or starts or [None])[0]


def section_rows(by_system: dict[str, list[Policy]]) -> list[list[Any]]:
    """CSV rows: each policy against its starting policy and every yardstick."""
    rows = []
    for system, policies in by_system.items():
        for p in policies:
            stat = p.over_seeds
            versus = [*(_yardsticks(policies))]
            start = _starting(p, policies)
            if start is not None:
                versus.insert(0, start)
            for other in versus:
                if other is p:
                    continue
                diff = paired_difference(p.per_episode, other.per_episode)
                rows.append(
                    [
                        system,
                        p.name,
                        stat.n,
                        round(stat.mean, 3),
                        _round(stat.ci95),
                        other.name,
                        _round(diff.mean),
                        _round(diff.ci95),
                    ]
                )
    return rows


@dataclass(frozen=True)
class StartComparison:
    """A trained policy against its untrained start (acceptance 2 of issue 10).

    Attributes:
        trained: The trained policy (one run per training seed).
        start: Its untrained starting policy.
        paired: Trained (mean over seeds) - untrained per evaluation episode, over episodes.
        over_seeds: Each seed's mean return - the untrained mean return, over seeds.
    """

    trained: Policy
    start: Policy
    paired: MeanCI
    over_seeds: MeanCI

    @property
    def episodes(self) -> int:
        """Evaluation episodes of the paired difference (0 if unpaired)."""
        return self.paired.n

    @property
    def verdict(self) -> str:
        """``yes`` (paired interval above zero), ``over seeds only``, ``no (below)`` or ``no``."""
        if self.paired.low > 0:
            return "yes"
        if self.paired.high < 0:
            return "no (below)"
        if self.over_seeds.low > 0:
            return "over seeds only"
        return "no"


def start_comparisons(by_system: dict[str, list[Policy]]) -> list[tuple[str, StartComparison]]:
    """``(system, comparison)`` for every trained policy that has an untrained start."""
    out = []
    for system, policies in by_system.items():
        for p in policies:
            start = _starting(p, policies)
            if start is None:
                continue
            untrained = float(np.mean(start.means))
            paired = paired_difference(p.per_episode, start.per_episode)
            seeds = mean_ci([m - untrained for m in p.means])
            out.append((system, StartComparison(p, start, paired, seeds)))
    return out


def start_rows(by_system: dict[str, list[Policy]]) -> list[list[Any]]:
    """CSV rows of :func:`start_comparisons` (:data:`START_HEADER`)."""
    rows = []
    for system, c in start_comparisons(by_system):
        trained = c.trained.over_seeds
        rows.append(
            [
                system,
                c.trained.name,
                c.episodes,
                round(float(np.mean(c.start.means)), 3),
                trained.n,
                round(trained.mean, 3),
                _round(trained.ci95),
                _round(c.paired.mean),
                _round(c.paired.ci95),
                _round(c.over_seeds.mean),
                _round(c.over_seeds.ci95),
                c.verdict,
            ]
        )
    return rows


def _start_markdown(by_system: dict[str, list[Policy]]) -> list[str]:
    comparisons = start_comparisons(by_system)
    if not comparisons:
        return []
    header = [
        "learner",
        "system",
        "untrained",
        "trained (seeds)",
        "trained − untrained, paired over episodes",
        "over seeds",
        "met?",
    ]
    rows = [
        [
            c.trained.name,
            system_label(system),
            f"{np.mean(c.start.means):.1f}",
            f"{c.trained.over_seeds.format(1)} ({len(c.trained.means)})",
            f"{_fmt(c.paired)} ({c.episodes})" if c.episodes else "–",
            _signed(c.over_seeds),
            c.verdict,
        ]
        for system, c in comparisons
    ]
    return [
        "### Does training beat its own start?",
        "",
        "Trained − untrained: paired over the evaluation episodes (their number in parentheses), "
        "and over the training seeds (each seed's mean return minus the untrained return); "
        "met: the paired interval is above zero.",
        "",
        markdown_table(header, rows),
        "",
    ]


def _signed(value: MeanCI) -> str:
    """``"+19.7 ± 5.7"``; ``"+19.7"`` for one value; ``"–"`` for none."""
    if value.n == 0:
        return "–"
    return f"{value.mean:+.1f}" + (f" ± {value.ci95:.1f}" if value.n > 1 else "")


def _round(value: float) -> float | str:
    return "" if math.isnan(value) else round(value, 3)


def _fmt(diff: MeanCI) -> str:
    if diff.n == 0:
        return "–"
    mark = " **↑**" if diff.low > 0 else (" ↓" if diff.high < 0 else "")
    return f"{diff.mean:+.1f} ± {diff.ci95:.1f}{mark}"


def section_markdown(
    by_system: dict[str, list[Policy]], figure: Path | None, start_plot: Path | None = None
) -> str:
    """The section's text: one table per system, its figure, the start table and its figure."""
    md = [
        f"## {TITLE}",
        "",
        "Each policy against its untrained starting policy (`train.episodes=0`), greedy, the "
        "best `team_reserve` setting among these runs and the `rollout` planner: mean paired "
        "difference of the evaluation return over the shared evaluation episodes ± the "
        "half-width of its 95 % t interval (**↑**: the interval is above zero, ↓: below). "
        "`return` is the mean over training seeds ± its 95 % interval over seeds.",
        "",
    ]
    for system, policies in by_system.items():
        sticks = _yardsticks(policies)
        header = ["policy", "seeds", "return", "vs untrained", *(f"vs {s.name}" for s in sticks)]
        rows = []
        for p in policies:
            start = _starting(p, policies)
            rows.append(
                [
                    p.name + (f" ({p.note})" if p.note else ""),
                    len(p.means),
                    p.over_seeds.format(1),
                    _fmt(paired_difference(p.per_episode, start.per_episode)) if start else "",
                    *(
                        "" if s is p else _fmt(paired_difference(p.per_episode, s.per_episode))
                        for s in sticks
                    ),
                ]
            )
        md += [f"### {system_label(system)}", "", markdown_table(header, rows), ""]
    if figure is not None:
        md += [f"![{TITLE}]({figure.name})", ""]
    md += _start_markdown(by_system)
    if start_plot is not None:
        md += [f"![Does training beat its own start?]({start_plot.name})", ""]
    return "\n".join(md)


def _color(diff: MeanCI) -> str:
    """Green above zero, red below, gray when the interval holds zero."""
    return "tab:green" if diff.low > 0 else "tab:red" if diff.high < 0 else "tab:gray"


def difference_figure(by_system: dict[str, list[Policy]], path: Path) -> Path | None:
    """Paired difference to the best team_reserve (or greedy), with 95 % intervals, per system."""
    from matplotlib.figure import Figure

    panels = []
    for system, policies in by_system.items():
        ref = next((p for p in policies if p.name == BEST_RESERVE), policies[0])
        items = [
            (p.name, paired_difference(p.per_episode, ref.per_episode))
            for p in policies
            if p is not ref
        ]
        items = [(n, d) for n, d in items if d.n]
        if items:
            panels.append((system, ref, items))
    if not panels:
        return None
    height = max(len(items) for _, _, items in panels) * 0.45 + 1.4
    names = [n for _, _, items in panels for n, _ in items]
    fig = Figure(figsize=((3.6 + _label_inches(names)) * len(panels), height))
    for k, (system, ref, items) in enumerate(panels):
        ax = fig.add_subplot(1, len(panels), k + 1)
        y = np.arange(len(items))[::-1]
        means = np.array([d.mean for _, d in items])
        errs = np.array([0.0 if math.isnan(d.ci95) else d.ci95 for _, d in items])
        colors = [_color(d) for _, d in items]
        ax.barh(y, means, xerr=errs, color=colors, alpha=0.8, capsize=3)
        ax.axvline(0.0, color="black", linewidth=0.8)
        ax.set_yticks(y, [n for n, _ in items], fontsize=8)
        ax.set_xlabel(f"paired difference to {ref.name}\n(team return per episode)")
        ax.set_title(f"{system_label(system)}: {ref.name} = {ref.over_seeds.mean:.1f}", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    return path


def _label_inches(labels: list[str]) -> float:
    """Width the longest y tick label takes at font size 8 (about 0.065 inch a character).

    A figure of fixed width lets long variant names (``semi-CQL [state=slots ...]``) push the
    axes out of it, and ``tight_layout`` then cuts the title and the axis label.
    """
    return 0.065 * max((len(label) for label in labels), default=0)


def start_figure(by_system: dict[str, list[Policy]], path: Path) -> Path | None:
    """Trained - untrained, paired over episodes with 95 % intervals: one bar per learner/system."""
    from matplotlib.figure import Figure

    comparisons = [(s, c) for s, c in start_comparisons(by_system) if c.episodes]
    if not comparisons:
        return None
    labels = [f"{c.trained.name}, {system_label(s)}" for s, c in comparisons]
    fig = Figure(figsize=(4.4 + _label_inches(labels), len(comparisons) * 0.32 + 1.4))
    ax = fig.add_subplot(1, 1, 1)
    y = np.arange(len(comparisons))[::-1]
    diffs = [c.paired for _, c in comparisons]
    errs = [0.0 if math.isnan(d.ci95) else d.ci95 for d in diffs]
    ax.barh(y, [d.mean for d in diffs], xerr=errs, color=[_color(d) for d in diffs], capsize=3)
    ax.axvline(0.0, color="black", linewidth=0.8)
    ax.set_yticks(y, labels, fontsize=8)
    ax.set_xlabel("trained − untrained, paired over the evaluation episodes\n(team return)")
    ax.set_title("Does training beat its own start? (95 % t intervals)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    return path


def write_section(runs: Sequence[RunRecord], out_dir: Path) -> tuple[str, dict[str, Path]]:
    """Build the section from the runs: markdown, ``yardsticks.csv`` and ``yardsticks.png``.

    Args:
        runs: Every finished run, duplicates included.
        out_dir: The report folder.

    Returns:
        The markdown (``""`` if the runs hold nothing to compare) and the files written.
    """
    by_system = collect_policies(runs)
    if not by_system:
        return "", {}
    files = {
        "yardsticks": write_csv(out_dir / "yardsticks.csv", CSV_HEADER, section_rows(by_system)),
        "yardsticks_start": write_csv(
            out_dir / "yardsticks_start.csv", START_HEADER, start_rows(by_system)
        ),
    }
    figure = difference_figure(by_system, out_dir / "yardsticks.png")
    if figure is not None:
        files["yardsticks_png"] = figure
    start = start_figure(by_system, out_dir / "yardsticks_start.png")
    if start is not None:
        files["yardsticks_start_png"] = start
    return section_markdown(by_system, figure, start), files

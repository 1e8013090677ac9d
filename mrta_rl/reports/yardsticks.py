"""Report section "Learning against the rules": every learner next to the rules it must beat.

For each system it sets, on the same evaluation episodes (every run plays evaluation episode
``e`` on the same task stream, ``runners/evaluate.py``): each learner's **trained** policy and its
**untrained** starting policy (a run with ``train.episodes=0``), per state encoding
(``features``); **greedy**, the plain auction (the baseline every run evaluates); the **best
team_reserve** setting found among the runs (``experiment=team_reserve_grid``) and the
**rollout** planner.

Differences are *paired*: per evaluation episode ``e``, ``d_e`` = (policy's return on ``e``,
averaged over its training seeds) - (yardstick's return on ``e``, averaged likewise), with the
95 % t interval over the episodes; the spread over training seeds is reported next to it. Runs
without per-episode returns (``team_return.per_episode``) are left out of the paired columns.

A run re-evaluated with ``scripts/evaluate.py`` is scored on that re-evaluation: its
``eval_metrics.json`` replaces the evaluation and greedy blocks of ``metrics.json``. Greedy is
taken from the run of the system with the most evaluation episodes; policies evaluated on another
number of episodes than a yardstick show no paired difference with it ("–").

A second table, "Does training beat its own start?", gives per trained learner its untrained
return, the trained mean over seeds, and trained - untrained paired over the evaluation episodes
and over the training seeds, with the verdict (``yes``: the paired interval is above zero).
"""

from __future__ import annotations

import dataclasses
import math
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from mrta_rl.config import UserError
from mrta_rl.reports import figures
from mrta_rl.reports.collect import RunRecord, configuration_variants
from mrta_rl.reports.frame import system_label
from mrta_rl.reports.stats import MeanCI, mean_ci
from mrta_rl.reports.tables import markdown_table, signed, write_csv
from mrta_rl.run_files import EVAL_METRICS_FILE, read_json

TITLE = "Learning against the rules"
RULES = ("team_reserve", "rollout")  # the yardstick rules (fixed learners)
GREEDY = "greedy"
BEST_RESERVE = "team_reserve (best)"
RESERVE_KEYS = ("reserve", "hold_level", "hold_scope", "grouping", "order")
CSV_HEADER = ["system", "policy", "seeds", "mean", "ci95_seeds", "versus", "diff", "diff_ci95"]
START_HEADER = ["system", "policy", "episodes", "untrained", "seeds", "trained", "trained_ci95"]
START_HEADER += ["paired_diff", "paired_ci95", "seeds_diff", "seeds_ci95", "met"]
EVALUATION_BLOCKS = ("eval", "baseline_greedy")  # what a re-evaluation replaces


@dataclass
class Policy:
    """One evaluated policy of one system: its runs' per-episode returns.

    Attributes:
        name: Display name (learner label, ``untrained``, ``[features]``).
        learner: Learner name (yaml stem).
        kind: ``"trained"``, ``"untrained"``, ``"rule"`` or ``"greedy"``.
        returns: One array of per-episode returns per run (training seed).
        means: Mean evaluation return of each run.
        note: Extra text (the best team_reserve setting).
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
        return np.mean(self.returns, axis=0) if len({len(r) for r in self.returns}) == 1 else None

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
    """The run scored on its re-evaluation (``eval_metrics.json``) if it has one."""
    path = Path(run.run_dir) / EVAL_METRICS_FILE
    if not path.is_file():
        return run
    again = read_json(path)
    missing = [k for k in EVALUATION_BLOCKS if not isinstance(again, dict) or k not in again]
    if missing:
        raise ValueError(f"{path}: not a re-evaluation of scripts/evaluate.py, no {missing}")
    return dataclasses.replace(
        run, metrics={**run.metrics, **{k: again[k] for k in EVALUATION_BLOCKS}}
    )


def _kind(run: RunRecord) -> str:
    """``"rule"`` (a fixed policy: no learning space), ``"untrained"`` or ``"trained"``."""
    if not run.metrics.get("learning_space"):
        return "rule"
    return "trained" if (run.metrics.get("train") or {}).get("episodes", 0) > 0 else "untrained"


def _features(run: RunRecord) -> str:
    return str((run.config.get("learner") or {}).get("features", "paper"))


def _check_same_streams(runs: Sequence[RunRecord], greedy: dict[str, RunRecord]) -> None:
    """Refuse runs of as many episodes as the reference greedy but other task streams.

    Every run also plays greedy (deterministic) on its evaluation episodes, so two runs were
    evaluated on the same task streams exactly when their greedy returns agree episode by
    episode; pairing runs on other streams (another ``eval.seed`` or ``eval.batch_size``) would
    be silently wrong.
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


def _variant(run: RunRecord, kind: str, trained_variant: str) -> str:
    """What makes a policy of a run: a rule's setting, or the encoding and other settings."""
    if kind == "rule":
        cfg = run.config.get("learner") or {}
        keys = RESERVE_KEYS if run.name == "team_reserve" else ()
        return ", ".join(f"{k}={cfg[k]}" for k in keys if k in cfg)
    if kind == "untrained":
        return _features(run)
    # eval.* settings do not make a policy: each run is scored on its (re-)evaluation
    rest = [t for t in trained_variant.split() if not t.startswith(("features=", "eval."))]
    features = _features(run)
    return " ".join([features] * (features != "paper") + rest) or "paper"


def collect_policies(runs: Sequence[RunRecord]) -> dict[str, list[Policy]]:
    """Group the runs into policies per system (module docstring); ``{}`` if nothing to compare.

    The section applies when the runs hold a yardstick rule or an untrained learner.
    """
    if not any(r.name in RULES or _kind(r) == "untrained" for r in runs):
        return {}
    runs = [with_reevaluation(r) for r in runs]
    # trained configurations are told apart among the trained runs only: the settings in which
    # an untrained run differs (train.episodes, learning rates...) do not change its policy
    trained = [r for r in runs if _kind(r) == "trained"]
    plain = [dataclasses.replace(r, learner=r.name) for r in trained]
    variants = dict(zip(map(id, trained), configuration_variants(plain), strict=True))
    groups: dict[tuple[str, str, str, str], list[RunRecord]] = defaultdict(list)
    greedy: dict[str, RunRecord] = {}
    for run in runs:  # greedy of the run with the most evaluation episodes (the first on ties)
        known = greedy.get(run.system)
        if known is None or len(_per_episode(run.metrics["baseline_greedy"])) > len(
            _per_episode(known.metrics["baseline_greedy"])
        ):
            greedy[run.system] = run
        if run.name != GREEDY:
            kind = _kind(run)
            variant = _variant(run, kind, variants.get(id(run), ""))
            groups[(run.system, run.name, kind, variant)].append(run)
    _check_same_streams(runs, greedy)
    out: dict[str, list[Policy]] = {}
    for system, base in greedy.items():
        block = base.metrics["baseline_greedy"]
        means = [block["team_return"]["mean"]]
        policies = [Policy(GREEDY, GREEDY, "greedy", [_per_episode(block)], means)]
        reserve = [
            (v, m) for (s, n, _, v), m in groups.items() if s == system and n == "team_reserve"
        ]
        if reserve:
            variant, members = max(reserve, key=lambda vm: np.mean([_mean(r) for r in vm[1]]))
            policies.append(_policy(BEST_RESERVE, "rule", members, variant))
        for (s, learner, kind, variant), members in sorted(groups.items(), key=_order):
            if s != system or learner == "team_reserve":
                continue
            name = members[0].label
            if kind != "rule":
                name += " untrained" if kind == "untrained" else ""
                name += f" [{variant}]" if variant != "paper" else ""
            features = _features(members[0]) if kind != "rule" else "paper"
            policies.append(_policy(name, kind, members, features=features))
        out[system] = policies
    return out


def _order(item: tuple[tuple[str, str, str, str], list[RunRecord]]) -> tuple:
    (system, learner, kind, variant), _ = item
    rank = {"rule": 0, "untrained": 1, "trained": 2}[kind]
    return (system, rank == 0 and learner != "rollout", learner, variant, rank)


def _mean(run: RunRecord) -> float:
    return float(run.metrics["eval"]["team_return"]["mean"])


def _policy(
    name: str, kind: str, runs: list[RunRecord], note: str = "", features="paper"
) -> Policy:
    returns = [_per_episode(r.metrics["eval"]) for r in runs]
    return Policy(name, runs[0].name, kind, returns, [_mean(r) for r in runs], note, features)


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


def _round(value: float) -> float | str:
    return "" if math.isnan(value) else round(value, 3)


def section_rows(by_system: dict[str, list[Policy]]) -> list[list[Any]]:
    """CSV rows (:data:`CSV_HEADER`): each policy against its start and every yardstick."""
    rows = []
    for system, policies in by_system.items():
        for p in policies:
            stat, start = p.over_seeds, _starting(p, policies)
            for other in [*([start] if start else []), *_yardsticks(policies)]:
                if other is not p:
                    diff = paired_difference(p.per_episode, other.per_episode)
                    rows.append(
                        [system, p.name, stat.n, round(stat.mean, 3), _round(stat.ci95)]
                        + [other.name, _round(diff.mean), _round(diff.ci95)]
                    )
    return rows


@dataclass(frozen=True)
class StartComparison:
    """A trained policy against its untrained start.

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
        return "over seeds only" if self.over_seeds.low > 0 else "no"


def start_comparisons(by_system: dict[str, list[Policy]]) -> list[tuple[str, StartComparison]]:
    """``(system, comparison)`` for every trained policy that has an untrained start."""
    out = []
    for system, policies in by_system.items():
        for p in policies:
            if (start := _starting(p, policies)) is not None:
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
            [system, c.trained.name, c.episodes, round(float(np.mean(c.start.means)), 3)]
            + [trained.n, round(trained.mean, 3), _round(trained.ci95)]
            + [_round(v) for v in (c.paired.mean, c.paired.ci95)]
            + [_round(v) for v in (c.over_seeds.mean, c.over_seeds.ci95)]
            + [c.verdict]
        )
    return rows


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
            versus = [
                "" if s is p else _fmt(paired_difference(p.per_episode, s.per_episode))
                for s in sticks
            ]
            start_text = _fmt(paired_difference(p.per_episode, start.per_episode)) if start else ""
            name = p.name + (f" ({p.note})" if p.note else "")
            rows.append([name, len(p.means), p.over_seeds.format(1), start_text, *versus])
        md += [f"### {system_label(system)}", "", markdown_table(header, rows), ""]
    if figure is not None:
        md += [f"![{TITLE}]({figure.name})", ""]
    comparisons = start_comparisons(by_system)
    if comparisons:
        header = ["learner", "system", "untrained", "trained (seeds)"]
        header += ["trained − untrained, paired over episodes", "over seeds", "met?"]
        rows = [
            [
                c.trained.name,
                system_label(system),
                f"{np.mean(c.start.means):.1f}",
                f"{c.trained.over_seeds.format(1)} ({len(c.trained.means)})",
                f"{_fmt(c.paired)} ({c.episodes})" if c.episodes else "–",
                signed(c.over_seeds),
                c.verdict,
            ]
            for system, c in comparisons
        ]
        md += [
            "### Does training beat its own start?",
            "",
            "Trained − untrained: paired over the evaluation episodes (their number in "
            "parentheses), and over the training seeds (each seed's mean return minus the "
            "untrained return); met: the paired interval is above zero.",
            "",
            markdown_table(header, rows),
            "",
        ]
    if start_plot is not None:
        md += [f"![Does training beat its own start?]({start_plot.name})", ""]
    return "\n".join(md)


def write_section(runs: Sequence[RunRecord], out_dir: Path) -> tuple[str, dict[str, Path]]:
    """The section's markdown (``""`` if nothing to compare) and its CSV and PNG files."""
    by_system = collect_policies(runs)
    if not by_system:
        return "", {}
    files = {
        "yardsticks": write_csv(
            out_dir / "yardsticks.csv", pd.DataFrame(section_rows(by_system), columns=CSV_HEADER)
        ),
        "yardsticks_start": write_csv(
            out_dir / "yardsticks_start.csv",
            pd.DataFrame(start_rows(by_system), columns=START_HEADER),
        ),
    }
    panels = []
    for system, policies in by_system.items():
        ref = next((p for p in policies if p.name == BEST_RESERVE), policies[0])
        diffs = [
            (p.name, paired_difference(p.per_episode, ref.per_episode))
            for p in policies
            if p is not ref
        ]
        if diffs := [(n, d) for n, d in diffs if d.n]:
            title = f"{system_label(system)}: {ref.name} = {ref.over_seeds.mean:.1f}"
            xlabel = f"paired difference to {ref.name}\n(team return per episode)"
            panels.append((title, xlabel, diffs))
    figure = out_dir / "yardsticks.png" if panels else None
    if figure is not None:
        files["yardsticks_png"] = figures.difference_bars(panels, figure)
    starts = [
        (f"{c.trained.name}, {system_label(s)}", c.paired)
        for s, c in start_comparisons(by_system)
        if c.episodes
    ]
    start = out_dir / "yardsticks_start.png" if starts else None
    if start is not None:
        title = "Does training beat its own start? (95 % t intervals)"
        xlabel = "trained − untrained, paired over the evaluation episodes\n(team return)"
        files["yardsticks_start_png"] = figures.difference_bars([(title, xlabel, starts)], start)
    return section_markdown(by_system, figure, start), files

"""The experiments' own sections of report.md: studies along a swept setting, and yardsticks.

A study scores a run as ``(R - G) / |G|``, its gain over greedy on the same task streams (a
ratio ``R / G`` flips where greedy's return is negative); a *task*, the bootstrap's stratum, is
one team under one setting. Yardstick differences are paired per evaluation episode, as seeds
are few.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from collections import defaultdict
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from mrta_rl.config import UserError
from mrta_rl.reports import collect, figures, stats
from mrta_rl.reports.claims import FAILS, HOLDS, NOT_EVALUABLE, check_claims
from mrta_rl.reports.collect import RunRecord, config_value
from mrta_rl.reports.frame import band, long_table, order_learners, summarize, system_label
from mrta_rl.reports.stats import BOOTSTRAP_REPS, MeanCI, mean_ci
from mrta_rl.reports.study import Axis, Prose, Study, paragraphs
from mrta_rl.reports.tables import markdown_table, signed, write_csv
from mrta_rl.run_layout import CONFIG_FILE, EVAL_METRICS_FILE, read_json

BOUND_KEY = "partition.max_group_size"
TEAM_SEED_KEY = "system.seed"
# learning space columns of the study drawn as lines, with the suffix of their series
SPACE_LINES = {"space_analytic": "", "space_visited": " (visited)", "parameters": " (parameters)"}
PROFILE_POINTS = 101  # thresholds of a performance profile
# study.csv: the columns before the swept settings, then those after them
STUDY_KEYS = ["series", "learner", "system"]
STUDY_VALUES = ["team_seed", "seed", "return_vs_greedy", "team_return", "space_analytic"]
STUDY_VALUES += ["space_visited", "parameters", "wall_s", "peak_rss_mb", "refused"]
# a run's evaluation and greedy's on the same streams: what a re-evaluation replaces
EVALUATION_BLOCKS = ("eval", "baseline_greedy")
FIELD_STATS_HEADER = ["statistic", "x", "y", "value", "ci_low", "ci_high", "n_runs"]


def _series(label: str, variant: str) -> str:
    """A study line: the learner's label and the learner settings that set its runs apart.

    ``variant`` (``collect.configuration_variants``) also names the swept system keys
    (``system.n_robots=200``): those are the x axis, not the line, and keep their dotted names.
    """
    settings = [token for token in variant.split() if "." not in token.partition("=")[0]]
    return " ".join([label, *settings])


def _point(cell: tuple, config: dict, metrics: dict, refused: str, along: Iterable[str]) -> dict:
    """One study row: ``cell`` is ``(series, learner, system, seed)``, ``along`` the swept keys."""
    label, learner, system, seed = cell
    ret, greedy = (
        ((metrics.get(k) or {}).get("team_return") or {}).get("mean") for k in EVALUATION_BLOCKS
    )
    greedy = None if greedy is None else float(greedy)
    score = (float(ret) - greedy) / abs(greedy) if ret is not None and greedy else math.nan
    resources = metrics.get("resources") or {}
    wall = resources.get("wall_s", (metrics.get("train") or {}).get("wall_s"))
    space = {k: int(v) for k, v in (metrics.get("learning_space") or {}).items()}
    bound = config_value(config, BOUND_KEY)
    settings = {k: config_value(config, k) for k in along}
    random_team = "n_robots" in (config.get("system") or {})
    team_seed = config_value(config, TEAM_SEED_KEY) if random_team else None
    return {
        "series": label + (f" (g={bound})" if bound is not None else ""),
        "learner": learner,
        "system": system,
        **settings,
        "team_seed": team_seed,
        "seed": seed,
        "return_vs_greedy": score,
        "team_return": math.nan if ret is None else float(ret),
        "space_analytic": str(space["analytic"]) if "analytic" in space else "",
        "space_visited": space.get("visited", ""),
        "parameters": space.get("parameters", ""),
        "wall_s": math.nan if wall is None else float(wall),
        "peak_rss_mb": float(resources.get("peak_rss_mb", math.nan)),
        "refused": refused,
        "task": (system, tuple(sorted(settings.items())), team_seed),  # the bootstrap stratum
    }


def study_points(runs: Sequence[RunRecord], inputs: Sequence[Path], study: Study) -> pd.DataFrame:
    """Every finished run and every refused run below the inputs, one row each.

    Each row has the study's swept settings (``study.along``), and the ``rank`` of its learner.
    """
    points = []
    for r in runs:
        cell = (_series(r.label, r.variant), r.name, r.system, r.seed)
        points.append(_point(cell, r.config, r.metrics, "", study.along))
    for run_dir in sorted(f.parent for f in collect.found_files(inputs, collect.REFUSED_FILE)):
        if (run_dir / collect.METRICS_FILE).is_file():
            continue
        record = read_json(run_dir / collect.REFUSED_FILE)
        path = run_dir / CONFIG_FILE
        config = collect.read_yaml_config(path) or {}
        learner, system = str(record.get("learner", "?")), str(record.get("system", "?"))
        cell = (learner, learner, system, int(record.get("seed", config.get("seed", 0))))
        points.append(_point(cell, config, {}, collect.refusal_reason(run_dir) or "", study.along))
    # objects, not floats: the CSV keeps ints as ints and an absent setting empty
    columns = [*STUDY_KEYS, *study.along, *STUDY_VALUES, "task"]
    points = pd.DataFrame(points, columns=columns, dtype=object)
    learners = order_learners(points["learner"], study.learners)
    return points.assign(rank=[learners.index(n) for n in points["learner"]])


def swept_dimensions(points: pd.DataFrame, study: Study) -> list[str]:
    """The study's swept settings that take at least two values among the points."""
    return [k for k in study.along if points[k].dropna().nunique() >= 2]


def order_series(points: pd.DataFrame) -> list[str]:
    """Series in the study's learner order, bounds after the unbounded learner."""
    rank = points.groupby("series")["rank"].min()
    return sorted(rank.index, key=lambda s: (rank[s], s))


def _line(points: pd.DataFrame, dim: str, column: str) -> pd.DataFrame | None:
    """Mean and 95 % interval of ``column`` per value of ``dim`` (None without any value)."""
    cells = [(float(x), mean_ci(g[column])) for x, g in points.dropna(subset=[dim]).groupby(dim)]
    kept = [(x, s) for x, s in cells if s.n]
    return band([x for x, _ in kept], [s for _, s in kept]) if kept else None


def dimension_table(points: pd.DataFrame, dim: str, axis: Axis, system: str) -> str:
    """Markdown: series x values of ``dim``, cells ``score mean ± CI`` or ``refused: reason``."""
    mine = points[points["system"] == system]
    xs = sorted(mine[dim].dropna().unique())
    rows = []
    for series in order_series(mine):
        row = [series]
        for x in xs:
            cell = mine[(mine["series"] == series) & (mine[dim] == x)]
            refused = sorted(set(cell["refused"]) - {""})
            finished = cell[cell["refused"] == ""]["return_vs_greedy"]
            text = mean_ci(finished).format(3) if len(finished) else refused[0] if refused else "–"
            if len(finished) and refused:
                text += f" ({len(refused)} {refused[0]})"
            row.append(text)
        rows.append(row)
    return markdown_table([f"learner \\ {axis.label}", *map(str, xs)], rows)


def dimension_figures(
    points: pd.DataFrame, dim: str, axis: Axis, out: Path, colors: dict
) -> dict[str, Path]:
    """The figures of one swept dimension (see module docstring), by file stem."""
    label, stem, log_x = axis.label, axis.stem, axis.log_x
    finished = points[points["refused"] == ""].copy()
    series = order_series(finished)

    def panel(rows: pd.DataFrame, column: str, suffix: str = "") -> dict[str, pd.DataFrame]:
        lines = {s + suffix: _line(rows[rows["series"] == s], dim, column) for s in series}
        return {s: line for s, line in lines.items() if line is not None}

    returns = [
        figures.Panel(
            f"{system_label(system)}: team return relative to greedy",
            panel(finished[finished["system"] == system], "return_vs_greedy"),
            label,
            "(R - greedy) / |greedy| (mean, 95% CI)",
            log_x=log_x,
            hline=(0.0, "greedy"),
        )
        for system in dict.fromkeys(finished["system"])
    ]
    written = {f"{stem}_return": figures.line_figure(returns, out / f"{stem}_return.png", colors)}
    if not axis.costs:
        return written
    space = {}
    for column, suffix in SPACE_LINES.items():
        finished[f"log_{column}"] = [
            math.log10(int(v)) if v != "" and int(v) > 0 else math.nan for v in finished[column]
        ]
        space |= panel(finished, f"log_{column}", suffix)
    title = "learning space: analytic dimension, entries visited, network parameters"
    written[f"{stem}_space"] = figures.line_figure(
        [figures.Panel(title, space, label, "log10 of the size", log_x=log_x)],
        out / f"{stem}_space.png",
        colors,
    )
    costs = [
        figures.Panel(title, panel(finished, key), label, unit, log_x=log_x, log_y=True)
        for title, key, unit in (
            ("wall time per run", "wall_s", "seconds"),
            ("peak memory per run", "peak_rss_mb", "peak RSS (MiB)"),
        )
    ]
    written[f"{stem}_cost"] = figures.line_figure(costs, out / f"{stem}_cost.png", colors)
    return written


def dimension_claims(runs: Sequence[RunRecord], dim: str, study: Study) -> str:
    """Markdown: per claim and system, the values of ``dim`` where it holds (paper runs only)."""
    by_value: dict[Any, list[RunRecord]] = {}
    for run in runs:
        value = config_value(run.config, dim)
        if value is not None and config_value(run.config, BOUND_KEY) is None:
            plain = dataclasses.replace(run, learner=run.name, variant="")
            by_value.setdefault(value, []).append(plain)
    where: dict[tuple[str, str], dict[str, list[Any]]] = {}  # (claim, system) -> verdict -> values
    for value in sorted(by_value):
        summary = summarize(long_table(by_value[value]), study.learners)
        for r in check_claims(summary, study):
            where.setdefault((r.claim, r.system), {}).setdefault(r.verdict, []).append(value)
    rows = [
        [claim, system_label(system)]
        + [", ".join(map(str, found.get(v, []))) or "none" for v in (HOLDS, FAILS, NOT_EVALUABLE)]
        for (claim, system), found in where.items()
    ]
    header = ["claim", "system", f"holds at {study.along[dim].label}", "does not hold at"]
    return markdown_table([*header, "not evaluable at"], rows)


def _scores(points: pd.DataFrame, series: str) -> pd.Series:
    """The scores of the finished runs of a series by task (the bootstrap's strata)."""
    mine = points[(points["series"] == series) & (points["refused"] == "")]
    mine = mine[mine["return_vs_greedy"].notna()]
    return mine.groupby("task", sort=False)["return_vs_greedy"].agg(list)


def field_statistics(points: pd.DataFrame) -> pd.DataFrame:
    """IQM per series, then P(X > Y) per ordered pair of series over the tasks both ran."""
    names = order_series(points[points["refused"] == ""])
    by_series = {s: _scores(points, s) for s in names}
    rows = [("iqm", s, "", stats.iqm_ci(by_series[s].tolist())) for s in names]
    for x, y in itertools.permutations(names, 2):
        common = [t for t in by_series[x].index if t in by_series[y].index]
        xs, ys = ([by_series[s][t] for t in common] for s in (x, y))
        rows.append(("probability_of_improvement", x, y, stats.probability_of_improvement(xs, ys)))
    return pd.DataFrame(
        [(k, x, y, e.value, e.low, e.high, e.n, e) for k, x, y, e in rows],
        columns=[*FIELD_STATS_HEADER, "estimate"],
    )


def field_statistics_markdown(field: pd.DataFrame, points: pd.DataFrame, prose: Prose) -> str:
    """The IQM table and the probability-of-improvement matrix."""
    iqm = field[field["statistic"] == "iqm"]
    finished = points[points["refused"] == ""]
    rows = [
        [s, finished[finished["series"] == s]["task"].nunique(), e.n, e.format(3)]
        for s, e in zip(iqm["x"], iqm["estimate"], strict=True)
    ]
    header = ["learner", "tasks", "runs", "IQM of (R - greedy) / |greedy| [95% CI]"]
    md = paragraphs(markdown_table(header, rows))
    names = list(iqm["x"])
    if len(names) >= 2:
        pairs = field[field["statistic"] != "iqm"].set_index(["x", "y"])["estimate"]
        matrix = [[x, *("–" if x == y else pairs[x, y].format(2) for y in names)] for x in names]
        table = markdown_table(["P(row > column)", *names], matrix)
        md += prose.section("improvement", table=table)
    return "\n".join(md)


def profile_figure(points: pd.DataFrame, path: Path, colors: dict) -> Path | None:
    """Performance profiles of every series (None if no finished run has a score)."""
    scored = points[(points["refused"] == "") & points["return_vs_greedy"].notna()]
    if scored.empty:
        return None
    low, high = scored["return_vs_greedy"].min(), scored["return_vs_greedy"].max()
    tau = np.linspace(low - 0.01, high + 0.01, PROFILE_POINTS)
    lines = {}
    for s in order_series(scored):
        p = stats.performance_profile(_scores(points, s), tau)
        lines[s] = pd.DataFrame({"x": p.tau, "mean": p.fraction, "low": p.low, "high": p.high})
    panel = figures.Panel(
        "Performance profiles (95% stratified bootstrap bands)",
        lines,
        "team return relative to greedy's, (R - G) / |G| (tau)",
        "fraction of runs with score > tau",
        vline=(0.0, "greedy's return"),
        ylim=(-0.02, 1.02),
    )
    return figures.line_figure([panel], path, colors, size=(7.5, 4.6))


def study_sections(
    runs: Sequence[RunRecord], inputs: Sequence[Path], out: Path, study: Study, prose: Prose
) -> tuple[str, dict[str, Path]]:
    """The field-statistics section and one section per swept dimension, with files."""
    points = study_points(runs, inputs, study)
    colors = figures.learner_colors(order_series(points))
    colors |= {f"{n} ({k})": c for n, c in list(colors.items()) for k in ("visited", "parameters")}
    field = field_statistics(points)
    files = {"field_stats": write_csv(out / "field_stats.csv", field[FIELD_STATS_HEADER])}
    profile = profile_figure(points, out / "performance_profile.png", colors)
    if profile is not None:
        files["performance_profile"] = profile
    md = prose.section("field", reps=BOOTSTRAP_REPS)
    md += [field_statistics_markdown(field, points, prose)]
    md += [prose.image(profile, "Performance profiles"), ""]
    dims = swept_dimensions(points, study)
    if dims:
        columns = [*STUDY_KEYS, *study.along, *STUDY_VALUES]
        files["study"] = write_csv(out / "study.csv", points[columns])
    for dim in dims:
        axis = study.along[dim]
        written = dimension_figures(points, dim, axis, out, colors)
        files.update(written)
        md += prose.section("along", label=axis.label, key=dim)
        for system in dict.fromkeys(points["system"]):
            md += paragraphs(f"{system_label(system)}:", dimension_table(points, dim, axis, system))
        alt = f"Team return against the {axis.label}"
        md += paragraphs(prose.image(written.get(f"{axis.stem}_return"), alt))
        if axis.costs:
            images = {
                key: prose.image(written[f"{axis.stem}_{key}"], f"{what} against the {axis.label}")
                for key, what in (("space", "Learning space"), ("cost", "Wall time and memory"))
            }
            md += prose.section("along_costs", **images)
        md += prose.section("along_claims", key=dim, table=dimension_claims(runs, dim, study))
    return "\n".join(md), files


# ---------------------------------------------------------------- learning against the rules

GREEDY = "greedy"
CSV_HEADER = ["system", "policy", "seeds", "mean", "ci95_seeds", "versus", "diff", "diff_ci95"]
CSV_HEADER += ["decision_ms_per_tick"]  # a planner's decision time (eval.decision_time); else empty
START_HEADER = ["system", "policy", "episodes", "untrained", "seeds", "trained", "trained_ci95"]
START_HEADER += ["paired_diff", "paired_ci95", "seeds_diff", "seeds_ci95", "met"]


@dataclass
class Policy:
    """One evaluated policy of one system: its runs' per-episode returns."""

    name: str
    learner: str
    kind: str
    returns: list[np.ndarray]
    means: list[float]
    note: str = ""
    features: str = "paper"
    decision_ms: float | None = None  # mean decision time per tick over the runs that report it
    best: bool = False  # the trained runs of the study's best learner: a yardstick

    @property
    def per_episode(self) -> np.ndarray | None:
        """Per-episode returns averaged over the runs, or None if a run lacks them."""
        lengths = {len(r) for r in self.returns}
        return np.mean(self.returns, axis=0) if len(lengths) == 1 and 0 not in lengths else None

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
    blocks = {k: again[k] for k in EVALUATION_BLOCKS}
    return dataclasses.replace(run, metrics={**run.metrics, **blocks})


def _kind(run: RunRecord) -> str:
    """``"rule"`` (a fixed policy: no learning space), ``"untrained"`` or ``"trained"``."""
    if not run.metrics.get("learning_space"):
        return "rule"
    if run.config.get("init"):  # trained in another run (on a family, or on another team)
        return "trained"
    return "trained" if (run.metrics.get("train") or {}).get("episodes", 0) > 0 else "untrained"


def _features(run: RunRecord) -> str:
    return str((run.config.get("learner") or {}).get("features", "paper"))


def _check_same_streams(runs: Sequence[RunRecord], greedy: dict[str, RunRecord]) -> None:
    """Refuse runs of as many episodes as the reference greedy but other task streams.

    Greedy is deterministic: two runs played the same streams iff their greedy returns agree.
    """
    for run in runs:
        reference = greedy[run.system]
        ours = _per_episode(run.metrics["baseline_greedy"])
        theirs = _per_episode(reference.metrics["baseline_greedy"])
        if len(ours) == len(theirs) and not np.array_equal(ours, theirs, equal_nan=True):
            raise UserError(
                f"{run.run_dir} and {reference.run_dir} were evaluated on different task streams "
                f"({len(ours)} episodes each, but their greedy baselines differ): evaluate both "
                "with the same eval.split and eval.batch_size (scripts/evaluate.py episodes=N "
                "batch_size=N)"
            )


def _base_label(base: str) -> str:
    """The learner label of a planner's base run (its ``metrics.json``), else its dir's name."""
    path = Path(base) / collect.METRICS_FILE
    try:
        return str(read_json(path)["learner"]["label"])
    except (OSError, ValueError, KeyError, TypeError):
        return Path(base).name


def _variant(run: RunRecord, kind: str, trained_variant: str, study: Study) -> str:
    """What makes a policy of a run: a rule's setting, or the encoding and other settings.

    A rule of ``study.best_setting`` is a policy per setting. A planner whose base is a trained
    run (``learner.base=<run dir>``, a path) is another policy than with a rule base:
    ``base=<the base run's learner label>``, so the planners on the runs of several seeds of one
    learner form one policy.
    """
    if kind == "rule":
        cfg = run.config.get("learner") or {}
        base = str(cfg.get("base", ""))
        if "/" in base:
            moves = cfg.get("neighbours") or []  # candidates around the base's own action
            return f"base={_base_label(base)}" + (f", neighbours={','.join(moves)}" * bool(moves))
        keys = [k for k in cfg if not k.startswith("_")] if run.name in study.best_setting else []
        return ", ".join(f"{k}={cfg[k]}" for k in keys)
    if kind == "untrained":
        return _features(run)
    # eval.* settings do not make a policy: each run is scored on its (re-)evaluation
    rest = [t for t in trained_variant.split() if not t.startswith(("features=", "eval."))]
    init = collect.named_init(run.config).get("init")
    if init and f"init={init}" not in rest:  # the policy was trained on other teams
        rest.append(f"init={init}")
    features = _features(run)
    return " ".join([features] * (features != "paper") + rest) or "paper"


def team_of(run: RunRecord) -> str:
    """The team a run played: its system, and for a random team its size and team seed.

    Random teams share the system name ``random``; each (size, team seed) is a team of its own,
    with its own streams and its own best rule.
    """
    m, seed = config_value(run.config, "system.n_robots"), config_value(run.config, "system.seed")
    if m is None:
        return run.system
    return f"{run.system} ({m:,} robots, team seed {seed})"


def collect_policies(runs: Sequence[RunRecord], study: Study) -> dict[str, list[Policy]]:
    """Per team: greedy, the best setting of a rule, the learners (trained and untrained), rules.

    No team without a run of a yardstick rule (``study.rules``) or an untrained run. A policy
    holds one run per seed, the first given (the tables keep it, duplicates follow).
    """
    if not any(r.name in study.rules or _kind(r) == "untrained" for r in runs):
        return {}
    runs = [dataclasses.replace(with_reevaluation(r), system=team_of(r)) for r in runs]
    # trained configurations are told apart among the trained runs only: the settings in which
    # an untrained run differs (train.episodes, learning rates...) do not change its policy
    trained = [r for r in runs if _kind(r) == "trained"]
    plain = [dataclasses.replace(r, learner=r.name) for r in trained]
    variants = dict(zip(map(id, trained), collect.configuration_variants(plain), strict=True))
    groups: dict[tuple[str, str, str, str], list[RunRecord]] = defaultdict(list)
    greedy: dict[str, RunRecord] = {}
    episodes = {id(r): len(_per_episode(r.metrics["baseline_greedy"])) for r in runs}
    for run in runs:  # greedy of the run with the most evaluation episodes (the first on ties)
        if run.system not in greedy or episodes[id(run)] > episodes[id(greedy[run.system])]:
            greedy[run.system] = run
        if run.name != GREEDY:
            kind = _kind(run)
            variant = _variant(run, kind, variants.get(id(run), ""), study)
            members = groups[(run.system, run.name, kind, variant)]
            if run.seed not in {m.seed for m in members}:  # a seed counts once, as in the tables
                members.append(run)
    _check_same_streams(runs, greedy)

    def order(key: tuple[str, str, str, str]) -> tuple:
        system, learner, kind, variant = key  # the yardstick rules among the learners
        rank = {"rule": 0, "untrained": 1, "trained": 2}[kind]
        return (system, rank == 0 and learner not in study.rules, learner, variant, rank)

    out: dict[str, list[Policy]] = {}
    for system, base in greedy.items():
        block = base.metrics["baseline_greedy"]
        means = [block["team_return"]["mean"]]
        policies = [Policy(GREEDY, GREEDY, "greedy", [_per_episode(block)], means)]
        for rule in study.best_setting:
            settings = [(v, m) for (s, n, _, v), m in groups.items() if (s, n) == (system, rule)]
            if settings:
                variant, members = max(settings, key=lambda vm: np.mean([_mean(r) for r in vm[1]]))
                policies.append(_policy(f"{rule} (best)", "rule", members, note=variant))
        for s, learner, kind, variant in sorted(groups, key=order):
            if s != system or learner in study.best_setting:
                continue
            members = groups[s, learner, kind, variant]
            shown = variant.startswith("base=") if kind == "rule" else variant != "paper"
            name = members[0].label + " untrained" * (kind == "untrained") + f" [{variant}]" * shown
            features = _features(members[0]) if kind != "rule" else "paper"
            best = kind == "trained" and learner == study.best_learner
            policies.append(_policy(name, kind, members, features=features, best=best))
        out[system] = policies
    return out


def _mean(run: RunRecord) -> float:
    return float(run.metrics["eval"]["team_return"]["mean"])


def _policy(name: str, kind: str, runs: list[RunRecord], **extra: Any) -> Policy:
    """The policy of the runs (``extra``: more fields of :class:`Policy`)."""
    returns = [_per_episode(r.metrics["eval"]) for r in runs]
    times = [
        float(r.metrics["eval"]["decision_time"]["ms_per_tick"])
        for r in runs
        if "ms_per_tick" in (r.metrics["eval"].get("decision_time") or {})
    ]
    decision = float(np.mean(times)) if times else None
    means = [_mean(r) for r in runs]
    return Policy(name, runs[0].name, kind, returns, means, decision_ms=decision, **extra)


def _yardsticks(policies: list[Policy]) -> list[Policy]:
    """Greedy, the rules, and the trained runs of the study's best learner."""
    return [p for p in policies if p.kind in ("greedy", "rule")] + [p for p in policies if p.best]


def _starting(policy: Policy, policies: list[Policy]) -> Policy | None:
    """The untrained start of a trained policy (an untrained policy reads no extra features)."""
    starts = [p for p in policies if p.kind == "untrained" and p.learner == policy.learner]
    same = [p for p in starts if p.features == policy.features]
    return (same or starts or [None])[0] if policy.kind == "trained" else None


def _versus(p: Policy, policies: list[Policy]) -> list[tuple[Policy, MeanCI]]:
    """Paired differences of a policy to its untrained start, then to every other yardstick."""
    start = _starting(p, policies)
    others = [o for o in [*([start] if start else []), *_yardsticks(policies)] if o is not p]
    return [(o, paired_difference(p.per_episode, o.per_episode)) for o in others]


def _round(value: float | None) -> float | str:
    return "" if value is None or math.isnan(value) else round(value, 3)


def section_rows(by_system: dict[str, list[Policy]]) -> list[list[Any]]:
    """CSV rows (:data:`CSV_HEADER`): each policy against its start and every yardstick."""
    return [
        [system, p.name, p.over_seeds.n, *map(_round, (p.over_seeds.mean, p.over_seeds.ci95))]
        + [other.name, _round(diff.mean), _round(diff.ci95), _round(p.decision_ms)]
        for system, policies in by_system.items()
        for p in policies
        for other, diff in _versus(p, policies)
    ]


@dataclass(frozen=True)
class StartComparison:
    """A trained policy against its untrained start: paired over episodes, and over seeds.

    ``verdict``: ``yes`` (the paired interval is above zero), ``no (below)``, ``over seeds only``
    (the interval over seeds is above zero) or ``no``.
    """

    trained: Policy
    start: Policy
    paired: MeanCI  # n: the evaluation episodes paired (0 if unpaired)
    over_seeds: MeanCI
    verdict: str


def start_comparisons(by_system: dict[str, list[Policy]]) -> list[tuple[str, StartComparison]]:
    """``(system, comparison)`` for every trained policy that has an untrained start."""
    out = []
    for system, policies in by_system.items():
        for p in policies:
            if (start := _starting(p, policies)) is not None:
                untrained = float(np.mean(start.means))
                paired = paired_difference(p.per_episode, start.per_episode)
                seeds = mean_ci([m - untrained for m in p.means])
                verdict = "yes" if paired.low > 0 else "no (below)" if paired.high < 0 else "no"
                verdict = "over seeds only" if verdict == "no" and seeds.low > 0 else verdict
                out.append((system, StartComparison(p, start, paired, seeds, verdict)))
    return out


def start_rows(by_system: dict[str, list[Policy]]) -> list[list[Any]]:
    """CSV rows of :func:`start_comparisons` (:data:`START_HEADER`)."""
    return [
        [system, c.trained.name, c.paired.n, _round(float(np.mean(c.start.means)))]
        + [c.trained.over_seeds.n, _round(c.trained.over_seeds.mean)]
        + [_round(v) for v in (c.trained.over_seeds.ci95, c.paired.mean, c.paired.ci95)]
        + [_round(c.over_seeds.mean), _round(c.over_seeds.ci95), c.verdict]
        for system, c in start_comparisons(by_system)
    ]


def _fmt(diff: MeanCI) -> str:
    if diff.n == 0:
        return "–"
    mark = " **↑**" if diff.low > 0 else (" ↓" if diff.high < 0 else "")
    return f"{diff.mean:+.1f} ± {diff.ci95:.1f}{mark}"


def section_markdown(
    by_system: dict[str, list[Policy]],
    figure: Path | None,
    start_plot: Path | None,
    study: Study,
    prose: Prose,
) -> str:
    """The section's text: one table per system, its figure, the start table and its figure."""
    title, start_title = prose.text("rules_title"), prose.text("start_title")
    md = prose.section(
        "yardsticks",
        title=title,
        best_setting=", ".join(f"`{r}`" for r in study.best_setting),
        rules=", ".join(f"`{r}`" for r in study.rules if r not in study.best_setting),
        best_learner=f"`{study.best_learner}`",
    )
    for system, policies in by_system.items():
        sticks = _yardsticks(policies)
        header = ["policy", "seeds", "return", "vs untrained", *(f"vs {s.name}" for s in sticks)]
        timed = any(p.decision_ms is not None for p in policies)
        header += ["ms per tick"] * timed
        rows = []
        for p in policies:
            diffs = {id(o): _fmt(d) for o, d in _versus(p, policies)}
            start = diffs.get(id(_starting(p, policies)), "")
            name = p.name + (f" ({p.note})" if p.note else "")
            row = [name, len(p.means), p.over_seeds.format(1), start]
            row += [diffs.get(id(s), "") for s in sticks]
            ms = "" if p.decision_ms is None else f"{p.decision_ms:.1f}"
            rows.append(row + [ms] * timed)
        table = markdown_table(header, rows)
        md += prose.section("yardsticks_system", system=system_label(system), table=table)
    md += paragraphs(f"![{title}]({figure.name})" if figure else "")
    comparisons = start_comparisons(by_system)
    if comparisons:
        header = ["learner", "system", "untrained", "trained (seeds)"]
        header += ["trained − untrained, paired over episodes", "over seeds", "met?"]
        rows = [
            [c.trained.name, system_label(system), f"{np.mean(c.start.means):.1f}"]
            + [f"{c.trained.over_seeds.format(1)} ({len(c.trained.means)})"]
            + [f"{_fmt(c.paired)} ({c.paired.n})" if c.paired.n else "–"]
            + [signed(c.over_seeds), c.verdict]
            for system, c in comparisons
        ]
        table = markdown_table(header, rows)
        md += prose.section("yardsticks_start", title=start_title, table=table)
    md += paragraphs(f"![{start_title}]({start_plot.name})" if start_plot else "")
    return "\n".join(md)


def write_section(
    runs: Sequence[RunRecord], out_dir: Path, study: Study, prose: Prose
) -> tuple[str, dict[str, Path]]:
    """The section's markdown (``""`` if nothing to compare) and its CSV and PNG files."""
    by_system = collect_policies(runs, study)
    if not by_system:
        return "", {}
    files = {
        stem: write_csv(out_dir / f"{stem}.csv", pd.DataFrame(rows(by_system), columns=header))
        for stem, rows, header in (
            ("yardsticks", section_rows, CSV_HEADER),
            ("yardsticks_start", start_rows, START_HEADER),
        )
    }
    panels, best = [], {f"{rule} (best)" for rule in study.best_setting}
    for system, policies in by_system.items():
        ref = next((p for p in policies if p.name in best), policies[0])
        others = [p for p in policies if p is not ref]
        diffs = [(p.name, paired_difference(p.per_episode, ref.per_episode)) for p in others]
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
        if c.paired.n
    ]
    start = out_dir / "yardsticks_start.png" if starts else None
    if start is not None:
        title = f"{prose.text('start_title')} (95 % t intervals)"
        xlabel = "trained − untrained, paired over the evaluation episodes\n(team return)"
        files["yardsticks_start_png"] = figures.difference_bars([(title, xlabel, starts)], start)
    return section_markdown(by_system, figure, start, study, prose), files

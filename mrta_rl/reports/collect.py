"""Collect finished runs (metrics.json, curve.csv) and the jobs a sweep expected but lost.

Input: a Hydra multirun dir (``multirun.yaml`` at the top, one job dir per job) or run dirs of
``scripts/train.py`` (or folders holding them). A run is a folder with ``metrics.json``.

The *expected* grid of a multirun is rebuilt exactly as Hydra's ``BasicSweeper`` built its job
list: the ``hydra.sweeper.params`` of ``multirun.yaml`` followed by the command-line task
overrides (``hydra.overrides.task``), expanded as a cartesian product. A job whose dir has no
``metrics.json`` (it failed: Hydra runs the remaining jobs and reports the error at the end, and
``train()`` writes metrics.json last and atomically) or has no dir at all is *missing*. Without a
multirun.yaml the expected grid is the product of the learners, systems and seeds found, so a
hole in a hand-made set of runs is reported too.

Runs are told apart by their whole configuration, not only by learner, system and seed: among
the runs of one learner on one system, every setting of ``.hydra/config.yaml`` whose value differs
between them (the seed and the settings in :data:`NOT_CONFIGURATION` aside) makes a
configuration of its own, named by what differs (``subg_reserve reserve=1 hold_level=0``; learner
hyperparameters by their name, other settings by their dotted key). That name is the run's
``learner`` in the report, so each configuration is its own row; only the same configuration with
the same seed is a duplicate. Runs evaluated on different splits differ in ``eval.split``, so a
table never averages test and validation runs together.
"""

from __future__ import annotations

import copy
import csv
import dataclasses
import itertools
import json
import logging
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from mrta_rl.config import UserError, declared_keywords
from mrta_rl.run_files import METRICS_FILE, REFUSED_FILE, REFUSED_JOBS_FILE, read_metrics
from mrta_rl.splits import DEFAULT_SPLIT, SPLIT_SEEDS

logger = logging.getLogger(__name__)

CURVE_FILE = "curve.csv"
BASIC_SWEEPER = "hydra._internal.core_plugins.basic_sweeper.BasicSweeper"
# settings that do not change what a run computes: never part of a configuration's name
NOT_CONFIGURATION = ("seed", "resume", "train.progress_bar", "train.checkpoint_every")


class ReportInputError(UserError):
    """The report's inputs hold nothing to report, or do not exist."""


@dataclass(frozen=True)
class RunRecord:
    """One finished run.

    Attributes:
        run_dir: The run's folder.
        learner: Learner name (yaml stem), from metrics.json, followed by the settings that set
            its configuration apart from the other runs of that learner and system
            (``subg_reserve reserve=1 hold_level=0``, see the module docstring).
        system: System name (``system1``...), from metrics.json.
        seed: Run seed, from metrics.json.
        metrics: The whole metrics.json.
        curve: Training curve rows ``(env_ticks, team_return_mean)``; empty for fixed policies.
        config: The run's ``.hydra/config.yaml`` as a plain dict (``{}`` if absent).
        overrides: The job's ``.hydra/overrides.yaml`` (``()`` if absent).
        variant: What sets the configuration apart (``reserve=1 hold_level=0``), or ``""``.
    """

    run_dir: Path
    learner: str
    system: str
    seed: int
    metrics: dict[str, Any]
    curve: tuple[tuple[int, float], ...]
    config: dict[str, Any]
    overrides: tuple[str, ...]
    variant: str = ""

    @property
    def key(self) -> tuple[str, str, int]:
        """``(configuration, system, seed)``: one cell of the grid."""
        return (self.learner, self.system, self.seed)


@dataclass(frozen=True)
class MissingJob:
    """A job of the expected grid without metrics.json.

    Attributes:
        learner: Learner name of the job.
        system: System name of the job.
        seed: Seed of the job (None if not determinable).
        overrides: The job's overrides (empty for a hole in a hand-made set of runs).
        job_dir: The job's dir if it exists (a failed job), else None (never started).
        reason: Short human-readable cause.
    """

    learner: str
    system: str
    seed: int | None
    overrides: tuple[str, ...]
    job_dir: Path | None
    reason: str


@dataclass
class Collection:
    """Everything the report is built from.

    Attributes:
        inputs: The paths given.
        runs: Finished runs, one per ``(learner, system, seed)``.
        missing: Expected jobs without results.
        duplicates: Runs dropped because another run had the same ``(learner, system, seed)``.
        expected_jobs: Size of the expected grid.
        sweep_source: How the expected grid was found (``multirun.yaml`` path or ``"runs found"``).
    """

    inputs: list[Path]
    runs: list[RunRecord] = field(default_factory=list)
    missing: list[MissingJob] = field(default_factory=list)
    duplicates: list[RunRecord] = field(default_factory=list)
    expected_jobs: int = 0
    sweep_source: str = "runs found"


def read_curve(path: Path) -> tuple[tuple[int, float], ...]:
    """Rows ``(env_ticks, team_return_mean)`` of a curve.csv (``()`` if absent or header-only).

    Args:
        path: The curve.csv file (columns of ``mrta_rl.metrics.CURVE_COLUMNS``).

    Returns:
        The rows in file order.
    """
    if not path.is_file():
        return ()
    with path.open(newline="") as handle:
        return tuple(
            (int(float(row["env_ticks"])), float(row["team_return_mean"]))
            for row in csv.DictReader(handle)
            if row.get("env_ticks") not in (None, "")
        )


def _load_yaml(path: Path) -> Any:
    return OmegaConf.to_container(OmegaConf.load(path), resolve=False) if path.is_file() else None


# each learner's label as its runs recorded it (metrics.json ``learner.label``, the class's own)
RECORDED_LABELS: dict[str, str] = {}


def load_run(run_dir: Path) -> RunRecord:
    """Read one run dir.

    Args:
        run_dir: Folder holding metrics.json (and curve.csv, .hydra/ if written by Hydra).

    Returns:
        The record.

    Raises:
        RunDirError: if metrics.json is damaged (naming the file and key).
    """
    metrics = read_metrics(run_dir / METRICS_FILE)
    config = _load_yaml(run_dir / ".hydra" / "config.yaml") or {}
    overrides = _load_yaml(run_dir / ".hydra" / "overrides.yaml") or []
    RECORDED_LABELS[metrics["learner"]["name"]] = metrics["learner"]["label"]
    return RunRecord(
        run_dir=run_dir,
        learner=str(metrics["learner"]["name"]),
        system=str(metrics["system"]),
        seed=int(metrics["seed"]),
        metrics=metrics,
        curve=read_curve(run_dir / CURVE_FILE),
        config=config,
        overrides=tuple(str(o) for o in overrides),
    )


def _flatten(config: Any, prefix: str = "") -> dict[str, Any]:
    """``{"learner.reserve": 1, ...}``: the leaves of a nested config (lists as values)."""
    if not isinstance(config, dict):
        return {prefix: config}
    out: dict[str, Any] = {}
    for key, value in config.items():
        out.update(_flatten(value, f"{prefix}.{key}" if prefix else str(key)))
    return out


def _setting_name(key: str) -> str:
    """``learner.reserve`` -> ``reserve``; other settings keep their dotted key."""
    return key.removeprefix("learner.") if key.count(".") == 1 else key


def configuration_variants(records: Sequence[RunRecord]) -> list[str]:
    """What sets each run's configuration apart from the other runs of its learner and system.

    Args:
        records: Runs with their configs.

    Returns:
        Per run, ``"name=value ..."`` of the settings whose values differ among the runs of its
        ``(learner, system)`` (seed and :data:`NOT_CONFIGURATION` aside), in config order;
        ``""`` when nothing differs.
    """
    flat = [_flatten(named_streams(_as_ran(r.config))) for r in records]
    variants = [""] * len(records)
    groups: dict[tuple[str, str], list[int]] = {}
    for i, record in enumerate(records):
        groups.setdefault((record.learner, record.system), []).append(i)
    for members in groups.values():
        keys = list(dict.fromkeys(k for i in members for k in flat[i]))  # config order
        for i in members:  # a learner setting added after a run was made: its declared default
            missing = [k for k in keys if k not in flat[i] and k.startswith("learner.")]
            if missing:
                defaults = _declared_defaults(records[i].config)
                flat[i].update({k: defaults[k] for k in missing if k in defaults})
        differing = [
            k
            for k in keys
            if k not in NOT_CONFIGURATION
            and len({json.dumps(flat[i].get(k), sort_keys=True) for i in members}) > 1
        ]
        for i in members:
            variants[i] = " ".join(
                f"{_setting_name(k)}={_format_value(flat[i].get(k))}" for k in differing
            )
    return variants


def named_streams(config: dict[str, Any]) -> dict[str, Any]:
    """The config with its evaluation streams named by ``eval.split`` (``mrta_rl/splits.py``).

    A run written before ``eval.split`` existed played the test split and records its seed as
    ``eval.seed``; a later run records the split and ``eval.seed: null``. Both name the same
    streams, so runs of different splits differ in ``eval.split`` and only there.
    """
    evaluation = config.get("eval")
    if not isinstance(evaluation, dict) or not {"seed", "split"} & set(evaluation):
        return config  # no streams recorded (not written by scripts/train.py)
    split = evaluation.get("split") or DEFAULT_SPLIT
    named = {**evaluation, "split": split}
    if evaluation.get("seed") == SPLIT_SEEDS.get(split):
        named["seed"] = None
    return {**config, "eval": named}


def _as_ran(config: dict[str, Any]) -> dict[str, Any]:
    """A copy of a run's config, to fill with declared defaults without touching the record."""
    return copy.deepcopy(config)


def _declared_defaults(config: dict[str, Any]) -> dict[str, Any]:
    """``{"learner.<name>": default}`` of the run's learner class, ``{}`` if it is unknown.

    A run made before a learner setting existed has no such key in its ``.hydra/config.yaml``
    and ran with the setting's declared default, so it is compared with that default.
    """
    from mrta_rl.runners.validation import learner_class  # imports the learner (and its deps)

    try:
        cls = learner_class(config.get("learner"))
    except UserError:
        return {}
    return {
        f"learner.{name}": (list(d.default) if isinstance(d.default, tuple) else d.default)
        for name, d in declared_keywords(cls).items()
        if not d.required
    }


def _format_value(value: Any) -> str:
    if value is None:
        return "null"
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, list):
        return "[" + ",".join(_format_value(v) for v in value) + "]"
    return str(value)


def natural_key(text: str) -> tuple[Any, ...]:
    """Sort key that orders the numbers in ``text`` by value (``reserve=2`` before ``=10``)."""
    return tuple(
        (0, int(part), "") if part.isdigit() else (1, 0, part)
        for part in re.split(r"(\d+)", text)
        if part
    )


def refusal_reason(run_dir: Path) -> str | None:
    """``"refused: <reason>"`` if the run was refused up front (its ``refused.json``), else None."""
    path = run_dir / REFUSED_FILE
    if not path.is_file():
        return None
    try:
        reason = json.loads(path.read_text()).get("reason", "no reason given")
    except (json.JSONDecodeError, AttributeError):
        reason = f"unreadable {REFUSED_FILE}"
    return f"refused: {reason}"


def refused_jobs(sweep_dir: Path) -> dict[frozenset[str], str]:
    """``"refused: <reason>"`` of the sweep's jobs refused by validation, keyed by overrides.

    Such a job leaves no run dir (``runners/cli.py`` removes it); the sweep dir keeps its
    reason in ``refused_jobs.jsonl``. An unreadable line is skipped.
    """
    path = sweep_dir / REFUSED_JOBS_FILE
    out: dict[frozenset[str], str] = {}
    if not path.is_file():
        return out
    for line in path.read_text(errors="replace").splitlines():
        try:
            record = json.loads(line)
            out[frozenset(str(o) for o in record["overrides"])] = f"refused: {record['reason']}"
        except (ValueError, KeyError, TypeError):
            continue
    return out


def expected_sweep_jobs(multirun_yaml: Path) -> list[list[str]] | None:
    """The job list Hydra's BasicSweeper built for a multirun, in job-number order.

    Args:
        multirun_yaml: The sweep's ``multirun.yaml``.

    Returns:
        One override list per job, or None if the sweep was not run by the BasicSweeper (another
        sweeper plugin builds its jobs differently).
    """
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra.core.override_parser.overrides_parser import OverridesParser

    cfg = OmegaConf.load(multirun_yaml)
    sweeper = OmegaConf.select(cfg, "hydra.sweeper", default=None)
    if sweeper is None or sweeper.get("_target_") != BASIC_SWEEPER:
        return None
    params = sweeper.get("params") or {}
    # same order as BasicSweeper.sweep: sweeper params, then the command line (which wins)
    arguments = [f"{k}={v}" for k, v in params.items()]
    arguments += [str(o) for o in OmegaConf.select(cfg, "hydra.overrides.task", default=[])]
    parsed = OverridesParser.create().parse_overrides(arguments)
    return [list(job) for batch in BasicSweeper.split_arguments(parsed, None) for job in batch]


def _override_value(overrides: Sequence[str], key: str) -> str | None:
    """Value of ``key=value`` (also ``+key=``/``++key=``) in an override list."""
    for item in overrides:
        name, _, value = item.partition("=")
        if name.lstrip("+") == key:
            return value
    return None


def _job_identity(job: Sequence[str], cfg: Any) -> tuple[str, str, int | None]:
    """``(learner, system, seed)`` of an expected job: its overrides, else the sweep defaults."""
    choices = OmegaConf.select(cfg, "hydra.runtime.choices", default={}) or {}
    learner = _override_value(job, "learner") or str(choices.get("learner", "?"))
    system = _override_value(job, "system") or str(choices.get("system", "?"))
    seed_text = _override_value(job, "seed")
    seed_text = seed_text if seed_text is not None else str(cfg.get("seed", ""))
    try:
        seed: int | None = int(seed_text)
    except ValueError:
        seed = None
    return learner, system, seed


def _find_run_dirs(path: Path) -> list[Path]:
    """Folders holding a metrics.json at or below ``path``, sorted."""
    if (path / METRICS_FILE).is_file():
        return [path]
    return sorted(p.parent for p in path.rglob(METRICS_FILE))


def _job_dirs(sweep_dir: Path) -> dict[frozenset[str], Path]:
    """Job dirs of a sweep (any ``.hydra/overrides.yaml`` below it), keyed by their overrides."""
    found: dict[frozenset[str], Path] = {}
    for path in sorted(sweep_dir.rglob("overrides.yaml")):
        if path.parent.name == ".hydra":
            found[frozenset(str(o) for o in _load_yaml(path) or [])] = path.parent.parent
    return found


def collect_runs(inputs: Iterable[Path | str]) -> Collection:
    """Gather the runs below the inputs and list the expected jobs that left no results.

    Args:
        inputs: Multirun dirs, run dirs, or folders holding run dirs.

    Returns:
        The collection (runs sorted by learner, system, seed).

    Raises:
        ReportInputError: if an input does not exist.
    """
    paths = [Path(p) for p in inputs]
    for path in paths:
        if not path.exists():
            raise ReportInputError(f"no such run or sweep dir: {path}")
    collection = Collection(inputs=paths)
    by_key: dict[tuple[str, str, int], RunRecord] = {}
    records = [load_run(d) for d in sorted({d.resolve() for p in paths for d in _find_run_dirs(p)})]
    variants = configuration_variants(records)
    for record, variant in zip(records, variants, strict=True):
        if variant:
            record = dataclasses.replace(
                record, learner=f"{record.learner} {variant}", variant=variant
            )
        run_dir = record.run_dir
        if record.key in by_key:  # e.g. a run repeated by hand; seeds must count once
            logger.warning(
                "%s repeats %s; keeping %s", run_dir, record.key, by_key[record.key].run_dir
            )
            collection.duplicates.append(record)
            continue
        by_key[record.key] = record
    collection.runs = sorted(by_key.values(), key=lambda r: (natural_key(r.learner), *r.key[1:]))

    sweeps = [p / "multirun.yaml" for p in paths if (p / "multirun.yaml").is_file()]
    expected_found = False
    for multirun_yaml in sweeps:
        jobs = expected_sweep_jobs(multirun_yaml)
        if jobs is None:
            logger.warning(
                "%s: not a BasicSweeper sweep, expected grid taken from the runs", multirun_yaml
            )
            continue
        expected_found = True
        collection.sweep_source = ", ".join(str(s) for s in sweeps)
        collection.expected_jobs += len(jobs)
        cfg = OmegaConf.load(multirun_yaml)
        dirs = _job_dirs(multirun_yaml.parent)
        refused = refused_jobs(multirun_yaml.parent)
        for job in jobs:
            job_dir = dirs.get(frozenset(job))
            if job_dir is not None and (job_dir / METRICS_FILE).is_file():
                continue
            learner, system, seed = _job_identity(job, cfg)
            reason = (
                refused.get(frozenset(job), "never started (no job dir)")
                if job_dir is None
                else refusal_reason(job_dir)
                or "failed or unfinished: no metrics.json (see train.log, sweep output)"
            )
            collection.missing.append(
                MissingJob(learner, system, seed, tuple(job), job_dir, reason)
            )
    if not expected_found:
        learners = sorted({r.learner for r in collection.runs}, key=natural_key)
        systems = sorted({r.system for r in collection.runs})
        seeds = sorted({r.seed for r in collection.runs})
        collection.expected_jobs = len(learners) * len(systems) * len(seeds)
        for key in itertools.product(learners, systems, seeds):
            if key not in by_key:
                collection.missing.append(
                    MissingJob(*key, overrides=(), job_dir=None, reason="no run with this seed")
                )
    return collection

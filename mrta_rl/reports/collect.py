"""Collect finished runs (metrics.json, curve.csv) and the jobs a sweep expected but lost.

The expected grid of a multirun (a sweep dir given, or found below an input) is rebuilt as
Hydra's ``BasicSweeper`` builds its jobs, so a job that failed or never started is *missing*.
Run dirs outside a sweep expect nothing: they are reported as the runs they are. A run whose
files cannot be read (a :class:`~mrta_rl.run_layout.RunDirError`) is left out by name. Every
setting that differs among the runs of a learner on a system names a configuration of its own,
so only the same configuration and seed is a duplicate, and test and validation runs are never
averaged together.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import logging
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from mrta_rl import checked_files, run_layout
from mrta_rl.checked_files import MAX_TEXT_BYTES, RunDirError, read_config, read_json
from mrta_rl.config import UserError
from mrta_rl.run_layout import CONFIG_FILE, METRICS_FILE, REFUSED_FILE
from mrta_rl.splits import DEFAULT_SPLIT, SPLIT_SEEDS
from mrta_rl.types import natural_key

logger = logging.getLogger(__name__)

CURVE_FILE = "curve.csv"
CURVE_COLUMNS = ("env_ticks", "team_return_mean")  # the columns of curve.csv a report reads
MULTIRUN_FILE = "multirun.yaml"  # what Hydra writes in a sweep dir
FAILED = "failed or unfinished: no metrics.json (see train.log, sweep output)"
BASIC_SWEEPER = "hydra._internal.core_plugins.basic_sweeper.BasicSweeper"
# settings that do not change what a run computes: never part of a configuration's name
# how a run was carried out, not what it computes (workers change where it runs, not the run)
NOT_CONFIGURATION = (
    *("seed", "resume", "train.progress_bar", "train.checkpoint_every"),
    *("train.workers", "train.ray_address"),
)
POLICY_KEY = "report"  # a run config's block of what a report makes of it (reports/study.py)


class ReportInputError(UserError):
    """The report's inputs hold nothing to report, or do not exist."""


@dataclass(frozen=True)
class RunRecord:
    """One finished run; ``learner`` is its configuration (``subg_reserve reserve=1``)."""

    run_dir: Path
    learner: str
    system: str
    seed: int
    metrics: dict[str, Any]  # the whole metrics.json
    curve: tuple[tuple[int, float], ...]  # (env_ticks, team_return_mean); () for fixed policies
    config: dict[str, Any]  # .hydra/config.yaml ({} if absent)
    overrides: tuple[str, ...]  # .hydra/overrides.yaml
    variant: str = ""  # what sets the configuration apart (reserve=1), or ""

    @property
    def name(self) -> str:
        """The learner's config choice name (yaml stem), without the configuration's settings."""
        learner = self.metrics.get("learner", self.learner)
        return str(learner["name"] if isinstance(learner, dict) else learner).partition(" ")[0]

    @property
    def label(self) -> str:
        """The learner's label (metrics.json's learner block), else its config choice name."""
        learner = self.metrics.get("learner")
        return str(learner.get("label", self.name)) if isinstance(learner, dict) else self.name

    @property
    def key(self) -> tuple[str, str, int]:
        """``(configuration, system, seed)``: one cell of the grid."""
        return (self.learner, self.system, self.seed)


@dataclass(frozen=True)
class MissingJob:
    """A job of the expected grid without metrics.json (``job_dir`` None: never started)."""

    learner: str
    system: str
    seed: int | None
    overrides: tuple[str, ...]
    job_dir: Path | None
    reason: str


@dataclass(frozen=True)
class UnreadableRun:
    """A run dir left out of the report: one of its files cannot be read (``reason`` says which)."""

    run_dir: Path
    reason: str


@dataclass
class Collection:
    """Everything the report is built from; a duplicate repeats a kept run's configuration, seed.

    ``expected_jobs`` and ``sweep_source`` come from the sweeps among the inputs (0 and "" when
    there is none: run dirs expect no other runs).
    """

    inputs: list[Path]
    runs: list[RunRecord] = field(default_factory=list)
    missing: list[MissingJob] = field(default_factory=list)
    duplicates: list[RunRecord] = field(default_factory=list)
    unreadable: list[UnreadableRun] = field(default_factory=list)
    expected_jobs: int = 0
    sweep_source: str = ""


def read_curve(path: Path) -> tuple[tuple[int, float], ...]:
    """Rows ``(env_ticks, team_return_mean)`` of a curve.csv (``()`` if absent or header-only).

    Raises:
        RunDirError: naming the file, and the line and column of a cell that is not a number.
    """
    if not path.exists():
        return ()
    rows = checked_files.read_csv_numbers(path, CURVE_COLUMNS, key="env_ticks")
    return tuple((int(ticks), value) for ticks, value in rows)


def read_yaml_config(path: Path) -> Any:
    """A run dir's YAML config as plain data (None if absent), read with the checked reader.

    Raises:
        RunDirError: naming the file, if it is not a regular file, too big or not YAML.
    """
    if not path.exists():
        return None
    return OmegaConf.to_container(read_config(path), resolve=False)


def config_value(config: dict[str, Any], dotted: str) -> Any:
    """A run config's value at a dotted key (``system.n_robots``), None if absent."""
    return OmegaConf.select(OmegaConf.create(config), dotted, default=None) if config else None


def load_run(run_dir: Path) -> RunRecord:
    """Read one run dir."""
    metrics = run_layout.read_metrics(run_dir / METRICS_FILE)
    config = read_yaml_config(run_dir / CONFIG_FILE) or {}
    overrides = read_yaml_config(run_dir / CONFIG_FILE.with_name("overrides.yaml")) or []
    learner = metrics["learner"]
    learner = str(learner["name"] if isinstance(learner, dict) else learner)
    curve = read_curve(run_dir / CURVE_FILE)
    seed, overrides = int(metrics["seed"]), tuple(str(o) for o in overrides)
    return RunRecord(
        run_dir, learner, str(metrics["system"]), seed, metrics, curve, config, overrides
    )


def _flatten(config: Any, prefix: str = "") -> dict[str, Any]:
    """``{"learner.reserve": 1, ...}``: the leaves of a nested config (lists as values)."""
    if not isinstance(config, dict):
        return {prefix: config}
    out: dict[str, Any] = {}
    for key, value in config.items():
        out.update(_flatten(value, f"{prefix}.{key}" if prefix else str(key)))
    return out


def configuration_variants(records: Sequence[RunRecord]) -> list[str]:
    """What sets each run's configuration apart from the other runs of its learner and system."""
    # the report block is what a study makes of its runs, not how a run computes
    configs = [{k: v for k, v in r.config.items() if k != POLICY_KEY} for r in records]
    flat = [_flatten(named_init(named_streams(c))) for c in configs]
    variants = [""] * len(records)
    groups: dict[tuple[str, str], list[int]] = {}
    for i, record in enumerate(records):
        groups.setdefault((record.learner, record.system), []).append(i)
    for members in groups.values():
        keys = list(dict.fromkeys(k for i in members for k in flat[i]))  # config order
        differing = [
            k
            for k in keys
            if k not in NOT_CONFIGURATION
            and len({json.dumps(flat[i].get(k), sort_keys=True) for i in members}) > 1
        ]
        names = {k: k.removeprefix("learner.") if k.count(".") == 1 else k for k in differing}
        for i in members:
            variants[i] = " ".join(f"{names[k]}={_format_value(flat[i].get(k))}" for k in differing)
    return variants


def named_streams(config: dict[str, Any]) -> dict[str, Any]:
    """The config with its evaluation streams named by ``eval.split`` (``mrta_rl/splits.py``).

    A run from before ``eval.split`` records the test split's seed as ``eval.seed``: both forms
    name the same streams, so runs differ in ``eval.split`` only when their streams differ.
    """
    evaluation = config.get("eval")
    if not isinstance(evaluation, dict) or not {"seed", "split"} & set(evaluation):
        return config  # no streams recorded (not written by scripts/train.py)
    split = evaluation.get("split") or DEFAULT_SPLIT
    named = {**evaluation, "split": split}
    if evaluation.get("seed") == SPLIT_SEEDS.get(split):
        named["seed"] = None
    return {**config, "eval": named}


def named_init(config: dict[str, Any]) -> dict[str, Any]:
    """The config with ``init`` (a run dir) named by the system that run trained on.

    Runs started from the runs of several seeds on one family (``init=<run dir>``) are one
    configuration, ``init=family``, apart from the runs trained on their own team.
    """
    init = config.get("init")
    if not init:
        return config
    try:
        trained_on = str(run_layout.read_metrics(Path(init) / METRICS_FILE)["system"])
    except (OSError, ValueError, KeyError, TypeError):
        trained_on = Path(init).name
    return {**config, "init": trained_on}


def _format_value(value: Any) -> str:
    if value is None:
        return "null"
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, list):
        return "[" + ",".join(_format_value(v) for v in value) + "]"
    return str(value)


def refusal_reason(run_dir: Path) -> str | None:
    """``"refused: <reason>"`` if the run was refused up front (its ``refused.json``), else None."""
    path = run_dir / REFUSED_FILE
    if not path.exists():
        return None
    try:
        reason = read_json(path).get("reason", "no reason given")
    except (RunDirError, AttributeError):
        reason = f"unreadable {REFUSED_FILE}"
    return f"refused: {reason}"


def refused_jobs(sweep_dir: Path) -> dict[frozenset[str], str]:
    """``"refused: <reason>"`` of the sweep's jobs refused by validation, keyed by overrides.

    Such a job leaves no run dir, so its reason is kept in the sweep dir.
    """
    path, out = sweep_dir / run_layout.REFUSED_JOBS_FILE, {}
    if not path.exists():
        return out
    data = checked_files.read_bytes(path, MAX_TEXT_BYTES, "a list of refused jobs")
    for line in data.decode(errors="replace").splitlines():
        try:
            record = checked_files.parse_json(line, path)
            out[frozenset(str(o) for o in record["overrides"])] = f"refused: {record['reason']}"
        except (RunDirError, KeyError, TypeError):
            continue
    return out


def expected_sweep_jobs(multirun_yaml: Path) -> list[list[str]] | None:
    """The job list Hydra's BasicSweeper built for a multirun (None: another sweeper ran it)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    cfg = read_config(multirun_yaml)
    sweeper = OmegaConf.select(cfg, "hydra.sweeper", default=None)
    if sweeper is None or sweeper.get("_target_") != BASIC_SWEEPER:
        return None
    params = sweeper.get("params") or {}
    # same order as BasicSweeper.sweep: sweeper params, then the command line (which wins)
    arguments = [f"{k}={v}" for k, v in params.items()]
    arguments += [str(o) for o in OmegaConf.select(cfg, "hydra.overrides.task", default=[])]
    choices: dict[str, list[str]] = {}  # key -> its values as overrides; a later key replaces
    for override in OverridesParser.create().parse_overrides(arguments):
        key = override.get_key_element()
        if override.is_sweep_override():
            choices[key] = [f"{key}={value}" for value in override.sweep_string_iterator()]
        else:
            choices[key] = [f"{key}={override.get_value_element_as_str()}"]
    return [list(job) for job in itertools.product(*choices.values())]


def _job_identity(job: Sequence[str], cfg: Any) -> tuple[str, str, int | None]:
    """``(learner, system, seed)`` of an expected job: its overrides, else the sweep defaults."""
    # key=value, +key=value or ++key=value; the first of a key counts
    given = {k.lstrip("+"): v for k, _, v in (item.partition("=") for item in reversed(job))}
    choices = OmegaConf.select(cfg, "hydra.runtime.choices", default={}) or {}
    learner = given.get("learner") or str(choices.get("learner", "?"))
    system = given.get("system") or str(choices.get("system", "?"))
    seed_text = given.get("seed", str(cfg.get("seed", "")))
    try:
        seed: int | None = int(seed_text)
    except ValueError:
        seed = None
    return learner, system, seed


def _load_runs(run_dirs: Iterable[Path], collection: Collection) -> list[RunRecord]:
    """The runs that can be read; the others go to ``collection.unreadable``, with a log line."""
    records = []
    for run_dir in run_dirs:
        try:
            records.append(load_run(run_dir))
        except RunDirError as err:
            logger.warning("%s left out of the report: %s", run_dir, err)
            collection.unreadable.append(UnreadableRun(run_dir, str(err)))
    return records


def found_files(paths: Sequence[Path], name: str) -> list[Path]:
    """The files ``name`` of the inputs: an input's own, else every one below it."""
    found = [[p / name] if (p / name).is_file() else p.rglob(name) for p in paths]
    return sorted({f.resolve() for files in found for f in files})


def collect_runs(inputs: Iterable[Path | str]) -> Collection:
    """Gather the runs below the inputs and list the jobs their sweeps expected but lost.

    Raises:
        ReportInputError: if an input does not exist.
    """
    paths = [Path(p) for p in inputs]
    for path in paths:
        if not path.exists():
            raise ReportInputError(f"no such run or sweep dir: {path}")
    collection = Collection(inputs=paths)
    by_key: dict[tuple[str, str, int], RunRecord] = {}
    # a run dir holds a metrics.json: an input itself, else every folder below it
    records = _load_runs((m.parent for m in found_files(paths, METRICS_FILE)), collection)
    variants = configuration_variants(records)
    for record, variant in zip(records, variants, strict=True):
        if variant:
            record = dataclasses.replace(
                record, learner=f"{record.learner} {variant}", variant=variant
            )
        if (kept := by_key.setdefault(record.key, record)) is not record:
            # e.g. a run repeated by hand: a seed counts once
            logger.warning("%s repeats %s; keeping %s", record.run_dir, record.key, kept.run_dir)
            collection.duplicates.append(record)
    collection.runs = sorted(by_key.values(), key=lambda r: (natural_key(r.learner), *r.key[1:]))

    # only a sweep expects jobs: run dirs given or found outside one expect no other runs
    sweeps = []
    for multirun_yaml in found_files(paths, MULTIRUN_FILE):
        jobs = expected_sweep_jobs(multirun_yaml)
        if jobs is None:
            logger.warning("%s: not a BasicSweeper sweep: no expected grid", multirun_yaml)
            continue
        sweeps.append(multirun_yaml)
        collection.sweep_source = ", ".join(str(s) for s in sweeps)
        collection.expected_jobs += len(jobs)
        cfg = read_config(multirun_yaml)
        dirs = {  # job dirs of the sweep by their overrides
            frozenset(str(o) for o in read_yaml_config(p) or []): p.parent.parent
            for p in sorted(multirun_yaml.parent.rglob("overrides.yaml"))
            if p.parent.name == ".hydra"
        }
        refused = refused_jobs(multirun_yaml.parent)
        for job in jobs:
            job_dir = dirs.get(frozenset(job))
            if job_dir is not None and (job_dir / METRICS_FILE).is_file():
                continue
            if job_dir is None:
                reason = refused.get(frozenset(job), "never started (no job dir)")
            else:
                reason = refusal_reason(job_dir) or FAILED
            missing = MissingJob(*_job_identity(job, cfg), tuple(job), job_dir, reason)
            collection.missing.append(missing)
    return collection

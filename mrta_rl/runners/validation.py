"""Check a whole run config before any work: settings, learner, system, env, memory.

:func:`validate_config` is the one gate of ``scripts/train.py`` (and of re-evaluation): it checks
every setting against its single declaration (``mrta_rl.config``), namely

* the run-level keys of ``conf/config.yaml`` (``seed``, ``train.*``, ``eval.*``, ``limits.*``),
  declared here by :class:`RunSettings`, :class:`TrainSettings`, :class:`EvalSettings`,
  :class:`LimitSettings` (their defaults stay in ``conf/config.yaml``, the one place of defaults);
* the learner's hyperparameters against its ``__init__`` signature (``conf/learner/*.yaml``);
* the system file (``mrta_rl.systems``) and the env parameters, the system's ``env:`` block and
  the run's ``env.*`` (``AuctionParams``);

then builds the system, parameters and partition and estimates what the learner will need
(``mrta_rl.learners.memory``), refusing a learner that cannot run on the system or needs more
memory than ``limits.memory_gb``. Every refusal is a :class:`~mrta_rl.config.ConfigError` whose
message names the key or the culprit; nothing has been written when it is raised.
"""

from __future__ import annotations

import importlib
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

import numpy as np
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from mrta_rl.cluster import EXTRA, ray_installed, unreachable
from mrta_rl.config import (
    Choices,
    ConfigError,
    Range,
    check_fields,
    check_keywords,
    check_value,
)
from mrta_rl.envs import AuctionParams
from mrta_rl.envs.auction import check_limits
from mrta_rl.learners import Learner
from mrta_rl.learners.base import TrainingTeam, learner_from_target
from mrta_rl.learners.memory import (
    estimate_resources,
    machine_memory,
    probe_env,
    team_floor_bytes,
)
from mrta_rl.learners.registry import any_team_learners
from mrta_rl.learners.resources import ResourceEstimate, format_bytes
from mrta_rl.loops import TORCH_LOOP
from mrta_rl.partition import Partition, subg_partition
from mrta_rl.run_layout import LEARNER_DIR, RunDirError
from mrta_rl.runners.bases import check_base
from mrta_rl.runners.run_config import read_run_config
from mrta_rl.splits import FAMILY_SEEDS, SEED_STRIDE, SPLIT_SEEDS, SPLIT_WIDTH
from mrta_rl.systems import (
    MAX_PAIRS,
    RobotSystem,
    SystemConfigError,
    build_system,
    system_shape,
)
from mrta_rl.systems.family import TeamFamily, build_family

logger = logging.getLogger(__name__)

# top-level keys of a run config besides RunSettings': conf/config.yaml's blocks and groups
RUN_BLOCKS = (
    "resume",
    "init",
    "train",
    "eval",
    "limits",
    "env",
    "system",
    "learner",
    "partition",
    "logger",
    "report",  # what scripts/report.py makes of the run (conf/experiment/*.yaml): data, unread here
)
MEMORY_FRACTION = 0.5  # default limits.memory_gb: this fraction of the machine's memory


@dataclass(frozen=True)
class RunSettings:
    """Top-level keys of ``conf/config.yaml``."""

    seed: Annotated[int, Range(0, 2**31 - 1)]  # learner generator; training env seeds from it


@dataclass(frozen=True)
class TrainSettings:
    """``train:`` of ``conf/config.yaml``."""

    episodes: Annotated[int, Range(0)]  # training episodes of all copies
    batch_size: Annotated[int, Range(1)]  # B: copies played in parallel
    progress_bar: bool  # tqdm bar on stderr
    log_every_s: Annotated[float, Range(0, low_open=True)]  # seconds between log lines, no bar
    checkpoint_every: Annotated[int, Range(0)]  # episodes between checkpoints, 0 = only on Ctrl-C
    # robot-copies per tick: caps B at robot_copies // m for a team of m robots (a tick costs in
    # proportion to the team); None = no cap
    robot_copies: Annotated[int | None, Range(1)]
    # torch learners: episodes between evaluations of the greedy policy on the validation
    # streams during training (val/team_return); 0 = none
    validate_every: Annotated[int, Range(0)]
    validate_episodes: Annotated[int, Range(1)]  # validation copy-episodes of each evaluation
    # the run ends with the weights of its best validation return (needs validate_every)
    keep_best: bool
    # Ray worker processes: an ES step's members (population_on_workers) or a torch learner's
    # collection (collection_on_workers); 0 = none, everything in this process
    workers: Annotated[int, Range(0)]
    # with workers: the Ray cluster to join; None = a local Ray instance of ``workers`` CPUs
    ray_address: str | None


@dataclass(frozen=True)
class EvalSettings:
    """``eval:`` of ``conf/config.yaml``."""

    episodes: Annotated[int, Range(1)]  # evaluation copy-episodes
    batch_size: Annotated[int, Range(1)]  # copies per round
    # the streams played (mrta_rl/splits.py): test (reported) or validation (choices made on)
    split: Annotated[str, Choices(*SPLIT_SEEDS)]
    # copy b plays seed + b; null: the split's seed. A value must be that seed (a saved config
    # may record it): the split names the streams
    seed: Annotated[int | None, Range(0, SEED_STRIDE - 1)]


@dataclass(frozen=True)
class LimitSettings:
    """``limits:`` of ``conf/config.yaml``; refused before any work when passed."""

    # memory the learner may take (GB): up front, and its Q-tables as they grow (qtable.py);
    # null: MEMORY_FRACTION of the machine's memory
    memory_gb: Annotated[float | None, Range(0, low_open=True)]


@dataclass(frozen=True)
class PartitionSettings:
    """``partition:`` of ``conf/config.yaml`` (conf/partition/subg.yaml; docs/spec/partition.md)."""

    # g: at most g robots per sub-group (oversized ones are split); None = the paper's rule
    max_group_size: Annotated[int | None, Range(1)]


@dataclass(frozen=True)
class EvaluateSettings:
    """``conf/evaluate.yaml``: the arguments of ``scripts/evaluate.py``."""

    checkpoint: str  # run dir of scripts/train.py
    episodes: Annotated[int | None, Range(1)] = None  # null: the run's eval.episodes
    batch_size: Annotated[int | None, Range(1)] = None  # null: the run's eval.batch_size
    eval: dict[str, Any] | None = None  # the streams, checked by EvaluateStreams


@dataclass(frozen=True)
class EvaluateStreams:
    """``eval:`` of ``conf/evaluate.yaml``: which streams ``scripts/evaluate.py`` plays."""

    split: Annotated[str | None, Choices(*SPLIT_SEEDS)] = None  # null: the run's eval.split


def check_evaluate_config(cfg: DictConfig) -> dict[str, Any]:
    """The checked arguments of ``scripts/evaluate.py`` (:class:`EvaluateSettings`).

    Returns:
        The arguments, with ``eval`` replaced by its ``split`` (None: the run's own).

    Raises:
        ConfigError: naming the argument (``checkpoint: missing; ...``, ``eval.split: ...``).
    """
    values = {k: _plain(cfg, k) for k in cfg if k != "hydra" and not OmegaConf.is_missing(cfg, k)}
    if values.get("checkpoint") is None:  # conf/evaluate.yaml: ???
        values.pop("checkpoint", None)
    args = check_fields(EvaluateSettings, values, "", require=True)
    streams = args.pop("eval", None)
    _check(
        streams is None or isinstance(streams, dict),
        f"eval: must be a mapping (eval.split=...), got {streams!r}",
    )
    args["split"] = check_fields(EvaluateStreams, streams or {}, "eval").get("split")
    return args


# mrta-partition format=: a plain-text table, or JSON (Partition.to_json)
PARTITION_FORMAT = Annotated[str, Choices("table", "json")]


def check_partition_config(cfg: DictConfig) -> dict[str, Any]:
    """The checked arguments of ``mrta-partition`` (``conf/partition.yaml``), the system as data.

    Returns:
        ``{"format": "table" | "json", "max_group_size": int | None, "system": ...}``: the
        system config as plain Python, its interpolations resolved (the team is checked by
        :func:`checked_team`).

    Raises:
        ConfigError: naming the argument (``partition.max_group_size: ...``, ``format: ...``).
    """
    known = ("format", "partition", "system")
    for key in cfg:
        _check(key in {*known, "hydra"}, f"{key}: unknown setting (known: {', '.join(known)})")
    output = check_value("format", _plain(cfg, "format"), PARTITION_FORMAT)
    bound = check_fields(PartitionSettings, _plain(cfg, "partition") or {}, "partition")
    return {
        "format": output,
        "max_group_size": bound.get("max_group_size"),
        "system": _plain(cfg, "system"),
    }


def check_streams(train: dict[str, Any], evaluation: dict[str, Any]) -> None:
    """Refuse copies that would play another's task streams (``mrta_rl/splits.py``).

    Args:
        train: The checked ``train`` block (:class:`TrainSettings`).
        evaluation: The checked ``eval`` block (:class:`EvalSettings`).

    Raises:
        ConfigError: naming ``eval.seed`` and ``eval.split`` when they contradict each other,
            ``eval.batch_size`` when the copies would run into another split's seeds, or
            ``train.batch_size`` when run seed 0's copies would run into the test split's.
    """
    split, seed = evaluation["split"], evaluation["seed"]
    if seed is not None:
        _check(
            seed + evaluation["batch_size"] <= SEED_STRIDE,
            f"eval.seed: must be <= 2**32 - eval.batch_size, got {seed}",
        )
        _check(
            seed == SPLIT_SEEDS[split],
            f"eval.seed: {seed} contradicts eval.split={split}, whose copy b plays "
            f"{SPLIT_SEEDS[split]} + b; drop eval.seed (eval.split names the streams)",
        )
    _check(
        evaluation["batch_size"] <= SPLIT_WIDTH,
        f"eval.batch_size: must be <= {SPLIT_WIDTH} (the seeds of one split), "
        f"got {evaluation['batch_size']}",
    )
    first = min(SPLIT_SEEDS.values())
    _check(
        train["batch_size"] <= first,
        f"train.batch_size: must be <= {first} (run seed 0's copies would play the evaluation "
        f"streams), got {train['batch_size']}",
    )


class ResourceRefusal(ConfigError):
    """A run refused up front because the learner would not fit (its reason is the message).

    ``train`` records it in the run dir (``refused.json``), so a sweep's report shows the run as
    refused with its reason instead of missing.
    """


@dataclass
class CheckedConfig:
    """A run config that passed :func:`validate_config`, with what it was built into.

    Attributes:
        learner_cls: The learner class.
        hyperparameters: The learner's settings, checked (declared defaults not filled in).
        system: The robot team.
        params: The dynamics parameters (system layer, then run layer).
        partition: The subG partition if the learner requires one, else None.
        estimate: What the learner will need.
        memory_limit: Bytes the learner may take (``limits.memory_gb``, :func:`memory_limit`).
        batch_size: Env copies per training tick (``train.batch_size`` capped by
            ``train.robot_copies``, :func:`training_copies`).
        family: The family of teams training draws from (``system.family``), else None; then
            ``system`` is its evaluation team.
        env_overrides: The run's ``env.*`` (every team's parameters take them last).
        init: The run dir whose learner state the learner starts from (``init=``), else None.
        base: The run dir whose trained learner the learner plays (``learner.base``,
            :func:`check_base`), else None.
    """

    learner_cls: type[Learner]
    hyperparameters: dict[str, Any]
    system: RobotSystem
    params: AuctionParams
    partition: Partition | None
    estimate: ResourceEstimate
    memory_limit: int
    batch_size: int
    family: TeamFamily | None = None
    env_overrides: dict[str, Any] | None = None
    init: Path | None = None
    base: Path | None = None

    @property
    def active_tasks(self) -> np.ndarray | None:
        """``[m, n]`` bool ``Lambda_i`` of the learner's envs, None = ``Gamma_i``."""
        return self.partition.active_tasks(self.system) if self.partition is not None else None


def _check(condition: bool, message: str) -> None:
    if not condition:
        raise ConfigError(message)


def hydra_choice(group: str, default: str) -> str:
    """The config-group choice of the current Hydra run (``learner`` -> ``greedy``) or default."""
    if HydraConfig.initialized():
        choice = HydraConfig.get().runtime.choices.get(group)
        if choice:
            return str(choice)
    return default


def _check_logger(settings: Any) -> None:
    """The curve logger's settings: declared keywords, and file names that stay in the run dir."""
    from mrta_rl.metrics.run_logger import RunLogger  # every logger of a run is one (checkpoint.py)

    if settings is None:
        return
    _check(isinstance(settings, dict), f"logger: must be a logger config, got {settings!r}")
    checked = check_keywords(RunLogger, settings, "logger")
    for key, refused in (("filename", ("", ".", "..")), ("log_dir", ("", ".."))):
        name = checked.get(key)  # log_dir "." is the run dir itself (wandb adds its wandb/)
        _check(
            name is None or (name not in refused and "/" not in name and "\\" not in name),
            f"logger.{key}: must be a plain name inside the run dir, got {name!r}",
        )


def _plain(cfg: DictConfig, key: str) -> Any:
    """The content of ``cfg.<key>`` as plain Python, interpolations resolved; None if absent."""
    try:
        node = OmegaConf.select(cfg, key, throw_on_missing=True)
        return OmegaConf.to_container(node, resolve=True) if OmegaConf.is_config(node) else node
    except OmegaConfBaseException as err:
        raise ConfigError(f"{key}: {type(err).__name__}: {err}".splitlines()[0]) from None


def _section(cfg: DictConfig, key: str, declaration: type) -> dict[str, Any]:
    values = _plain(cfg, key)
    _check(values is not None, f"{key}: missing (see conf/config.yaml)")
    return check_fields(declaration, values, key, require=True)


def learner_class(cfg_learner: Any) -> type[Learner]:
    """The learner class named by a ``conf/learner/*.yaml``, checked.

    Args:
        cfg_learner: The ``learner`` config group content.

    Returns:
        The :class:`Learner` subclass.

    Raises:
        ConfigError: if ``_target_``/``_partial_`` are missing, the class cannot be imported or
            is not a :class:`Learner`.
    """
    _check(
        OmegaConf.is_dict(cfg_learner) or isinstance(cfg_learner, dict),
        f"learner: must be a learner config (conf/learner/*.yaml), got {cfg_learner!r}",
    )
    target = cfg_learner.get("_target_")
    _check(target is not None, "learner: the learner config has no _target_")
    _check(cfg_learner.get("_partial_") is True, f"learner {target}: set `_partial_: true`")
    return learner_from_target(str(target), "learner._target_")


def training_loop(cls: type[Learner]) -> Any:
    """Import the training loop a learner class declares (``training_loop``, ``learners/base.py``).

    Raises:
        ConfigError: if the loop's module or function is missing.
    """
    module_name, _, function = cls.training_loop.partition(":")
    try:
        loop = getattr(importlib.import_module(module_name), function)
    except (ModuleNotFoundError, AttributeError) as err:
        raise ConfigError(
            f"no training loop {cls.training_loop!r} for learner {cls.__name__}: {err}"
        ) from err
    return loop


def training_copies(batch_size: int, robot_copies: int | None, n_robots: int) -> int:
    """Env copies per training tick: ``train.batch_size``, capped by ``train.robot_copies``.

    A tick costs in proportion to the team, so ``robot_copies`` bounds copies x robots:
    ``min(batch_size, max(1, robot_copies // n_robots))``; None leaves ``batch_size``.
    """
    if robot_copies is None:
        return batch_size
    return min(batch_size, max(1, robot_copies // n_robots))


def memory_limit(limits: dict[str, Any]) -> int:
    """Bytes a learner may take: ``limits.memory_gb``, else a fraction of the machine's memory."""
    if limits.get("memory_gb") is not None:
        return int(limits["memory_gb"] * 1e9)
    return int(MEMORY_FRACTION * machine_memory())


def check_team_size(
    system_cfg: dict[str, Any],
    file: str,
    limit: int,
    train: dict[str, Any] | None = None,
    eval_copies: int = 0,
) -> None:
    """Refuse a team too big to run, from its shape alone, before it is built.

    Refused: more than ``MAX_PAIRS`` robot-task pairs, or a memory floor above the limit.

    A random team of 10^8 robots would take 28 GB to draw; the floor
    (:func:`~mrta_rl.learners.memory.team_floor_bytes`) counts the system while it is built
    and the env copies alive at once: training's and evaluation's, the learner's and the greedy
    baseline's (none without ``train``: a command that builds the team only).

    Raises:
        SystemConfigError: naming the system, its shape, the floor and the limit.
    """
    shape = system_shape(system_cfg)
    if shape is None:
        return  # malformed: build_system names what is wrong
    m, n = shape
    if m * n > MAX_PAIRS:
        raise SystemConfigError(
            f"system {file}: {m:,} robots x {n:,} task types = {m * n:,} robot-task pairs, more "
            f"than the limit of {MAX_PAIRS:,} (mrta_rl.systems.MAX_PAIRS); use a smaller team"
        )
    copies = 2 * eval_copies  # the learner's and the greedy baseline's
    if train is not None:
        copies += training_copies(train["batch_size"], train.get("robot_copies"), m)
    parts = team_floor_bytes(m, n, copies)
    floor = sum(parts.values())
    if floor > limit:
        detail = ", ".join(f"{name} {format_bytes(b)}" for name, b in parts.items())
        raise SystemConfigError(
            f"system {file}: {m:,} robots x {n:,} task types need at least {format_bytes(floor)} "
            f"before any learner ({detail} for {copies} copies), more than the limit of "
            f"{format_bytes(limit)} (limits.memory_gb); use a smaller team"
        )


def check_workers_available(cfg: DictConfig) -> None:
    """Refuse workers this machine cannot give a run that is about to train.

    Ray must be installed and the cluster of ``train.ray_address`` must answer. These are facts
    of the machine, not of the config, so they are checked where training starts, not in
    :func:`validate_config`: a finished run trained on a cluster is re-evaluated, or serves as a
    base or a start, anywhere.

    Raises:
        ConfigError: naming ``train.workers`` (the missing extra) or ``train.ray_address``.
    """
    # a run written before train.workers existed has neither key: it trains in one process
    workers, address = int(cfg.train.get("workers", 0)), cfg.train.get("ray_address")
    if not workers:
        return
    _check(
        ray_installed(),
        f"train.workers={workers} needs Ray, which is not installed: "
        f"pip install 'mrta_rl[{EXTRA}]'",
    )
    if address is not None:
        why = unreachable(str(address))
        _check(why is None, f"train.ray_address={address}: {why}")


def validate_config(cfg: DictConfig) -> CheckedConfig:
    """Check a composed run config, build system, params and partition, estimate the memory.

    Args:
        cfg: The composed run config (``conf/config.yaml``).

    Returns:
        The checked pieces; nothing has been written and no learner or env has been built.

    Raises:
        ConfigError: naming the key or culprit (``SystemConfigError`` for a system file).
    """
    # a key added with +key=... that nothing reads is refused, not stored; a config group
    # composed into its own package (+budget=neural) is a group, not a setting
    groups = set(HydraConfig.get().runtime.choices) if HydraConfig.initialized() else set()
    for key in cfg:
        _check(
            key in RUN_BLOCKS
            or key in RunSettings.__dataclass_fields__
            or key in {*groups, "hydra"},
            f"{key}: unknown setting (known: {', '.join(['seed', *RUN_BLOCKS])})",
        )
    check_fields(RunSettings, {"seed": _plain(cfg, "seed")}, "", require=True)
    train = _section(cfg, "train", TrainSettings)
    evaluation = _section(cfg, "eval", EvalSettings)
    check_streams(train, evaluation)
    limits = _section(cfg, "limits", LimitSettings)
    bound = check_fields(PartitionSettings, _plain(cfg, "partition") or {}, "partition")

    cls = learner_class(cfg.get("learner"))
    training_loop(cls)  # fail now, not after building everything, if the loop is missing
    _check(
        not train["validate_every"] or cls.training_loop == TORCH_LOOP,
        f"train.validate_every: the torch loop's; {cls.__name__} trains on "
        f"{cls.training_loop}: set train.validate_every=0",
    )
    _check(
        not train["keep_best"] or train["validate_every"] > 0,
        "train.keep_best: keeps the weights of the best validation return, so it needs "
        "train.validate_every > 0",
    )
    _check(
        not train["workers"] or cls.population_on_workers or cls.collection_on_workers,
        f"train.workers: Ray workers play an evolution strategies step's members or collect a "
        f"torch learner's frames; {cls.__name__} spreads neither: set train.workers=0",
    )
    hyperparameters = check_keywords(cls, _plain(cfg, "learner"), "learner")
    _check_logger(_plain(cfg, "logger"))

    eval_copies = min(evaluation["batch_size"], evaluation["episodes"])
    env_overrides = _plain(cfg, "env") or {}
    file, family, system, params = checked_team(
        _plain(cfg, "system"), memory_limit(limits), env_overrides, train, eval_copies
    )
    if family is not None:
        check_family(cls, hyperparameters, family, file, train, params.horizon)
    init = check_init(cls, hyperparameters, _plain(cfg, "init"))
    base = check_base(cls, hyperparameters)
    partition = (
        subg_partition(system, bound.get("max_group_size")) if cls.requires_partition else None
    )
    robot_copies = train.get("robot_copies")
    batch_size = training_copies(train["batch_size"], robot_copies, system.n_robots)
    if batch_size < train["batch_size"]:
        logger.info(
            "train.batch_size %d capped to %d copies by train.robot_copies=%d (%d robots)",
            train["batch_size"],
            batch_size,
            robot_copies,
            system.n_robots,
        )
    if train["workers"] and cls.collection_on_workers:  # each worker collects whole copies
        _check(
            family is None,
            "train.workers: collection on workers plays one team, not system=family: "
            "set train.workers=0",
        )
        _check(
            batch_size % train["workers"] == 0,
            f"train.batch_size {batch_size} must be a multiple of train.workers "
            f"{train['workers']} (each worker collects as many copies)",
        )

    try:  # relations between the settings, and to the team and the copies
        active = partition.active_tasks(system) if partition is not None else None
        team = TrainingTeam(probe_env(system, params, active), partition, batch_size)
        cls.check_settings(cls.complete_settings(hyperparameters), team)
        estimate = estimate_resources(
            cls,
            system,
            params,
            partition,
            hyperparameters,
            batch_size=batch_size,
            episodes=train["episodes"],
            eval_batch_size=min(evaluation["batch_size"], evaluation["episodes"]),
        )
    except ConfigError:
        raise
    except ValueError as err:  # the env's own limits (AuctionEnv._check_limits)
        raise ConfigError(f"env: {err}") from None
    limit = memory_limit(limits)
    refusal = estimate.refusal(limit)
    name = hydra_choice("learner", cls.__name__)
    where = f"{name} on system {file} ({system.n_robots} robots)"
    if refusal is not None:
        advice = estimate.advice
        if estimate.reason is None:
            advice += ", or raise limits.memory_gb"
        raise ResourceRefusal(f"{where}: {refusal}; {advice}")
    if estimate.worst > limit:
        logger.warning(
            "%s: its tables could grow to %s if every state were met (limit %s); watch the memory",
            where,
            format_bytes(estimate.worst),
            format_bytes(limit),
        )
    return CheckedConfig(
        cls,
        hyperparameters,
        system,
        params,
        partition,
        estimate,
        limit,
        batch_size,
        family,
        env_overrides,
        init,
        base,
    )


def checked_team(
    system_cfg: Any,
    limit: int,
    env_overrides: dict[str, Any],
    train: dict[str, Any] | None = None,
    eval_copies: int = 0,
) -> tuple[str, TeamFamily | None, RobotSystem, AuctionParams]:
    """The team of a system config within the limits of a run, refused before it is built if not.

    Its shape against :data:`MAX_PAIRS` and the memory limit (:func:`check_team_size`), then
    its parameters against the env's limits (:func:`~mrta_rl.envs.auction.check_limits`),
    before anything that grows with the team (a partition, an env, a learner) is built.

    Args:
        system_cfg: The content of the ``system`` group (a system file), plain Python.
        limit: Memory limit in bytes (:func:`memory_limit`).
        env_overrides: The run's ``env.*``.
        train: The checked ``train`` block of a run, None for a command that builds the team
            only (:func:`check_team_size`).
        eval_copies: Evaluation copies played at once.

    Returns:
        ``(name, family, system, params)``: the system's name in messages (its config group
        choice in a Hydra job, else its ``name``), the family of teams it draws from (or
        None), the team and its parameters.

    Raises:
        ConfigError: naming the system and what is wrong (``SystemConfigError`` for its file).
    """
    _check(isinstance(system_cfg, dict), f"system: must be a system file, got {system_cfg!r}")
    file = hydra_choice("system", str(system_cfg.get("name", "?")))
    check_team_size(system_cfg, file, limit, train, eval_copies)
    try:
        family = build_family(system_cfg)
        system = build_system(system_cfg)
        params = team_params(system, env_overrides)
    except SystemConfigError as err:
        message = str(err)
        raise SystemConfigError(
            message if message.startswith("system") else f"system {file}: {message}"
        ) from None
    try:
        check_limits(system, params)
    except ValueError as err:
        raise ConfigError(f"env: {err} (system {file}, {system.n_robots:,} robots)") from None
    return file, family, system, params


def team_params(system: RobotSystem, env_overrides: dict[str, Any]) -> AuctionParams:
    """A team's dynamics parameters: the spec's, then its ``env:`` block, then the run's ``env.*``.

    Raises:
        ConfigError: naming the parameter (``system.env.<key>`` or ``env.<key>``).
    """
    return AuctionParams.merged(
        check_fields(AuctionParams, system.env_overrides, "system.env", null_is_default=True),
        env_overrides,
    )


def check_family(
    cls: type[Learner],
    settings: dict[str, Any],
    family: TeamFamily,
    file: str,
    train: dict[str, Any],
    horizon: int,
) -> None:
    """Refuse training on a family of teams by a learner whose state is tied to one team.

    Raises:
        ConfigError: naming the learner and the system, ``train.episodes``, or a learner
            setting that cannot work on a family (``Learner.check_family_settings``).
    """
    full = cls.complete_settings(settings)
    _check(
        not cls.trains() or cls.fits_any_team(full),
        f"system {file}: learner {hydra_choice('learner', cls.__name__)} ({cls.__name__}) is "
        f"tied to one team's robots at these settings and cannot train on a family of teams; "
        f"learners that can: {', '.join(any_team_learners())}",
    )
    _check(
        (train["episodes"] + 1) * train["batch_size"] <= FAMILY_SEEDS,
        f"train.episodes: {train['episodes']} episodes of {train['batch_size']} copies on a "
        f"family of teams need more env seeds than a run seed owns ({FAMILY_SEEDS:,})",
    )
    if cls.trains():
        cls.check_family_settings(full, horizon, train["batch_size"])


def check_init(cls: type[Learner], settings: dict[str, Any], init: Any) -> Path | None:
    """The run dir of ``init=`` (the learner starts from its saved state), checked.

    Its learner must be of the same class and hold nothing of one team (``Learner.any_team``),
    so that its state plays the run's team, whichever team it was trained on.

    Raises:
        ConfigError: naming ``init`` and what is wrong.
    """
    if init is None:
        return None
    _check(isinstance(init, str) and init != "", f"init: must be a run dir, got {init!r}")
    name = hydra_choice("learner", cls.__name__)
    _check(
        cls.fits_any_team(cls.complete_settings(settings)),
        f"init: learner {name} ({cls.__name__}) is tied to one team's robots at these settings; "
        "only a learner "
        f"whose state fits any team starts from another run ({', '.join(any_team_learners())})",
    )
    run_dir = Path(init)
    try:
        saved = learner_class(read_run_config(run_dir).get("learner"))
    except RunDirError as err:
        raise ConfigError(f"init: {err}") from None
    _check(
        saved is cls,
        f"init: {run_dir} trained {saved.__name__}, not {cls.__name__} (learner={name})",
    )
    _check((run_dir / LEARNER_DIR).is_dir(), f"init: {run_dir / LEARNER_DIR} is missing")
    return run_dir

"""Run wiring: config -> system, params, partition, env, learner; train, evaluate, write results.

``train(cfg)`` is the single entry point of ``scripts/train.py``. It validates and builds
everything first (:func:`build_run`), so a bad config fails before any file is written; then the
training loop the learner class declares runs (``training_loop``), and the shared evaluation
(``runners/evaluate.py``) scores the learner and the greedy baseline on the same task streams.

Seeds: the learner's generator is ``default_rng(seed)``; training copy ``b`` uses env seed
``seed * 2**32 + b``, and evaluation copy ``b`` the seed of its split ``eval.split`` plus ``b``
(``mrta_rl/splits.py``), so training and evaluation task streams never coincide and every learner
and run seed is evaluated on identical streams.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig, open_dict

from mrta_rl.config import ConfigError, UserError, short_list
from mrta_rl.envs import AuctionEnv
from mrta_rl.errors import check_output_file
from mrta_rl.learners import Learner
from mrta_rl.learners.tabular.qtable import TableGrowthError, limit_growth
from mrta_rl.metrics.run_logger import finish_run
from mrta_rl.metrics.usage import RunResources
from mrta_rl.run_layout import (
    CONFIG_FILE,
    EVAL_METRICS_FILE,
    LEARNER_DIR,
    METRICS_FILE,
    REFUSED_FILE,
    RunDirError,
    write_json,
)
from mrta_rl.runners.checkpoint import TrainingCheckpoint, TrainingInterrupted
from mrta_rl.runners.evaluate import evaluate_run
from mrta_rl.runners.learner_state import load_learner, save_learner, team_record
from mrta_rl.runners.run_config import read_run_config, run_choices
from mrta_rl.runners.run_dir import claim_run_dir, releases_run_dirs
from mrta_rl.runners.run_setup import RunSetup
from mrta_rl.runners.validation import (
    SEED_STRIDE,
    ResourceRefusal,
    check_workers_available,
    hydra_choice,
    team_params,
    training_loop,
    validate_config,
)
from mrta_rl.splits import FAMILY_SEEDS

logger = logging.getLogger(__name__)


def build_run(cfg: DictConfig, name: str | None = None) -> RunSetup:
    """Validate the config and build system, params, partition, training env and learner.

    Args:
        cfg: The composed run config (conf/config.yaml).
        name: Learner name; default: the Hydra choice of the ``learner`` group, else the class name.

    Returns:
        The run's components; nothing has been written yet.

    Raises:
        ConfigError: on any invalid setting, system file or a learner too big for the machine
            (the message names it; see ``runners/validation.py``).
    """
    checked = validate_config(cfg)
    cls = checked.learner_cls
    name = name or hydra_choice("learner", cls.__name__)
    env = AuctionEnv(
        checked.system,
        checked.params,
        batch_size=checked.batch_size,
        active_tasks=checked.active_tasks,
        seed=cfg.seed * SEED_STRIDE,
    )
    # a trained learner a setting names by its run dir (learner.base): the runner loads it
    runner_supplied = {}
    if checked.base is not None:
        runner_supplied["base_policy"] = load_base(checked.base, env)
    try:  # the settings are checked plain values: the class is called, nothing else is built
        learner = cls(
            env=env,
            rng=np.random.default_rng(cfg.seed),
            partition=checked.partition,
            **runner_supplied,
            **checked.hyperparameters,
        )
    except (TypeError, ValueError) as err:  # a relation between settings (eps_end <= eps_start)
        raise ConfigError(f"learner {name!r} ({cls.__name__}): {err}") from err
    if checked.init is not None:  # zero-shot on this team, or fine-tuning from there
        try:
            load_learner(learner, checked.init / LEARNER_DIR)
        except RunDirError as err:
            raise ConfigError(f"init: {err}") from None
    limit_growth(learner, checked.memory_limit)  # tables grow with the states met (qtable.py)
    return RunSetup(
        name,
        checked.system,
        env.params,
        checked.partition,
        checked.active_tasks,
        env,
        learner,
        family=checked.family,
        env_overrides=checked.env_overrides,
    )


def family_env(run: RunSetup, episode: int, seed: int) -> AuctionEnv:
    """The training env of one episode on a family of teams: team ``episode`` of the family.

    Args:
        run: The built run (its ``family``, training batch and ``env.*``).
        episode: The training episode (1, 2, ...), which names the team.
        seed: The run seed.

    Returns:
        ``B`` copies of the team; copy ``b`` has env seed
        ``seed * SEED_STRIDE + FAMILY_SEEDS + episode * B + b``.
    """
    assert run.family is not None
    team = run.family.team(episode)
    batch = run.env.batch_size
    return AuctionEnv(
        team,
        team_params(team, run.env_overrides or {}),
        batch_size=batch,
        seed=seed * SEED_STRIDE + FAMILY_SEEDS + episode * batch,
    )


def build_saved_run(cfg: DictConfig, run_dir: Path, name: str | None) -> RunSetup:
    """:func:`build_run` from a run dir's own config: a setting it refuses names the file.

    Raises:
        RunDirError: naming ``.hydra/config.yaml`` and the setting.
    """
    try:
        return build_run(cfg, name=name)
    except UserError as err:
        raise RunDirError(f"{run_dir / CONFIG_FILE}: {err}") from None


def _check_saved_config(cfg: DictConfig, run_dir: Path) -> None:
    """Validate a run dir's own config; a refusal names ``.hydra/config.yaml``.

    Raises:
        RunDirError: naming the file and the setting.
    """
    try:
        validate_config(cfg)
    except UserError as err:
        raise RunDirError(f"{run_dir / CONFIG_FILE}: {err}") from None


def _blame(arguments: dict[str, tuple[str, Any]], message: str) -> str:
    """A refusal of the run config with the command line's arguments, said of the arguments.

    A message about the key an argument sets (``eval.batch_size: ...``) names the argument
    instead (``batch_size: ...``); any other is prefixed with every argument given.
    """
    for name, (key, _) in arguments.items():
        if message.startswith(f"{key}:"):
            return f"{name}:{message[len(key) + 1 :]}"
    given = " ".join(f"{name}={value}" for name, (_, value) in arguments.items())
    return f"{given}: {message}"


def _write_refusal(run_dir: Path, cfg: DictConfig, reason: str) -> None:
    """``refused.json`` (``reports/collect.py``): this run was refused, and why.

    Refused up front (:class:`ResourceRefusal`), or stopped in training because its tables
    outgrew ``limits.memory_gb`` (:class:`TableGrowthError`).
    """
    run_dir.mkdir(parents=True, exist_ok=True)
    record = {
        "learner": hydra_choice("learner", "?"),
        "system": hydra_choice("system", "?"),
        "seed": int(cfg.seed),
        "reason": reason,
    }
    write_json(run_dir / REFUSED_FILE, record)


@releases_run_dirs
def train(cfg: DictConfig, run_dir: Path | str | None = None) -> dict[str, Any]:
    """Train the configured learner, evaluate it and greedy, write ``metrics.json``.

    With ``resume=<run dir>`` the run in that dir continues from its last checkpoint, built from
    its own ``.hydra/config.yaml`` (read as data, see ``runners/checkpoint.py``), and ends as
    the uninterrupted run would have.

    Args:
        cfg: The composed run config (conf/config.yaml).
        run_dir: Output folder; default: the Hydra run dir (the ``resume`` dir when resuming).

    Returns:
        The content of ``metrics.json``.

    Raises:
        ValueError: on an invalid config or run dir, before anything is written.
        SystemExit: with code 130 after Ctrl-C, 143 after SIGTERM (a checkpoint is saved first).
    """
    resources = RunResources().start()  # wall, CPU time and peak memory of the run (build to eval)
    resume = cfg.get("resume")
    if resume:
        run_dir = Path(resume)
        _check_resume_overrides()
        claim_run_dir(run_dir, resume=True)  # locked for this process (runners/run_dir.py)
        choices = run_choices(run_dir)
        progress = cfg.train.progress_bar
        cfg = read_run_config(run_dir)
        with open_dict(cfg):
            cfg.resume = str(run_dir)
            cfg.train.progress_bar = progress
        run = build_saved_run(cfg, run_dir, name=choices.get("learner"))
        check_workers_available(cfg)
        system_name = choices.get("system", run.system.name)
    else:
        run_dir = Path(run_dir if run_dir is not None else HydraConfig.get().runtime.output_dir)
        try:
            run = build_run(cfg)
        except ResourceRefusal as refusal:
            # a sweep's job keeps it as data (its report shows the reason); a single run is
            # refused like any bad input: one line, no run dir left
            if HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN:
                _write_refusal(run_dir, cfg, str(refusal))
            raise
        check_workers_available(cfg)
        system_name = hydra_choice("system", run.system.name)
        claim_run_dir(run_dir, resume=False)  # made and locked (runners/run_dir.py)
    # checked by validate_config; absent in runs written before checkpoints existed: none
    every = cfg.train.checkpoint_every
    run.checkpoint = TrainingCheckpoint(
        run.learner,
        run_dir,
        every,
        resume=bool(resume),
        episodes=cfg.train.episodes,
        resources=resources,
    )
    logger.info(  # the system by the name metrics.json gives it
        "learner %s (%s) on %s, seed %d, run dir %s",
        run.name,
        type(run.learner).__name__,
        system_name,
        cfg.seed,
        run_dir,
    )
    try:  # the loop times itself (train.wall_s), a resumed run's earlier processes included
        train_info = training_loop(type(run.learner))(run, cfg, run_dir)
    except TrainingInterrupted as stop:
        if stop.checkpoint is None:
            logger.error("interrupted before the first checkpoint: nothing to resume from")
        else:
            logger.error(
                "interrupted: checkpoint saved in %s; continue with: "
                "python scripts/train.py resume=%s",
                stop.checkpoint,
                run_dir,
            )
        raise SystemExit(128 + stop.signum) from None  # the shell's code of the signal
    except (TableGrowthError, MemoryError) as err:  # the tables outgrew the machine mid-run
        where = f"{run.name} on system {system_name} ({run.system.n_robots} robots)"
        reason = (
            f"{where}: stopped in training: {err}; use smaller sub-groups "
            "(partition.max_group_size), fewer train.episodes or train.batch_size, "
            "or raise limits.memory_gb"
        )
        _write_refusal(run_dir, cfg, reason)  # kept as data: a sweep's report shows the reason
        raise TableGrowthError(reason) from None
    if run.learner.trains():
        save_learner(run.learner, run_dir / LEARNER_DIR)
    results = evaluate_run(run, cfg)
    metrics = {
        "learner": learner_record(run),
        "system": system_name,
        "seed": int(cfg.seed),
        **results,
        "train": train_info,
        "learning_space": {k: int(v) for k, v in run.learner.learning_space().items()},
        "resources": resources.result(),
    }
    if run.partition is not None:
        write_json(run_dir / "partition.json", run.partition.to_json())
    write_json(run_dir / METRICS_FILE, metrics, exclusive=True)
    finish_run(run_dir, metrics)  # the final metrics to the run's tracker (logger=wandb...)
    run.checkpoint.finish()
    logger.info("wrote %s", run_dir / METRICS_FILE)
    return metrics


def learner_record(run: RunSetup) -> dict[str, str]:
    """metrics.json's ``learner`` block: the config's name, the class's label and kind.

    Reports label a run from it without importing the learner.
    """
    cls = type(run.learner)
    return {"name": run.name, "label": cls.label, "kind": cls.kind}


RESUME_KEEPS = ("resume", "train.progress_bar")  # overrides allowed with resume=


def _check_resume_overrides() -> None:
    """Resuming takes the run's own config: refuse other overrides instead of ignoring them."""
    if not HydraConfig.initialized():
        return
    given = [str(o) for o in HydraConfig.get().overrides.task]
    other = [o for o in given if o.split("=")[0].lstrip("+~") not in RESUME_KEEPS]
    if other:
        raise ConfigError(f"resume= continues a run with its own config; drop {other}")


def load_run(run_dir: Path | str, cfg: DictConfig | None = None) -> RunSetup:
    """A finished run rebuilt from its config, read as data, with its saved learner state.

    Re-evaluation (:func:`evaluate_checkpoint`) and a planner playing a trained run as its base
    policy (``learner.base=<run dir>`` of ``rollout``) load a run this one way.

    Args:
        run_dir: The run dir of ``scripts/train.py`` (holding ``.hydra/`` and ``learner/``).
        cfg: The run's config as :func:`~mrta_rl.runners.run_config.read_run_config` read it,
            possibly with its ``eval`` settings changed; default: read here.

    Returns:
        The run, its learner trained as saved (built on a training env of the run's team).

    Raises:
        RunDirError: on a missing, tampered or damaged run dir (a ``ValueError``), or a setting
            of its config that is refused (naming ``.hydra/config.yaml``).
    """
    run_dir = Path(run_dir)
    cfg = read_run_config(run_dir) if cfg is None else cfg
    run = build_saved_run(cfg, run_dir, name=run_choices(run_dir).get("learner"))
    if run.learner.trains():
        load_learner(run.learner, run_dir / LEARNER_DIR)
    return run


def load_base(run_dir: Path, env: AuctionEnv) -> Learner:
    """The trained learner of the run dir a learner plays as its base (``learner.base``).

    The run is rebuilt as re-evaluation rebuilds it (:func:`load_run`), so its learner plays
    as it was trained. A learner that holds nothing of one team (a family's policy) plays the
    team of ``env`` (:meth:`~mrta_rl.learners.base.Learner.play_on`), as ``init=`` plays it
    zero-shot; any other must have been trained on that team (tables and weights are indexed by
    robot and task type). :func:`~mrta_rl.runners.validation.check_base` has checked the run
    dir and its chain of bases.

    Args:
        run_dir: The base's run dir of ``scripts/train.py``.
        env: The env of the run that plays the base.

    Returns:
        The base's learner, trained as saved.

    Raises:
        ConfigError: naming ``learner.base`` and the culprit (a run dir refused, or of another
            team).
    """
    key = "learner.base"
    try:
        learner = load_run(run_dir).learner
    except UserError as err:
        raise ConfigError(f"{key}: {err}") from None
    if type(learner).fits_any_team(learner.hp):
        learner.play_on(env)
        return learner
    system = env.system
    theirs, ours = team_record(learner.env.system), team_record(system)
    for part in ("robots", "task_types", "willingness"):
        if theirs[part] != ours[part]:
            raise ConfigError(
                f"{key}: {run_dir} is a run of another team ({learner.env.system.name}, not "
                f"{system.name}): its {part} [{short_list(theirs[part], quote=True)}] are not "
                f"[{short_list(ours[part], quote=True)}]"
            )
    return learner


def evaluate_checkpoint(
    checkpoint: Path | str,
    episodes: int | None = None,
    batch_size: int | None = None,
    split: str | None = None,
) -> dict[str, Any]:
    """Re-evaluate a finished run: rebuild it from its ``.hydra/config.yaml``, load the learner.

    The run dir is read as data (``runners/checkpoint.py``): its config must name a learner
    class of this package with plain hyperparameters, and the saved state must fit the learner
    built for the run; otherwise nothing is evaluated. Writes ``eval_metrics.json`` in the run
    dir.

    Args:
        checkpoint: The run dir of ``scripts/train.py`` (holding ``.hydra/`` and ``learner/``).
        episodes: Evaluation episodes; default: the run's ``eval.episodes``.
        batch_size: Copies per evaluation round; default: the run's ``eval.batch_size``. Episode
            ``b`` of one round of ``batch_size >= episodes`` copies is copy ``b``'s first episode,
            the layout of a run evaluated with ``eval.batch_size`` = ``eval.episodes``.
        split: Evaluation streams, ``test`` or ``validation`` (``mrta_rl/splits.py``); default:
            the run's ``eval.split``.

    Returns:
        The content of ``eval_metrics.json`` (as metrics.json, without the training block).

    Raises:
        RunDirError: on a missing, tampered or damaged run dir (a ``ValueError``), or a setting
            of its config that is refused (naming ``.hydra/config.yaml``).
        ConfigError: if ``episodes``, ``batch_size`` or ``split`` make the run config refused
            (naming the argument).
        UserError: if ``eval_metrics.json`` could not be written in the run dir; checked first,
            before any work.
    """
    run_dir = Path(checkpoint)
    cfg = read_run_config(run_dir)
    check_output_file(run_dir / EVAL_METRICS_FILE, EVAL_METRICS_FILE)  # before any work
    arguments = {  # argument -> (key of the run config, value)
        name: (key, value)
        for name, key, value in (
            ("episodes", "eval.episodes", episodes),
            ("batch_size", "eval.batch_size", batch_size),
            ("eval.split", "eval.split", split),
        )
        if value is not None
    }
    if arguments:
        _check_saved_config(cfg, run_dir)  # a refusal names the file: the run's own settings
        if episodes is not None:
            cfg.eval.episodes = int(episodes)
        if batch_size is not None:
            cfg.eval.batch_size = int(batch_size)
        if split is not None:
            with open_dict(cfg):  # a run written before eval.split existed has no such key
                cfg.eval.split = str(split)
                cfg.eval.seed = None  # the split names the streams, not the seed recorded
        try:  # now a refusal is the arguments' doing: it names them
            validate_config(cfg)
        except UserError as err:
            raise ConfigError(_blame(arguments, str(err))) from None
    choices = run_choices(run_dir)
    run = load_run(run_dir, cfg)
    metrics = {
        "learner": learner_record(run),
        "system": choices.get("system", run.system.name),
        "seed": int(cfg.seed),
        "checkpoint": str(run_dir),
        **evaluate_run(run, cfg),
        "learning_space": {k: int(v) for k, v in run.learner.learning_space().items()},
    }
    write_json(run_dir / EVAL_METRICS_FILE, metrics)
    return metrics

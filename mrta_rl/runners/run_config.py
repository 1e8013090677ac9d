"""A run dir's config, read as data: never executed, every refusal naming the key.

A run dir may come from anyone (a shared drive, a download), so reading one never executes what
it says. :func:`read_run_config` accepts a ``.hydra/config.yaml`` only if its learner is a
:class:`~mrta_rl.learners.Learner` class of this package or one the user made known
(:func:`known_learner`: imported by their own code, or declared by an installed distribution in
the ``mrta_rl.learners`` entry-point group) with plain scalar or list hyperparameters, its logger
a curve logger of this package, and everything else plain data (no ``_target_``, no
interpolation); anything else is refused with a message naming the key.

The run settings' values have one home, the shipped ``conf/config.yaml``: a saved config that
lacks one of its ``train``, ``eval`` or ``limits`` keys (a run written before the key existed)
reads it as that file's value (:data:`SHIPPED_RUN_BLOCKS`).
"""

from __future__ import annotations

import importlib
import importlib.metadata
import logging
import os
import secrets
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from mrta_rl.checked_files import YamlSyntaxError, read_config, read_yaml_text
from mrta_rl.conf_paths import conf_dir
from mrta_rl.learners import Learner
from mrta_rl.metrics.run_logger import RunLogger
from mrta_rl.run_layout import CONFIG_FILE, HYDRA_FILE, RunDirError

logger = logging.getLogger(__name__)

PACKAGE = "mrta_rl."
LEARNER_ENTRY_POINTS = "mrta_rl.learners"  # group of the learner classes of other distributions
SCALARS = (str, int, float, bool, type(None))
SHIPPED_RUN_BLOCKS = ("train", "eval", "limits")  # run settings a saved config may lack


# ---------------------------------------------------------------------------------- run dirs
RUN_ID = f"{os.getpid() % 0x10000:04x}{secrets.token_hex(2)}"  # this process's run dir suffix


def register_resolvers() -> None:
    """OmegaConf resolvers of the run dir pattern in ``conf/config.yaml`` (``hydra.run.dir``).

    * ``${run_id:}``: a short id unique to this process (pid and random bits): runs started in
      the same second get different dirs.
    * ``${resume_or:<resume>,<default>}``: the ``resume`` dir if given, else ``default``.
    * ``${unless_resume:<resume>,<value>}``: ``value``, or null when resuming (so a resumed run
      does not overwrite its ``.hydra/`` snapshot with the resume command's config).
    """
    resolvers = {
        "run_id": lambda: RUN_ID,
        "resume_or": lambda resume, default: str(resume) if resume else default,
        "unless_resume": lambda resume, value: None if resume else value,
    }
    for name, function in resolvers.items():
        if not OmegaConf.has_resolver(name):
            OmegaConf.register_new_resolver(name, function)


# ---------------------------------------------------------------------------------- config
def package_class(target: Any, base: type, what: str, where: str) -> type:
    """The class ``target`` names, if it is a subclass of ``base`` defined in this package.

    Only modules of ``mrta_rl`` are imported, so a tampered name runs no foreign code.

    Args:
        target: The ``_target_`` value.
        base: The required base class.
        what: What the class is for (in messages: ``learner``, ``logger``).
        where: ``<file>: <key>`` for messages.

    Returns:
        The class.

    Raises:
        RunDirError: if the name is not a ``mrta_rl`` class derived from ``base``.
    """
    if not isinstance(target, str) or not target.startswith(PACKAGE) or "." not in target:
        raise RunDirError(f"{where}: {target!r} is not a {what} class of {PACKAGE.rstrip('.')}")
    module_name, _, name = target.rpartition(".")
    try:
        cls = getattr(importlib.import_module(module_name), name)
    except (ImportError, AttributeError) as err:
        raise RunDirError(f"{where}: unknown {what} class {target!r} ({err})") from err
    if not (isinstance(cls, type) and issubclass(cls, base)):
        raise RunDirError(f"{where}: {target!r} is not a {what} ({base.__name__} subclass)")
    return cls


def known_learner(target: str) -> type[Learner] | None:
    """A learner class outside this package that the user made known, or None.

    Known: a :class:`~mrta_rl.learners.Learner` subclass already imported in this process (the
    user's own code, imported before the run dir is read), or one an installed distribution
    declares in the ``mrta_rl.learners`` entry-point group (``name = "module:Class"``). No other
    module is imported.

    Args:
        target: The ``_target_`` value (``my_pkg.my_learner.MyLearner``).

    Returns:
        The class, or None.
    """
    pending = list(Learner.__subclasses__())
    while pending:
        cls = pending.pop()
        if f"{cls.__module__}.{cls.__qualname__}" == target:
            return cls
        pending.extend(cls.__subclasses__())
    for entry in importlib.metadata.entry_points(group=LEARNER_ENTRY_POINTS):
        if entry.value.replace(":", ".") == target:
            cls = entry.load()
            return cls if isinstance(cls, type) and issubclass(cls, Learner) else None
    return None


def _check_data(value: Any, key: str, source: Path) -> None:
    """Plain data only: mappings without special keys, lists, scalars without interpolation."""
    if isinstance(value, dict):
        for k, v in value.items():
            if str(k).startswith("_"):
                raise RunDirError(
                    f"{source}: {key}.{k}: special key refused (a run dir is data, never code)"
                )
            _check_data(v, f"{key}.{k}" if key else str(k), source)
    elif isinstance(value, list):
        for i, item in enumerate(value):
            _check_data(item, f"{key}[{i}]", source)
    elif isinstance(value, str) and "${" in value:
        raise RunDirError(f"{source}: {key}: interpolation {value!r} refused (plain values only)")
    elif not isinstance(value, SCALARS):
        raise RunDirError(f"{source}: {key}: unexpected value {value!r}")


def _check_component(
    block: Any, key: str, base: type, source: Path, *, flat: bool, known: bool = False
) -> None:
    """A ``_target_`` block: a package class, ``_partial_: true``, plain (scalar/list) settings.

    With ``known``, a class outside the package is accepted if the user made it known
    (:func:`known_learner`).
    """
    if not isinstance(block, dict):
        raise RunDirError(f"{source}: {key}: expected a mapping with _target_, got {block!r}")
    target, where = block.get("_target_"), f"{source}: {key}._target_"
    if known and isinstance(target, str) and not target.startswith(PACKAGE):
        if known_learner(target) is None:
            raise RunDirError(
                f"{where}: {target!r} is not a learner class of mrta_rl, nor one your code "
                f"imported or a distribution declares (entry points {LEARNER_ENTRY_POINTS}); "
                "a run dir is data, its classes are never imported"
            )
    else:
        package_class(target, base, key, where)
    if block.get("_partial_") is not True:
        raise RunDirError(f"{source}: {key}._partial_: must be true")
    for name, value in block.items():
        if name in ("_target_", "_partial_"):
            continue
        if flat and isinstance(value, dict):
            raise RunDirError(
                f"{source}: {key}.{name}: a mapping is refused; hyperparameters are plain scalars "
                f"or lists (got {value!r})"
            )
        _check_data({name: value}, key, source)


def check_run_config(config: dict[str, Any], source: Path) -> None:
    """Refuse anything in a run's config that is not plain data (module docstring).

    Args:
        config: The config as a plain container (``resolve=False``).
        source: Its file, for messages.

    Raises:
        RunDirError: naming the first offending key.
    """
    if not isinstance(config, dict):
        raise RunDirError(f"{source}: not a mapping of settings")
    for key in ("learner", "logger"):  # the rest is checked by validate_config
        if key not in config:
            raise RunDirError(f"{source}: {key}: missing")
    for key, value in config.items():
        if key == "learner":
            _check_component(value, "learner", Learner, source, flat=True, known=True)
        elif key == "logger":
            _check_component(value, "logger", RunLogger, source, flat=True)
        else:
            _check_data({key: value}, "", source)


def read_run_config(run_dir: Path | str) -> DictConfig:
    """The run's ``.hydra/config.yaml``, checked to hold only plain data (module docstring).

    Args:
        run_dir: A run dir of ``scripts/train.py``.

    Returns:
        The config, safe to build the run from.

    Raises:
        RunDirError: if the file is missing, unreadable or holds anything but plain data (its
            settings are checked when the run is built: ``train.build_saved_run``).
    """
    run_dir = Path(run_dir)
    path = run_dir / CONFIG_FILE
    if not path.exists():
        raise RunDirError(f"{run_dir} is not a run dir of scripts/train.py: no {path}")
    cfg = read_config(path)  # size, encoding, depth, aliases: before OmegaConf expands it
    check_run_config(OmegaConf.to_container(cfg, resolve=False), path)
    shipped = read_config(conf_dir() / "config.yaml")
    for block in SHIPPED_RUN_BLOCKS:
        if OmegaConf.is_dict(cfg.get(block)):  # a block that is missing or not one is refused
            for key, value in shipped[block].items():
                cfg[block].setdefault(key, value)
    return cfg  # type: ignore[return-value]


def run_choices(run_dir: Path) -> dict[str, str]:
    """Config-group choices recorded in ``.hydra/hydra.yaml`` (``learner`` -> ``greedy``)."""
    path = Path(run_dir) / HYDRA_FILE
    if not path.exists():
        return {}
    try:  # a hostile file is refused; a merely damaged one loses the names
        text = read_yaml_text(path)
    except YamlSyntaxError as err:
        logger.warning("config-group choices unreadable: %s", err)
        return {}
    try:
        choices = OmegaConf.select(OmegaConf.create(text), "hydra.runtime.choices", default={})
        return {str(k): str(v) for k, v in dict(choices).items() if isinstance(v, str | int)}
    except Exception as err:  # a damaged hydra.yaml only loses the names
        logger.warning("%s: config-group choices unreadable (%s)", path, err)
        return {}

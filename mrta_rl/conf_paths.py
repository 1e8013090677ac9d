"""Where the shipped configs are, and which yaml file a system name or path means.

The repository keeps its configs in ``conf/`` at the top level; pyproject.toml ships that folder
inside the package as ``mrta_rl.conf``, so a wheel carries it and an editable install maps it
back to ``conf/``. :func:`conf_dir` finds it in either case, and in a source checkout used
without installing it (``PYTHONPATH=<checkout>``), where it is the checkout's own ``conf/``.

A system is named by a file of ``conf/system/`` (``system2``) or given as the path of a team
yaml anywhere (``/path/to/team.yaml``); :func:`system_file` turns both into the file, with one
message for a name or path that has none. The commands, the Gymnasium and PettingZoo views and
the BenchMARL task all go through it.

A learner is a file of the ``learner/`` group: :func:`learner_files` lists them over the config
search path and :func:`learner_block` reads one as Hydra composes it (with the learner files it
extends). Importing their classes is :mod:`mrta_rl.learners.registry`'s; this module imports no
learner and no env, so that every floor of the package may ask where the configs are (a learner's
defaults are its yaml's, ``Learner.defaults``).
"""

from __future__ import annotations

import importlib.util
import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from mrta_rl.checked_files import read_yaml
from mrta_rl.config import UserError
from mrta_rl.config_guard import check_yaml_file

CONF_PACKAGE = "mrta_rl.conf"
SYSTEM_SUFFIXES = (".yaml", ".yml")  # a system argument ending so is a path, anything else a name


def conf_dir() -> Path:
    """The folder of the shipped configs (``config.yaml``, ``system/``, ``learner/``...).

    Returns:
        The ``conf/`` of the source checkout the package runs from (a ``pyproject.toml`` beside
        the package: so a checkout on ``PYTHONPATH`` reads its own configs), else the installed
        package ``mrta_rl.conf`` (a wheel, or an editable install's mapping).
    """
    checkout = Path(__file__).resolve().parents[1]
    if (checkout / "pyproject.toml").is_file() and (checkout / "conf" / "config.yaml").is_file():
        return checkout / "conf"
    spec = importlib.util.find_spec(CONF_PACKAGE)
    if spec is None or not spec.submodule_search_locations:
        raise RuntimeError(f"the package {CONF_PACKAGE} is missing: reinstall mrta_rl")
    return Path(next(iter(spec.submodule_search_locations)))


def system_dir() -> Path:
    """The folder of the shipped systems (``conf/system``)."""
    return conf_dir() / "system"


def shipped_systems() -> list[str]:
    """Names of the shipped systems, sorted (``random``, ``system1``, ``system2``)."""
    return sorted(p.stem for p in system_dir().glob("*.yaml"))


def is_system_path(system: str | os.PathLike) -> bool:
    """True if ``system`` is a yaml path rather than the name of a shipped system."""
    return Path(system).suffix in SYSTEM_SUFFIXES


def system_file(system: str | os.PathLike) -> Path:
    """The yaml file of a system name (``system2``) or path (``team.yaml``, ``/a/b/team.yml``).

    Args:
        system: A shipped system's name, or the path of a team yaml (relative to the working
            directory, or absolute).

    Returns:
        The file (absolute), which exists.

    Raises:
        UserError: naming the system, the file looked for and the shipped systems, or the file
            and the bound it passes (size, encoding, nesting, aliases: ``mrta_rl/config_guard.py``).
    """
    path = Path(system).expanduser() if is_system_path(system) else system_dir() / f"{system}.yaml"
    if not path.exists():
        raise UserError(
            f"unknown system {str(system)!r}: no file {path}; known: {shipped_systems()} "
            "or the path of a team yaml"
        )
    check_yaml_file(path)
    return path.resolve()


def learner_files(config_dirs: Iterable[str | os.PathLike] = ()) -> dict[str, Path]:
    """The learners of the config search path: name (the yaml stem) -> its file.

    Args:
        config_dirs: User config dirs (``--config-dir``, ``hydra.searchpath``) after the
            shipped ``conf/``; a learner's name is its file's stem in any ``learner/`` of them.

    Returns:
        Every learner, sorted by name; where two dirs hold one name, the shipped or the first
        given file.

    Raises:
        UserError: if a given config dir does not exist.
    """
    files: dict[str, Path] = {}
    for folder in (conf_dir(), *(Path(d).expanduser() for d in config_dirs)):
        if not folder.is_dir():
            raise UserError(f"config dir {str(folder)!r}: no such directory")
        for path in sorted((folder / "learner").glob("*.yaml")):
            files.setdefault(path.stem, path.resolve())
    return dict(sorted(files.items()))


def learner_block(name: str, files: dict[str, Path], seen: tuple[str, ...] = ()) -> dict[str, Any]:
    """A learner yaml's content over that of the learners it extends, as Hydra composes them.

    ``defaults: [qmix, _self_]`` in ``learner/qmix_set.yaml`` composes ``learner/qmix.yaml``
    under it: the entries of its defaults list that name a learner file come first, in order,
    then the file's own keys (its ``_target_`` included). Other entries (``/budget@_global_``)
    are no learner's and are left out, and so is the defaults list itself.

    Args:
        name: The learner's name (a key of ``files``).
        files: The learner files (:func:`learner_files`).
        seen: The learners on the way here (a file that extends itself is read once).

    Returns:
        The composed keys; empty if the file holds no mapping.
    """
    block: Any = read_yaml(files[name])
    if not isinstance(block, dict):
        return {}
    entries = block.get("defaults") or []
    parents = [e.removesuffix(".yaml") for e in entries if isinstance(e, str) and e != "_self_"]
    composed: dict[str, Any] = {}
    for parent in parents:
        if parent in files and parent not in (*seen, name):
            composed.update(learner_block(parent, files, (*seen, name)))
    composed.update({key: value for key, value in block.items() if key != "defaults"})
    return composed


def learner_settings(block: dict[str, Any]) -> dict[str, Any]:
    """A learner block's settings: its keys but Hydra's (``_target_``, ``_partial_``...)."""
    return {
        key: value for key, value in block.items() if not key.startswith("_") and key != "defaults"
    }

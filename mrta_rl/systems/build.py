"""Build a system from its config: a table, a random team or a family of teams, in one place.

A system config (``conf/system/*.yaml`` or a team file) takes one of three forms: a table of
robots (:meth:`~mrta_rl.systems.robot_system.RobotSystem.from_table`), a reproducible random team
(:func:`~mrta_rl.systems.robot_system.random_system`) or a family of teams
(:mod:`mrta_rl.systems.family`). This module reads the form and builds it; it imports both
``robot_system`` and ``family``, which import nothing of each other's building.
"""

from __future__ import annotations

import inspect
from collections.abc import Mapping
from typing import Any

from mrta_rl.config import short_list
from mrta_rl.systems.family import EVAL_TEAM, build_family
from mrta_rl.systems.robot_system import RobotSystem, SystemConfigError, random_system

_TABLE_KEYS = {"name", "robots", "task_types", "env"}
_RANDOM_KEYS = {"name", "n_robots", "n_task_types", "density", "seed", "scale_auction", "env"}


def system_shape(cfg: Mapping[str, Any]) -> tuple[int, int] | None:
    """Robots and task types a system config describes, read without building anything.

    Args:
        cfg: The ``system`` config group content (table, random or family form).

    Returns:
        ``(m, n)``, for a family its largest team's; for a table, ``n`` counts the distinct task
        type names. None when the config is malformed (:func:`build_system` then names what is
        wrong).
    """
    if "family" in cfg:  # the largest team the family can draw
        try:
            family = build_family(cfg)
        except SystemConfigError:
            return None
        return family.largest if family is not None else None
    if "robots" in cfg:
        robots = cfg["robots"]
        if not isinstance(robots, Mapping) or not robots:
            return None
        names = set()
        for spec in robots.values():
            if isinstance(spec, (Mapping, list, tuple)):
                names.update(str(t) for t in spec)
        return len(robots), len(names)
    default = inspect.signature(random_system).parameters["n_task_types"].default
    m, n = cfg.get("n_robots"), cfg.get("n_task_types", default)
    if all(isinstance(v, int) and not isinstance(v, bool) and v >= 1 for v in (m, n)):
        return int(m), int(n)  # type: ignore[arg-type]
    return None


def build_system(cfg: Mapping[str, Any]) -> RobotSystem:
    """Build a system from a system config (table, random or family form: module docstring).

    Args:
        cfg: The ``system`` config group content (a dict or OmegaConf mapping).

    Returns:
        The validated system; for a family of teams (``family:``, ``systems/family.py``), the
        team its runs are evaluated on.

    Raises:
        SystemConfigError: on unknown keys or malformed content, naming the culprit.
    """
    if not isinstance(cfg, Mapping):  # an empty file reads as None, a text file as a string
        shown = "empty" if cfg is None else f"a {type(cfg).__name__}"
        raise SystemConfigError(
            f"a team must be a mapping with 'robots' (a table) or 'n_robots' (a random team), "
            f"got {shown}"
        )
    cfg = dict(cfg)
    name = str(cfg.get("name", "unnamed"))
    if "family" in cfg:  # a family of teams: the run plays its evaluation team
        return build_family(cfg).team(EVAL_TEAM)
    if "robots" in cfg:
        unknown = set(cfg) - _TABLE_KEYS
        if unknown:
            shown = short_list(sorted(unknown, key=str), quote=True)
            raise SystemConfigError(
                f"system {name!r}: unknown keys [{shown}] (allowed: {sorted(_TABLE_KEYS)})"
            )
        return RobotSystem.from_table(name, cfg["robots"], cfg.get("task_types"), cfg.get("env"))
    if "n_robots" in cfg:
        unknown = set(cfg) - _RANDOM_KEYS
        if unknown:
            shown = short_list(sorted(unknown, key=str), quote=True)
            raise SystemConfigError(
                f"system {name!r}: unknown keys [{shown}] (allowed: {sorted(_RANDOM_KEYS)})"
            )
        sizes = {k: v for k, v in cfg.items() if k not in ("name", "env")}
        return random_system(**sizes, name=name, env=cfg.get("env"))
    raise SystemConfigError(
        f"system {name!r}: needs either 'robots' (a table) or 'n_robots' (a random team)"
    )

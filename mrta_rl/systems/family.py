"""A family of teams: a distribution of random teams, one drawn per training episode.

A system config with a ``family:`` block (``conf/system/family.yaml``) describes teams instead of
one team. Team ``k`` of the family is :func:`~mrta_rl.systems.random_system` with its size,
number of task types, density and team seed drawn from ``default_rng([seed, k])``, and each
robot-task willingness drawn uniformly from ``willingness`` (both ends 1: willingness 1.0, as
System-I and II). Training episode ``e`` (1, 2, ...) plays team ``e``; the run is evaluated on team
:data:`EVAL_TEAM`, which no training episode plays. A learner that holds nothing of one team
(``Learner.any_team``) trains on it; its state then plays any team (``init=<run dir>``).
"""

from __future__ import annotations

import reprlib
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mrta_rl.config import short_list
from mrta_rl.systems.robot_system import (
    RobotSystem,
    SystemConfigError,
    env_parameters,
    random_system,
)

EVAL_TEAM = 0  # the team a family run is evaluated on; training episode e plays team e >= 1
FAMILY_KEYS = {"name", "family", "seed", "scale_auction", "env"}  # keys of a family config
RANGES = ("n_robots", "n_task_types", "density", "willingness")  # keys of its family: block


@dataclass(frozen=True)
class TeamFamily:
    """Random teams with their sizes and densities drawn from ranges (module docstring).

    Attributes:
        n_robots: ``[lo, hi]`` robots per team (integers, both ends included).
        n_task_types: ``[lo, hi]`` task types per team (integers, both ends included).
        density: ``[lo, hi]`` probability that a robot can do a task type.
        willingness: ``[lo, hi]`` willingness of each robot-task pair, in (0, 1].
        seed: Seed of the draws; the same family and index give the same team.
        scale_auction: Scale slots and queue with each team (``random_system``).
        name: Family name; team ``k`` is named ``<name>[k]``.
        env: Per-system environment parameters, for every team.
    """

    n_robots: tuple[int, int]
    n_task_types: tuple[int, int]
    density: tuple[float, float]
    willingness: tuple[float, float] = (1.0, 1.0)
    seed: int = 0
    scale_auction: bool = True
    name: str = "family"
    env: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for key, low, high, whole in (
            ("n_robots", 1, None, True),
            ("n_task_types", 1, None, True),
            ("density", 0.0, 1.0, False),
            ("willingness", 0.0, 1.0, False),
        ):
            value = getattr(self, key)
            ok = isinstance(value, (list, tuple)) and len(value) == 2
            ok = ok and all(
                isinstance(v, int if whole else (int, float)) and not isinstance(v, bool)
                for v in value
            )
            ok = ok and value[0] <= value[1] and value[0] >= low
            ok = ok and (high is None or value[1] <= high)
            ok = ok and (key != "willingness" or value[0] > 0)
            if not ok:
                kind = "integers" if whole else "numbers"
                bounds = f">= {low}" if high is None else f"in [{low}, {high}]"
                if key == "willingness":
                    bounds = "in (0, 1]"
                raise SystemConfigError(
                    f"system {self.name!r}: family.{key} must be [lo, hi] {kind} {bounds} with "
                    f"lo <= hi, got {value!r}"
                )
            object.__setattr__(self, key, tuple(value))
        if not (isinstance(self.seed, int) and not isinstance(self.seed, bool) and self.seed >= 0):
            raise SystemConfigError(f"system {self.name!r}: seed must be an integer >= 0")
        if not isinstance(self.scale_auction, bool):
            raise SystemConfigError(
                f"system {self.name!r}: scale_auction must be true or false, "
                f"got {reprlib.repr(self.scale_auction)}"
            )

    @property
    def largest(self) -> tuple[int, int]:
        """``(m, n)`` of the largest team the family can draw."""
        return self.n_robots[1], self.n_task_types[1]

    def team(self, index: int) -> RobotSystem:
        """Team ``index`` of the family (training episode ``index``; :data:`EVAL_TEAM`).

        Args:
            index: Which team, >= 0.

        Returns:
            The team, named ``<name>[index]``.
        """
        rng = np.random.default_rng([self.seed, index])
        m = int(rng.integers(self.n_robots[0], self.n_robots[1] + 1))
        n = int(rng.integers(self.n_task_types[0], self.n_task_types[1] + 1))
        density = float(rng.uniform(*self.density))
        team_seed = int(rng.integers(2**31))
        team = random_system(
            m, n, density, team_seed, self.scale_auction, f"{self.name}[{index}]", self.env
        )
        low, high = self.willingness
        if low == high == 1.0:
            return team
        pairs = team.willingness > 0
        willingness = np.where(pairs, rng.uniform(low, high, pairs.shape), 0.0)
        return RobotSystem(
            team.name, team.robots, team.task_types, willingness, {}, team.env_overrides
        )


def build_family(cfg: Mapping[str, Any]) -> TeamFamily | None:
    """The family of a system config with a ``family:`` block, else None.

    Raises:
        SystemConfigError: on unknown keys or ranges out of bounds, naming them.
    """
    if "family" not in cfg:
        return None
    name = str(cfg.get("name", "family"))
    unknown = set(cfg) - FAMILY_KEYS
    if unknown:
        shown = short_list(sorted(unknown, key=str), quote=True)
        raise SystemConfigError(
            f"system {name!r}: unknown keys [{shown}] (allowed: {sorted(FAMILY_KEYS)})"
        )
    ranges = cfg["family"]
    if not isinstance(ranges, Mapping):
        raise SystemConfigError(f"system {name!r}: family must be a mapping of ranges")
    unknown = set(ranges) - set(RANGES)
    missing = set(RANGES[:3]) - set(ranges)
    if unknown or missing:
        shown = short_list(sorted(unknown, key=str), quote=True)
        raise SystemConfigError(
            f"system {name!r}: family has unknown keys [{shown}] or lacks "
            f"{sorted(missing)} (keys: {', '.join(RANGES)}; willingness is optional)"
        )
    return TeamFamily(
        **{key: ranges[key] for key in RANGES if key in ranges},
        seed=cfg.get("seed", 0),
        scale_auction=cfg.get("scale_auction", True),
        name=name,
        env=env_parameters(name, cfg.get("env")),
    )

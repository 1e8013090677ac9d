"""RobotSystem: robots R_i, task types T_j, task sets Gamma_i, willingness d_ij (paper §4, eqs 5-6).

A system file (``conf/system/*.yaml``) is plain data::

    name: system1
    robots:                  # robot -> task types it can do (willingness 1.0) ...
      R1: [T1, T4, T5]
      R2: {T2: 0.9, T4: 1.0} # ... or task type -> willingness d in (0, 1]
    task_types:              # optional per-type duration ranges overriding the env defaults
      T2: {duration_low: [3, 6], duration_high: [6, 12]}
    env: {arrival_rate: 2.0} # optional per-system environment parameters

or describes a reproducible random team (``n_robots``, ``n_task_types``, ``density``, ``seed``).
Every check runs at construction, so a malformed file fails before any work starts.

Names are labels: robots and task types may be called anything (``R1``, ``arm_2``, ``pick``),
as long as names are unique and not empty. Robots keep the file's order; task types are in
natural order of their names (digits compared as numbers: ``T2`` before ``T10``), so the paper's
``T1..Tn`` keep their numeric order. A task type is known from the robots that can do it; a
``task_types`` entry no robot can do is an error.
"""

from __future__ import annotations

import reprlib
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Annotated, Any

import numpy as np

from mrta_rl.config import ConfigError, Range, check_keywords
from mrta_rl.types import RobotId, TaskType, natural_key

_DURATION_KEYS = ("duration_low", "duration_high")
# robot-task pairs of the largest team: a team is built, checked and partitioned robot by robot
# in Python, which takes minutes past this; 10^7 is 100,000 robots of 100 task types
MAX_PAIRS = 10**7


class SystemConfigError(ConfigError):
    """A system description is malformed; the message names the robot or task type at fault."""


def _label(value: Any, what: str) -> str:
    """A robot or task type name from a system file: a non-empty string (or an integer)."""
    if isinstance(value, bool) or not isinstance(value, (str, int)) or str(value).strip() == "":
        raise SystemConfigError(f"{what} must be a non-empty string, got {value!r}")
    return str(value)


@dataclass(frozen=True)
class DurationRange:
    """Integer duration range ``[lo, hi]`` (both ends included) of one task type and priority."""

    lo: int
    hi: int

    def __post_init__(self) -> None:
        if (
            not (isinstance(self.lo, int) and isinstance(self.hi, int))
            or not 1 <= self.lo <= self.hi
        ):
            raise SystemConfigError(
                f"duration range must be integers 1 <= lo <= hi, got [{self.lo}, {self.hi}]"
            )


@dataclass(frozen=True, eq=False)
class RobotSystem:
    """A heterogeneous robot team.

    Attributes:
        name: System name (``system1``...).
        robots: Robot ids in order, ``("R1", ...)``; robot index ``i`` is position in this tuple.
        task_types: Task type names (``("T1", ..., "Tn")`` for the paper's systems), in order.
        willingness: ``[m, n]`` floats, ``d_ij`` in (0, 1] where ``R_i`` can do ``T_j``, else 0.
        durations: Per task type overrides ``{"T2": {"duration_low": DurationRange, ...}}``.
        env_overrides: Per-system environment parameters (see ``AuctionParams``).
    """

    name: str
    robots: tuple[RobotId, ...]
    task_types: tuple[TaskType, ...]
    willingness: np.ndarray  # d_ij, [m, n]
    durations: Mapping[TaskType, Mapping[str, DurationRange]] = field(default_factory=dict)
    env_overrides: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        d = np.asarray(self.willingness, dtype=np.float64)
        if d.shape != (len(self.robots), len(self.task_types)):
            raise SystemConfigError(
                f"willingness has shape {d.shape}, "
                f"expected ({len(self.robots)}, {len(self.task_types)})"
            )
        for kind, names in (("robot", self.robots), ("task type", self.task_types)):
            for name in names:
                _label(name, f"system {self.name!r}: {kind} name")
            if len(set(names)) != len(names):
                raise SystemConfigError(f"system {self.name!r}: duplicate {kind} name in {names}")
        for i, robot in enumerate(self.robots):
            bad = [self.task_types[j] for j in range(d.shape[1]) if not (0.0 <= d[i, j] <= 1.0)]
            if bad or np.isnan(d[i]).any():
                raise SystemConfigError(f"robot {robot}: willingness for {bad} is outside (0, 1]")
            if not (d[i] > 0).any():
                raise SystemConfigError(f"robot {robot} has no task type")
        for j, task in enumerate(self.task_types):
            if not (d[:, j] > 0).any():
                raise SystemConfigError(f"task type {task}: no robot can do it")
        for task in self.durations:
            if task not in self.task_types:
                raise SystemConfigError(f"task type {task!r} in task_types is unknown")
        d.setflags(write=False)
        object.__setattr__(self, "willingness", d)
        object.__setattr__(self, "durations", MappingProxyType(dict(self.durations)))
        object.__setattr__(self, "env_overrides", MappingProxyType(dict(self.env_overrides)))

    @property
    def n_robots(self) -> int:
        """Number of robots ``m``."""
        return len(self.robots)

    @property
    def n_task_types(self) -> int:
        """Number of task types ``n``."""
        return len(self.task_types)

    @property
    def rtm(self) -> np.ndarray:
        """Robot-task relation matrix ``M`` (paper eq. 6), ``[m, n]`` int 0/1."""
        return (self.willingness > 0).astype(np.int64)

    def task_set(self, robot: RobotId) -> dict[TaskType, float]:
        """Gamma_i of one robot: ``{task type: willingness d_iz}`` (paper eq. 5)."""
        i = self.robots.index(robot)
        return {
            t: float(self.willingness[i, j])
            for j, t in enumerate(self.task_types)
            if self.willingness[i, j] > 0
        }

    @classmethod
    def from_table(
        cls,
        name: str,
        robots: Mapping[str, Any],
        task_types: Mapping[str, Any] | None = None,
        env: Mapping[str, Any] | None = None,
    ) -> RobotSystem:
        """Build a system from the yaml table format (module docstring).

        Args:
            name: System name.
            robots: ``{robot: [task types]}`` or ``{robot: {task type: willingness}}``.
            task_types: Optional ``{task type: {duration_low: [lo, hi], duration_high: [lo, hi]}}``.
            env: Optional per-system environment parameters.

        Returns:
            The validated system.

        Raises:
            SystemConfigError: naming the robot or task type at fault.
        """
        if not isinstance(robots, Mapping) or not robots:
            raise SystemConfigError(
                f"system {name!r}: 'robots' must be a non-empty mapping robot -> task types"
            )
        entries: dict[str, dict[str, float]] = {}
        for robot, spec in robots.items():
            robot = _label(robot, f"system {name!r}: robot name")
            if spec is None or (hasattr(spec, "__len__") and len(spec) == 0):
                raise SystemConfigError(f"robot {robot} has no task type")
            if isinstance(spec, Mapping):
                pairs = {_label(k, f"robot {robot}: task type name"): v for k, v in spec.items()}
            elif (
                isinstance(spec, (list, tuple))
                or hasattr(spec, "__iter__")
                and not isinstance(spec, str)
            ):
                pairs = {_label(k, f"robot {robot}: task type name"): 1.0 for k in spec}
            else:
                raise SystemConfigError(
                    f"robot {robot}: expected a list of task types or a mapping, got {spec!r}"
                )
            for task, d in pairs.items():
                if (
                    isinstance(d, bool)
                    or not isinstance(d, (int, float))
                    or not 0.0 < float(d) <= 1.0
                ):
                    raise SystemConfigError(
                        f"robot {robot}: willingness {d!r} for {task} is outside (0, 1]"
                    )
            entries[robot] = {t: float(d) for t, d in pairs.items()}
        if task_types is not None and not isinstance(task_types, Mapping):
            raise SystemConfigError(
                f"system {name!r}: 'task_types' must be a mapping task type -> duration ranges"
            )
        durations_cfg = {
            _label(t, "task_types: task type name"): spec for t, spec in (task_types or {}).items()
        }
        capable = {t for pairs in entries.values() for t in pairs}
        for task in durations_cfg:
            if task not in capable:
                raise SystemConfigError(
                    f"task_types: task type {task!r} is listed, but no robot in 'robots' can do it"
                )
        names = tuple(sorted(capable, key=natural_key))
        column = {task: j for j, task in enumerate(names)}
        willingness = np.zeros((len(entries), len(names)))
        for i, pairs in enumerate(entries.values()):
            for task, d in pairs.items():
                willingness[i, column[task]] = d
        durations = {t: _parse_durations(t, spec) for t, spec in durations_cfg.items()}
        return cls(name, tuple(entries), names, willingness, durations, env_parameters(name, env))


def env_parameters(name: str, env: Any) -> dict[str, Any]:
    """A system's ``env:`` block as a dict (empty when absent), refused unless it is a mapping.

    Its keys and values are checked with the run's (``runners/validation.py``, ``team_params``).

    Raises:
        SystemConfigError: naming the system and ``env``.
    """
    if env is None:
        return {}
    if not isinstance(env, Mapping):
        raise SystemConfigError(
            f"system {name!r}: env must be a mapping of env parameters (env: {{horizon: 200}}), "
            f"got {reprlib.repr(env)}"
        )
    return dict(env)


def _parse_durations(task: str, spec: Any) -> dict[str, DurationRange]:
    if not isinstance(spec, Mapping):
        raise SystemConfigError(
            f"task type {task}: expected {{duration_low: [lo, hi], duration_high: [lo, hi]}}"
        )
    out = {}
    for key, value in spec.items():
        if key not in _DURATION_KEYS:
            raise SystemConfigError(
                f"task type {task}: unknown key {key!r} (allowed: {_DURATION_KEYS})"
            )
        try:
            lo, hi = value
            out[key] = DurationRange(lo, hi)
        except (TypeError, ValueError, SystemConfigError) as err:
            raise SystemConfigError(
                f"task type {task}: {key} must be [lo, hi] integers, got {value!r}"
            ) from err
    return out


def random_system(
    n_robots: Annotated[int, Range(1)],
    n_task_types: Annotated[int, Range(1)] = 8,
    density: Annotated[float, Range(0, 1)] = 0.3,
    seed: Annotated[int, Range(0)] = 0,
    scale_auction: bool = False,
    name: str = "random",
    env: Mapping[str, Any] | None = None,
) -> RobotSystem:
    """A reproducible random team for scaling studies (willingness 1.0).

    Each robot can do each task type with probability ``density``; then every robot with no
    task type gets one at random, and every task type nobody can do gets one random robot, so the
    result is always a valid system.

    With ``scale_auction``, the auction grows with the team as in System-I and II (10 robots,
    ``slots`` 3, ``queue_capacity`` 32, one auction): :func:`auction_for_team`'s ``slots``,
    ``queue_capacity`` and ``zones`` go into the system's env parameters, so that the team bids
    in one auction zone per 10 robots, each of about 10 robots and 3 slots fed by the shared
    queue. The spec's arrival rate is already ``m / 6``, so arrivals, slots, queue and bidders
    per slot stay those of the paper's systems at every team size (docs/guide/teams.md, "Random
    teams"). Values in ``env`` win.

    Args:
        n_robots: Number of robots ``m`` (>= 1).
        n_task_types: Number of task types ``n`` (>= 1).
        density: Probability of each robot-task pair, in [0, 1].
        seed: Seed of the generator; the same arguments give the same system.
        scale_auction: Scale ``slots``, ``queue_capacity`` and ``zones`` with the team (above).
        name: System name.
        env: Optional per-system environment parameters.

    Returns:
        The system.

    Raises:
        SystemConfigError: on arguments out of range (the annotations are the declarations).
    """
    given = {
        "n_robots": n_robots,
        "n_task_types": n_task_types,
        "density": density,
        "seed": seed,
        "scale_auction": scale_auction,
    }
    try:
        check_keywords(random_system, given, "system")
    except ConfigError as err:
        raise SystemConfigError(str(err)) from None
    rng = np.random.default_rng(seed)
    rtm = rng.random((n_robots, n_task_types)) < density
    for i in np.flatnonzero(~rtm.any(axis=1)):
        rtm[i, rng.integers(n_task_types)] = True
    for j in np.flatnonzero(~rtm.any(axis=0)):
        rtm[rng.integers(n_robots), j] = True
    robots = tuple(f"R{i + 1}" for i in range(n_robots))
    tasks = tuple(f"T{j + 1}" for j in range(n_task_types))
    scaled = auction_for_team(n_robots) if scale_auction else {}
    overrides = scaled | env_parameters(name, env)
    return RobotSystem(name, robots, tasks, rtm.astype(np.float64), {}, overrides)


# System-I and II (paper Tables 1-2): 10 robots, spec defaults slots = 3, queue_capacity = 32,
# one auction zone
PAPER_TEAM, PAPER_SLOTS, PAPER_QUEUE = 10, 3, 32


def auction_for_team(n_robots: int) -> dict[str, int]:
    """The auction of a team of ``m`` robots, per robot that of the paper's 10-robot systems.

    Slots and queue places grow in proportion to the team, and the team bids in one auction zone
    per 10 robots (spec, "Auction zones"). One zone would not do: every idle robot bids for the
    lowest slot it may take (the spec's greedy), so the first slot of each task type draws all
    the bids for that type and one auction assigns at most one task per type and tick, however
    many slots it has; the ``m / 6`` arrivals per tick outgrow the ``n`` task types from about
    ``6 n`` robots on. In zones of about 10 robots, as many robots compete for a slot as in
    System-I and II at every size.

    Args:
        n_robots: Team size ``m``.

    Returns:
        ``{"slots": ceil(3 m / 10), "queue_capacity": ceil(32 m / 10), "zones": ceil(m / 10)}``.
    """
    return {
        "slots": -(-PAPER_SLOTS * n_robots // PAPER_TEAM),
        "queue_capacity": -(-PAPER_QUEUE * n_robots // PAPER_TEAM),
        "zones": -(-n_robots // PAPER_TEAM),
    }

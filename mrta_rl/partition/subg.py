"""subG-CQL partition of a robot system into sub-groups (paper §4, spec docs/spec/partition.md).

The paper describes the partition in words and in pseudo-code, and Tables 3 and 4 give the
sub-groups it produces for System-I and System-II. Taken literally, the pseudo-code cannot
produce those tables: once a robot has joined a sub-group, the rule "if ``R_i`` is in ``L_f``,
add the triplet to ``L_f``" sends every later pair of that robot to the same sub-group. The
robot's first sub-group therefore always collects all of its dependency, it always wins the
final comparison, and no robot ever drops a task type, while the paper reports dropped pairs
(R1-T1 and R6-T5 in System-I). This module follows ``docs/spec/partition.md``, which
fixes the ambiguous points so that both tables come out exactly. It departs from the
pseudo-code in three places:

1. **Fixed weights.** ``w_ij = d_ij / (r0_i * c0_j)`` uses the row and column sums of the
   *original* matrix ``M`` and never changes. The pseudo-code computes ``w_ij`` inside the
   loop, where ``r_i`` and ``c_j`` are the shrinking sums of the working matrix; the spec fixes
   the original sums, the reading under which both tables come out.
2. **One home sub-group per task type.** The first time a task type is matched, it gets a
   *home*: the lowest-numbered sub-group its matched robot already belongs to, or a new one if
   the robot belongs to none. Every later triplet of that task type goes to its home only (not
   to the robot's other sub-groups), and the robot joins that home. So a task type always lives
   in exactly one sub-group, and a robot whose task types have different homes ends up in
   several sub-groups (the set ``C``).
3. **Dependency over the original task set.** ``eta_ig`` is the sum of ``w_ij`` over all of the
   robot's original task types whose home is ``g``. The robot keeps the sub-group with the
   largest ``eta_ig`` (ties to the lowest number) and exactly the task types homed there, and
   drops the others.

Two steps the pseudo-code leaves implicit are added as the spec prescribes: a repair step (a
task type that lost all its robots goes back to the sub-group whose capable robots depend on
it most) and the deletion of empty sub-groups, which are then renumbered ``G1, G2, ...`` in
order of creation.

**Size bound (not in the paper).** With ``max_group_size=g`` a sub-group of more than
``g`` robots is split after step 4 (:func:`_split_group`): every robot stays with its *anchor*,
the kept task type it depends on most (largest ``w_ij``, ties to the lowest type), so the pairs
that are cut are each robot's weaker ones. The robots anchored to one type form a class (strongest
first); a class larger than ``g`` is cut into pieces of ``g`` robots, and the pieces are packed
first-fit decreasing into chunks of at most ``g`` robots. A chunk handles its robots' anchors; a
type of the sub-group that is nobody's anchor goes to the chunk whose robots keeping it depend on
it most (sum of ``w_ij``, ties to the lowest chunk). So every chunk has at most ``g`` robots, every
robot keeps at least its anchor, every task type keeps a robot, and a task type is shared by
several sub-groups only when more than ``g`` robots are anchored to it. The chunks replace the
sub-group in the numbering. Without the bound (``None``, the default) nothing changes.

System-I hangs on two exact ties (R4: 1/6 against 1/6, R1: 1/9 against 1/9), so weights and
dependencies are exact ``fractions.Fraction`` values. Willingness values are floats; each is
converted with ``Fraction(d).limit_denominator(10**6)``, i.e. to the closest fraction with a
denominator of at most one million (``0.9`` -> ``9/10``, not the binary expansion of 0.9), so
values that differ only by float rounding (``0.3`` and ``0.1 + 0.2``) compare equal. A willingness
below one millionth, which would round to 0, is kept as its exact binary value instead.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from fractions import Fraction
from typing import Any

import numpy as np

from mrta_rl.systems import RobotSystem, natural_key
from mrta_rl.types import GroupMap, GroupName, RobotId, TaskType

logger = logging.getLogger(__name__)

WILLINGNESS_MAX_DENOMINATOR = 10**6  # d_ij -> Fraction, see module docstring


@dataclass(frozen=True)
class Partition:
    """Result of the subG-CQL partition (paper §4, Tables 3-4).

    Attributes:
        groups: Sub-group ``L_g`` -> robot -> its new task set ``Lambda_i``, e.g.
            ``{"G1": {"R2": ["T1", "T2", "T8"], ...}}``. Groups are numbered ``G1..`` in order
            of creation (empty ones removed), robots are in system order and task types in
            numeric order.
        dropped: ``(robot, task type)`` pairs of ``Gamma_i`` that are not in ``Lambda_i``, sorted
            by robot then task type.
    """

    groups: dict[GroupName, dict[RobotId, list[TaskType]]]
    dropped: list[tuple[RobotId, TaskType]]

    def group_map(self) -> GroupMap:
        """TorchRL ``group_map``: sub-group -> its robots, e.g. ``{"G1": ["R2", "R5"]}``."""
        return {name: list(robots) for name, robots in self.groups.items()}

    def group_tasks(self) -> dict[GroupName, list[TaskType]]:
        """Task types handled by each sub-group, in numeric order.

        Without a size bound each type is in exactly one sub-group; with one, a type more than
        ``max_group_size`` robots are anchored to is shared (see :meth:`types_disjoint`).
        """
        out = {}
        for name, robots in self.groups.items():
            tasks = {t for kept in robots.values() for t in kept}
            out[name] = sorted(tasks, key=natural_key)
        return out

    def types_disjoint(self) -> bool:
        """True if every task type is handled by exactly one sub-group (always without a bound)."""
        types = [t for tasks in self.group_tasks().values() for t in tasks]
        return len(types) == len(set(types))

    def active_tasks(self, system: RobotSystem) -> np.ndarray:
        """New task sets ``Lambda_i`` as a mask aligned with ``system``.

        Args:
            system: The system this partition was computed from.

        Returns:
            ``[m, n]`` bool array, True where robot ``i`` keeps task type ``j``.

        Raises:
            ValueError: if a robot or task type of the partition is not in ``system`` or a robot
                of ``system`` is missing from the partition.
        """
        mask = np.zeros((system.n_robots, system.n_task_types), dtype=bool)  # [m, n]
        seen = set()
        for robots in self.groups.values():
            for robot, kept in robots.items():
                if robot not in system.robots:
                    raise ValueError(
                        f"robot {robot} of the partition is not in system {system.name!r}"
                    )
                i = system.robots.index(robot)
                seen.add(robot)
                for task in kept:
                    if task not in system.task_types:
                        raise ValueError(
                            f"task type {task} of the partition is not in system {system.name!r}"
                        )
                    mask[i, system.task_types.index(task)] = True
        missing = [r for r in system.robots if r not in seen]
        if missing:
            raise ValueError(f"robot {missing[0]} of system {system.name!r} is in no sub-group")
        return mask

    def to_json(self) -> dict[str, Any]:
        """JSON-ready form of the partition.

        Returns:
            ``{"groups": [{"name": "G1", "robots": {"R2": ["T1", ...]}}, ...],
            "dropped": [["R2", "T5"], ...]}``.
        """
        return {
            "groups": [
                {"name": name, "robots": {r: list(kept) for r, kept in robots.items()}}
                for name, robots in self.groups.items()
            ],
            "dropped": [[robot, task] for robot, task in self.dropped],
        }


def subg_partition(system: RobotSystem, max_group_size: int | None = None) -> Partition:
    """Partition a robot system into subG-CQL sub-groups (paper §4, spec docs/spec/partition.md).

    Args:
        system: The robot team; ``M`` is ``system.rtm`` and ``D`` is ``system.willingness``.
        max_group_size: ``g``: split sub-groups of more than ``g`` robots (module docstring,
            "Size bound"); None = the paper's rule, unbounded.

    Returns:
        The partition.

    Raises:
        ValueError: on invalid input, naming the robot or task type at fault.
    """
    return partition_matrices(
        system.rtm, system.willingness, system.robots, system.task_types, max_group_size
    )


def partition_matrices(
    rtm: Any,
    willingness: Any | None = None,
    robots: Sequence[RobotId] | None = None,
    task_types: Sequence[TaskType] | None = None,
    max_group_size: int | None = None,
) -> Partition:
    """Run the subG-CQL partition on a raw relation matrix (spec docs/spec/partition.md, steps 1-5).

    Args:
        rtm: Robot-task relation matrix ``M`` (paper eq. 6), ``[m, n]``, entries 0 or 1.
        willingness: ``D``, ``[m, n]``, ``d_ij`` in (0, 1] where ``m_ij = 1``; entries where
            ``m_ij = 0`` are ignored. Defaults to all ones.
        robots: Robot ids, default ``R1..Rm``.
        task_types: Task type ids in numeric order, default ``T1..Tn``.
        max_group_size: ``g``, at most this many robots per sub-group (module docstring, "Size
            bound"); None = unbounded, the paper's rule.

    Returns:
        The partition.

    Raises:
        ValueError: on a malformed matrix, naming the robot or task type at fault: an entry of
            ``M`` that is not 0/1, a willingness outside (0, 1], a robot with no task type, or a
            task type no robot can do; or on a ``max_group_size`` that is not an integer >= 1.
    """
    if max_group_size is not None and (
        isinstance(max_group_size, bool)
        or not isinstance(max_group_size, int | np.integer)
        or max_group_size < 1
    ):
        raise ValueError(
            f"partition.max_group_size must be an integer >= 1 or null, got {max_group_size!r}"
        )
    relation, d_exact, robots, task_types = _validate(rtm, willingness, robots, task_types)
    m, n = relation.shape
    capable = [[j for j in range(n) if relation[i, j]] for i in range(m)]  # Gamma_i as indices

    # spec step 1 (deviation 1): w_ij from the ORIGINAL row/column sums, fixed for the whole run
    r0 = relation.sum(axis=1)  # [m]
    c0 = relation.sum(axis=0)  # [n]
    weight = {
        (i, j): d_exact[i, j] / (int(r0[i]) * int(c0[j])) for i in range(m) for j in capable[i]
    }

    # spec step 2: match tasks to robots until M is empty
    home: dict[int, int] = {}  # task index -> home sub-group index (deviation 2)
    member_of: list[set[int]] = [set() for _ in range(m)]  # sub-groups each robot belongs to
    n_created = 0
    in_several: set[int] = set()  # the paper's set C
    work = relation.copy()  # [m, n], the shrinking M
    while work.any():
        r = work.sum(axis=1)  # [m], current r_i
        c = work.sum(axis=0)  # [n], current c_j
        omega = work.T @ r  # [n], omega_j = sum_i m_ij r_i (paper eq. 8)
        # spec step 2: largest c_j, ties to the smallest omega_j, then the lowest index
        j = min((j for j in range(n) if c[j] > 0), key=lambda j: (-c[j], omega[j], j))
        # spec step 2: smallest r_i, ties to the largest d_ij, then the lowest index
        i = min((i for i in range(m) if work[i, j]), key=lambda i: (r[i], -d_exact[i, j], i))
        if j not in home:
            # spec step 2 (deviation 2): a task's home is the robot's lowest sub-group, else new
            if member_of[i]:
                home[j] = min(member_of[i])
            else:
                home[j] = n_created
                n_created += 1
        member_of[i].add(home[j])
        if len(member_of[i]) >= 2:
            in_several.add(i)
        logger.debug(
            "match <%s, %s, %s> -> sub-group %d",
            robots[i],
            task_types[j],
            weight[i, j],
            home[j] + 1,
        )
        work[i, j] = 0

    # spec step 3 (deviation 3): eta_ig over the robot's original task types homed in g
    chosen: list[int] = []
    kept: list[set[int]] = []
    for i in range(m):
        eta: dict[int, Fraction] = {}
        for j in capable[i]:
            eta[home[j]] = eta.get(home[j], Fraction(0)) + weight[i, j]
        g = min(eta, key=lambda g: (-eta[g], g))  # largest eta, ties to the lowest number
        chosen.append(g)
        kept.append({j for j in capable[i] if home[j] == g})
        if i in in_several:
            logger.debug("%s in C: eta=%s -> sub-group %d", robots[i], eta, g + 1)

    # spec step 4: a task type left with no robot goes to the sub-group that depends on it most
    for j in range(n):
        if any(j in kept[i] for i in range(m)):
            continue
        score: dict[int, Fraction] = {}
        for i in range(m):
            if relation[i, j]:
                score[chosen[i]] = score.get(chosen[i], Fraction(0)) + weight[i, j]
        g = min(score, key=lambda g: (-score[g], g))  # largest sum of w_ij, ties to the lowest
        logger.debug("repair: %s goes back to sub-group %d", task_types[j], g + 1)
        for i in range(m):
            if relation[i, j] and chosen[i] == g:
                kept[i].add(j)

    # spec step 5: delete empty sub-groups, renumber the rest G1.. in order of creation; with a
    # size bound an oversized sub-group is replaced by its chunks (module docstring)
    groups: dict[GroupName, dict[RobotId, list[TaskType]]] = {}
    for g in range(n_created):
        members = [i for i in range(m) if chosen[i] == g]
        chunks = [members]
        if max_group_size is not None and len(members) > max_group_size:
            chunks = _split_group(members, kept, weight, int(max_group_size))
            logger.debug(
                "bound: sub-group %d (%d robots) split into %s",
                g + 1,
                len(members),
                [len(c) for c in chunks],
            )
        for chunk in chunks:
            if chunk:
                groups[f"G{len(groups) + 1}"] = {
                    robots[i]: [task_types[j] for j in sorted(kept[i])] for i in chunk
                }
    dropped = [(robots[i], task_types[j]) for i in range(m) for j in capable[i] if j not in kept[i]]
    return Partition(groups=groups, dropped=dropped)


def _split_group(
    members: list[int],
    kept: list[set[int]],
    weight: dict[tuple[int, int], Fraction],
    bound: int,
) -> list[list[int]]:
    """Split one oversized sub-group into chunks of at most ``bound`` robots (size bound rule).

    Narrows ``kept`` of the members in place to the task types of their chunk.

    Args:
        members: Robot indices of the sub-group, in system order.
        kept: ``Lambda_i`` per robot (task indices), after step 4.
        weight: The fixed ``w_ij`` of step 1.
        bound: ``g``.

    Returns:
        The chunks, each a list of robot indices in system order.
    """
    # each robot's anchor: the kept type it depends on most (largest w_ij, ties to the lowest)
    anchor = {i: min(kept[i], key=lambda j, i=i: (-weight[i, j], j)) for i in members}
    classes: dict[int, list[int]] = {}
    for i in sorted(members, key=lambda i: (-weight[i, anchor[i]], i)):  # strongest first
        classes.setdefault(anchor[i], []).append(i)
    # a class larger than the bound is cut into pieces of `bound` robots, strongest first
    pieces = [
        (j, robots_[k : k + bound])
        for j, robots_ in classes.items()
        for k in range(0, len(robots_), bound)
    ]
    pieces.sort(key=lambda piece: (-len(piece[1]), piece[0]))  # first-fit decreasing
    chunks: list[list[int]] = []
    chunk_types: list[set[int]] = []
    for j, piece in pieces:
        for c, chunk in enumerate(chunks):
            if len(chunk) + len(piece) <= bound:
                chunk.extend(piece)
                chunk_types[c].add(j)
                break
        else:
            chunks.append(list(piece))
            chunk_types.append({j})
    # a type that is nobody's anchor goes to the chunk whose robots keeping it depend on it most
    for j in sorted({j for i in members for j in kept[i]} - set(anchor.values())):
        score = {
            c: sum((weight[i, j] for i in chunk if j in kept[i]), Fraction(0))
            for c, chunk in enumerate(chunks)
        }
        best = min((c for c in score if score[c] > 0), key=lambda c: (-score[c], c))
        chunk_types[best].add(j)
    for chunk, types in zip(chunks, chunk_types, strict=True):
        for i in chunk:
            kept[i] &= types
    return [sorted(chunk) for chunk in chunks]


def format_partition(partition: Partition) -> str:
    """Render a partition as a plain-text table: group, robot, kept and dropped task types.

    Args:
        partition: The partition to show.

    Returns:
        The table, one line per robot, followed by a one-line summary.
    """
    dropped: dict[RobotId, list[TaskType]] = {}
    for robot, task in partition.dropped:
        dropped.setdefault(robot, []).append(task)
    header = ("group", "robot", "kept task types", "dropped task types")
    rows = [
        (name, robot, ", ".join(kept), ", ".join(dropped.get(robot, [])) or "-")
        for name, robots in partition.groups.items()
        for robot, kept in robots.items()
    ]
    widths = [max(len(row[k]) for row in [header, *rows]) for k in range(len(header))]

    def line(row: Sequence[str]) -> str:
        return "  ".join(
            cell.ljust(width) for cell, width in zip(row, widths, strict=True)
        ).rstrip()

    out = [line(header), line(["-" * w for w in widths])]
    previous = None
    for row in rows:
        out.append(line(row if row[0] != previous else ("", *row[1:])))
        previous = row[0]
    n_groups, n_dropped = len(partition.groups), len(partition.dropped)
    out.append(f"{n_groups} sub-groups, {len(rows)} robots, {n_dropped} dropped pairs")
    return "\n".join(out)


def _validate(
    rtm: Any,
    willingness: Any | None,
    robots: Sequence[RobotId] | None,
    task_types: Sequence[TaskType] | None,
) -> tuple[np.ndarray, np.ndarray, tuple[RobotId, ...], tuple[TaskType, ...]]:
    """Check the inputs and return ``M`` as int, ``D`` as Fractions, and the ids."""
    try:
        raw = np.asarray(rtm, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise ValueError(f"relation matrix M must be numeric, got {rtm!r}") from err
    if raw.ndim != 2 or raw.size == 0:
        raise ValueError(f"relation matrix M must be a non-empty 2-D array, got shape {raw.shape}")
    m, n = raw.shape
    robots = tuple(robots) if robots is not None else tuple(f"R{i + 1}" for i in range(m))
    task_types = (
        tuple(task_types) if task_types is not None else tuple(f"T{j + 1}" for j in range(n))
    )
    if len(robots) != m or len(task_types) != n:
        raise ValueError(
            f"M has shape {(m, n)} but {len(robots)} robots and {len(task_types)} task types"
            " were given"
        )
    for i in range(m):
        bad = [task_types[j] for j in range(n) if raw[i, j] not in (0.0, 1.0)]  # NaN is not 0/1
        if bad:
            raise ValueError(f"robot {robots[i]}: relation matrix entries for {bad} are not 0 or 1")
    relation = raw.astype(np.int64)  # [m, n]
    if willingness is None:
        d = relation.astype(np.float64)
    else:
        try:
            d = np.asarray(willingness, dtype=np.float64)  # [m, n]
        except (TypeError, ValueError) as err:
            raise ValueError(f"willingness D must be numeric, got {willingness!r}") from err
        if d.shape != (m, n):
            raise ValueError(f"willingness D has shape {d.shape}, expected {(m, n)} like M")
    d_exact = np.zeros((m, n), dtype=object)  # [m, n] Fraction
    for i in range(m):
        for j in range(n):
            if not relation[i, j]:
                continue  # willingness of a pair the robot cannot do is ignored
            if not 0.0 < d[i, j] <= 1.0:  # also rejects NaN
                raise ValueError(
                    f"robot {robots[i]}: willingness {d[i, j]} for {task_types[j]}"
                    " is outside (0, 1]"
                )
            exact = Fraction(float(d[i, j]))
            # module docstring: round to a small denominator, but never turn a positive d into 0
            d_exact[i, j] = exact.limit_denominator(WILLINGNESS_MAX_DENOMINATOR) or exact
    for i in range(m):
        if not relation[i].any():
            raise ValueError(f"robot {robots[i]} has no task type")
    for j in range(n):
        if not relation[:, j].any():
            raise ValueError(f"task type {task_types[j]}: no robot can do it")
    return relation, d_exact, robots, task_types

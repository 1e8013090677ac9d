"""Learning space dimension of the tabular learners, paper §5.2 eqs. (10)-(16), as exact ints.

Each tabular learner class answers for its own dimension (``learning_space_dimension``, a
classmethod built on the formulas here); :func:`mrta_rl.learners.registry.learning_space_dimension`
asks the class of a learner name, and :func:`mrta_rl.learners.registry.learning_space_table` every
tabular learner of a system. The state counts come from the project's encodings
(``mrta_rl.envs.encodings``) and every robot has ``|A_i| = K + 1`` actions (wait or bid for one
of ``K`` slots, spec step 4):

* DQL, eqs. (10)-(11): ``sum_i |S_i| |A_i|`` with ``S_i`` the local view of robot ``i``.
* semi-CQL, eq. (11) with each robot's state the whole-system state: ``sum_i |S| |A_i|``; with
  a coarser shared ``state`` its ``|S|`` (``tabular.encoding.system_state_count``).
* CQL, eqs. (13), (15), (16): ``|S| prod_i |A_i|`` with ``S`` the whole-system group view. The
  paper bounds ``|S|`` by the sum of the individual spaces (eq. 13); here ``|S|`` is the exact
  count of the encoding, which holds every robot's idle and battery state.
* subG-CQL (§5.2, last paragraph): ``sum_g |S_g| prod_{i in g} |A_i|`` over the sub-groups, each
  with its own group view over its kept task types; with ``state=idle`` each robot's idle
  flag instead of its three states (``tabular.encoding.subgroup_state_count``).

Python ints never overflow, which matters for CQL on System-II.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Literal

TabularLearnerName = Literal["cql", "semi_cql", "dql", "subg_cql"]
# the rows of the paper's Table 9, in its order (each learner's formula is its class's)
TABULAR_LEARNERS: tuple[TabularLearnerName, ...] = ("cql", "semi_cql", "dql", "subg_cql")


def decentralized_dimension(state_counts: Sequence[int], action_counts: Sequence[int]) -> int:
    """Eq. (11): ``|U| = sum_i |S_i| |A_i|`` (each term is eq. 10).

    Args:
        state_counts: ``|S_i|`` per robot.
        action_counts: ``|A_i|`` per robot.

    Returns:
        The exact dimension.

    Raises:
        ValueError: if the two lists differ in length.
    """
    if len(state_counts) != len(action_counts):
        raise ValueError("one state count and one action count per robot")
    return sum(int(s) * int(a) for s, a in zip(state_counts, action_counts, strict=True))


def centralized_dimension(state_count: int, action_counts: Sequence[int]) -> int:
    """Eqs. (15)-(16): ``|U| = |S| prod_i |A_i|``.

    Args:
        state_count: ``|S|`` of the joint state.
        action_counts: ``|A_i|`` of every robot of the group.

    Returns:
        The exact dimension.
    """
    return int(state_count) * math.prod(int(a) for a in action_counts)


def subgroup_dimension(groups: Sequence[tuple[int, Sequence[int]]]) -> int:
    """subG-CQL: the sum over sub-groups of their centralized dimensions (eq. 16 each).

    Args:
        groups: ``(|S_g|, [|A_i| for i in g])`` per sub-group.

    Returns:
        The exact dimension.
    """
    return sum(centralized_dimension(s, a) for s, a in groups)


def factorize(value: int) -> str:
    """Prime factorisation as in paper Table 9 (``2^12 * 3^4 * 17``), for display.

    Args:
        value: A positive integer.

    Returns:
        The factorisation, factors in increasing order.
    """
    parts, p = [], 2
    while p * p <= value:
        k = 0
        while value % p == 0:
            value //= p
            k += 1
        if k:
            parts.append(f"{p}^{k}" if k > 1 else str(p))
        p += 1 if p == 2 else 2
    if value > 1:
        parts.append(str(value))
    return " * ".join(parts) or "1"


def format_learning_space_table(tables: dict[str, dict[TabularLearnerName, int]]) -> str:
    """Table 9 layout: one row per learner, one column per system, exact value and factors.

    Args:
        tables: ``{system name: learning_space_table(system)}``
            (:func:`mrta_rl.learners.registry.learning_space_table`).

    Returns:
        A plain-text table.
    """
    names = list(tables)
    cells = {
        (learner, s): f"{tables[s][learner]:,} = {factorize(tables[s][learner])}"
        for learner in TABULAR_LEARNERS
        for s in names
    }
    widths = [max(len(s), *(len(cells[(lr, s)]) for lr in TABULAR_LEARNERS)) for s in names]
    lines = ["learner   " + "  ".join(s.ljust(w) for s, w in zip(names, widths, strict=True))]
    for learner in TABULAR_LEARNERS:
        row = "  ".join(cells[(learner, s)].ljust(w) for s, w in zip(names, widths, strict=True))
        lines.append(f"{learner:<10}" + row)
    return "\n".join(line.rstrip() for line in lines)

"""What a learner will need, estimated from the system and hyperparameters before it is built.

:func:`estimate_resources` answers, without building the learner or training anything, whether a
learner can run on a system at all (its joint actions and state indices fit the int64 codes of
the tables and networks) and how much memory it takes:

* ``up_front``: memory the run takes for sure: the env copies of training and evaluation, dense
  tables (DQL), network weights with their target copies, gradients and Adam moments, a full
  replay buffer and a collector batch; for CQL and subG-CQL a full row of each group's table per
  copy of a tick, training's or evaluation's (``per_copy``: before each tick a table makes room
  for every copy's state to be new, ``GroupQLearner._reserve``);
* ``worst``: ``up_front`` plus an upper bound of the tables that grow with the states met
  (CQL, subG-CQL, semi-CQL store only visited states: at most ``min(|S_g|, decisions)`` rows, a
  decision being one copy-tick of training).

The runner refuses a run whose ``up_front`` passes ``limits.memory_gb`` and warns when ``worst``
does (the bound is loose: a run visits far fewer states). The counts follow the learners' storage:
``tabular.qtable`` (per state, the conflict-free joint actions; int64 code, float64 Q, int64
visits), the neural networks of ``learners/neural`` (float32; checked against built learners in
``tests/learners/test_memory.py``) and the transitions their TorchRL replay buffer keeps.

Each learner class counts its own state (its ``estimate_memory`` classmethod, see
``learners/base.py``) with the helpers here (:func:`group_table_estimate`,
:func:`neural_estimate`...); :func:`estimate_resources` adds the env copies. A learner that
cannot run at all raises :class:`Unfit`.
"""

from __future__ import annotations

import dataclasses
import math
import os
from typing import Any

from mrta_rl.envs import AuctionEnv, AuctionParams
from mrta_rl.envs.encodings import (
    ROBOT_TOKEN_SIZE,
    SLOT_TOKEN_SIZE,
    TYPE_TOKEN_SIZE,
    global_feature_size,
    local_feature_size,
    prior_dtype,
)
from mrta_rl.learners.resources import MemoryQuery, ResourceEstimate
from mrta_rl.partition import Partition, subg_partition
from mrta_rl.systems import RobotSystem

INT64_CODES = 2**63  # joint-action codes and state indices are int64
JOINT_ENTRY_BYTES = 8 + 8 + 8  # joint Q-table entry: code int64, Q float64, visits int64
JOINT_ROW_BYTES = 4 * 8 + 120  # row arrays (state, offset, length, greedy) + its dict entry
GROWTH = 2  # growable arrays double their capacity
TABLE_ENTRY_BYTES = 8 + 8  # dense tables: Q float64 and visits int64
# per float32 weight: itself, its target copy, its gradient and Adam's two moments
BYTES_PER_WEIGHT = 4 * 5


def conflict_free_joint_actions(n_robots: int, n_slots: int) -> int:
    """Joint actions of ``n_robots`` with at most one bidder per slot (all idle, all slots open).

    Sum over ``j`` bidders of ``C(m, j) K! / (K - j)!``: the most a joint Q-table row holds with
    ``prune_conflicts``.
    """
    return sum(
        math.comb(n_robots, j) * math.perm(n_slots, j) for j in range(min(n_robots, n_slots) + 1)
    )


def mlp_weights(n_in: int, n_out: int, depth: int, hidden: int) -> int:
    """Weights and biases of a TorchRL ``MLP`` with ``depth`` hidden layers of ``hidden`` units."""
    inner = (depth - 1) * (hidden * hidden + hidden)
    return n_in * hidden + hidden + inner + hidden * n_out + n_out


def probe_env(system: RobotSystem, params: AuctionParams, active_tasks: Any = None) -> AuctionEnv:
    """A one-copy env with the smallest queue: the sizes and limits of the real env, no memory.

    Raises:
        ValueError: if the parameters pass the env's limits (``AuctionEnv`` names which).
    """
    small = dataclasses.replace(params, queue_capacity=params.slots)
    return AuctionEnv(system, small, batch_size=1, active_tasks=active_tasks)


def env_copy_bytes(env: AuctionEnv, queue_capacity: int) -> int:
    """Bytes of one env copy: its task queue and the per-robot, per-type and per-slot state."""
    return copy_bytes(env.n_robots, env.n_task_types, env.n_slots, queue_capacity)


def copy_bytes(m: int, n: int, K: int, queue_capacity: int) -> int:
    """Bytes of one env copy of ``m`` robots, ``n`` task types and ``K`` slots."""
    return 8 * (queue_capacity + 1) + 16 * m + 40 * n + 32 * K + 24 + (K + 1) * m


# building a system of m robots and n task types: its random draw (float64), the bool table and
# the willingness (float64) at once, per robot-task pair; per robot, its name and tuple slot
SYSTEM_PAIR_BYTES = 8 + 1 + 8
ROBOT_NAME_BYTES = 64


def team_floor_bytes(n_robots: int, n_task_types: int, copies: int) -> dict[str, int]:
    """The least memory any run on a team of this shape takes, from the shape alone.

    Nothing is built: the system while it is built, and ``copies`` env copies as
    :func:`env_copy_bytes` counts them with the fewest slots (one) and no queue. A team whose
    floor passes the memory limit is refused before its system is built.

    Args:
        n_robots: Robots ``m``.
        n_task_types: Task types ``n``.
        copies: Env copies alive at once (training, evaluation and the greedy baseline's).

    Returns:
        ``{"system": bytes, "env copies": bytes}``.
    """
    m, n = int(n_robots), int(n_task_types)
    return {
        "system": SYSTEM_PAIR_BYTES * m * n + ROBOT_NAME_BYTES * m,
        "env copies": int(copies) * copy_bytes(m, n, K=1, queue_capacity=0),
    }


class Unfit(Exception):
    """A learner cannot run on a system at all (e.g. joint actions beyond int64).

    Raised by a learner's ``estimate_memory``; :func:`estimate_resources` turns it into the
    estimate's ``reason`` and ``advice``.

    Args:
        reason: Why, for the messages.
        advice: What to change.
    """

    def __init__(self, reason: str, advice: str) -> None:
        super().__init__(reason)
        self.reason, self.advice = reason, advice


def estimate_resources(
    cls: type,
    system: RobotSystem,
    params: AuctionParams,
    partition: Partition | None = None,
    hyperparameters: dict[str, Any] | None = None,
    *,
    batch_size: int = 1,
    episodes: int = 1,
    eval_batch_size: int = 0,
) -> ResourceEstimate:
    """Estimate what a learner class needs on a system, without building it.

    The learner's own state is the class's answer (``cls.estimate_memory``, see
    :class:`~mrta_rl.learners.base.Learner`); the env copies of training and evaluation are
    counted here.

    Args:
        cls: The learner class (``conf/learner/*.yaml`` ``_target_``).
        system: The robot team.
        params: Dynamics parameters (``slots``, ``horizon`` and ``queue_capacity`` matter).
        partition: The subG partition, for learners that require one (default: computed).
        hyperparameters: Settings of the learner; the rest take its yaml's (``Learner.defaults``).
        batch_size: Training copies (``train.batch_size``), bounds the states met.
        episodes: Training episodes (``train.episodes``), bounds the states met.
        eval_batch_size: Evaluation copies played at once.

    Returns:
        The estimate; a fixed policy needs only its env copies.

    Raises:
        ValueError: if the parameters pass the env's limits (see :func:`probe_env`).
    """
    hp = cls.complete_settings(hyperparameters or {})
    active = None
    if cls.requires_partition:
        partition = partition if partition is not None else subg_partition(system)
        active = partition.active_tasks(system)
    env = probe_env(system, params, active)
    decisions = max(1, episodes * batch_size * env.params.horizon)
    try:
        training = batch_size if episodes > 0 else 0  # copies that train (none: it only plays)
        estimate = cls.estimate_memory(MemoryQuery(env, partition, hp, decisions, training))
    except Unfit as unfit:
        estimate = ResourceEstimate(cls.__name__, reason=unfit.reason, advice=unfit.advice)
    copies = (batch_size + eval_batch_size) * env_copy_bytes(env, params.queue_capacity)
    ticking = max(batch_size if episodes > 0 else 0, eval_batch_size)  # copies of one tick
    first_tick = {
        f"{ticking:,} copies x {part}": ticking * b for part, b in estimate.per_copy.items()
    }
    up_front = estimate.up_front + sum(first_tick.values()) + copies
    return dataclasses.replace(
        estimate,
        up_front=up_front,
        worst=max(estimate.worst + copies, up_front),
        parts={"env copies": copies, **estimate.parts},
        up_front_parts=first_tick and {"env copies": copies, **first_tick},
        advice=estimate.advice or "lower train.batch_size, eval.batch_size or env.queue_capacity",
    )


def robot_groups(env: AuctionEnv, partition: Partition | None) -> dict[str, list[int]]:
    """Robot indices of each sub-group of the partition, or of the whole team without one."""
    robots = env.system.robots
    if partition is not None:
        return {g: [robots.index(r) for r in ids] for g, ids in partition.group_map().items()}
    return {"team": list(range(env.n_robots))}


def check_joint_actions(group: str, size: int, n_actions: int) -> None:
    """Refuse a group whose ``n_actions^size`` joint actions pass the int64 codes.

    Raises:
        Unfit: naming the group (``GROUP_ADVICE``).
    """
    if n_actions**size >= INT64_CODES:
        where = "the team" if group == "team" else f"sub-group {group}"
        reason = f"{where} has {size} robots: {n_actions}^{size} joint actions do not fit in int64"
        raise Unfit(reason, GROUP_ADVICE)


GROUP_ADVICE = "use fewer robots per group (smaller sub-groups) or a smaller system"
NEURAL_ADVICE = "lower learner.buffer_size or learner.hidden, or use a smaller system"


def neural_estimate(
    name: str,
    env: AuctionEnv,
    settings: dict[str, Any],
    weights: int,
    copies: int,
    advice: str,
    *,
    loss_keys_only: bool = False,
    state_bytes: int = 4,
) -> ResourceEstimate:
    """A TorchRL learner's networks, replay buffer and collector batch (float32 weights).

    Args:
        name: The learner class's name.
        env: The probe env (sizes).
        settings: The learner's settings, declared defaults filled in (``buffer_size``,
            ``collect_ticks``, ``features``, ``network``: ``set`` stores the set inputs instead
            of the local features).
        weights: Its trainable weights (the class counts them).
        copies: Training copies (``train.batch_size``); 0 for a run that only plays
            (``train.episodes=0``), which fills no buffer and collects no batch.
        advice: What to change when it does not fit.
        loss_keys_only: The replay buffer keeps only what the loss reads (the mixed learners'
            ``transitions``), not every leaf of the collected batch.
        state_bytes: Bytes per global feature of a stored state (float32: 4, bool: 1, not
            read by the loss: 0); ``loss_keys_only`` learners only.

    Returns:
        The estimate, all of it up front.
    """
    m, A = env.n_robots, env.n_actions
    F, S = feature_sizes(env, settings)
    robot, root = F * 4, 0  # observation bytes per robot and at the root
    if settings.get("network", "mlp") == "set":  # the set inputs instead (encodings.set_inputs)
        n, K = env.n_task_types, env.n_slots
        robot = ROBOT_TOKEN_SIZE * 4 + n  # robots (float32), robot_types (bool)
        root = K * (SLOT_TOKEN_SIZE * 4 + 8) + n * TYPE_TOKEN_SIZE * 4  # slots, slot_type, types
    # an observation: per robot its inputs, mask (bool) and the prior's action index
    observation = m * (robot + A + prior_dtype(A).itemsize) + root
    # one collected transition: observation and state (and their next); per robot the action
    # (int64), robot and group rewards (and their next), the invalid-action flags, the next
    # team reward; flags (measured on the buffer, tests/learners/test_memory.py)
    collected = 2 * (observation + S * 4) + m * (8 + 16 + 2 + 4) + 32
    stored = collected
    if loss_keys_only:  # observation and state (and their next), the action; next reward, flags
        stored = 2 * (observation + S * state_bytes) + m * 8 + 16
    parts = {
        "networks": weights * BYTES_PER_WEIGHT,
        "replay buffer": int(settings["buffer_size"]) * stored if copies else 0,
        "collector batch": int(settings["collect_ticks"]) * copies * collected,
    }
    total = sum(parts.values())
    return ResourceEstimate(name, total, total, parts, advice=advice)


def feature_sizes(env: AuctionEnv, settings: dict[str, Any]) -> tuple[int, int]:
    """``(F, S)``: local observation and global state widths of the learner's ``features``."""
    features = settings.get("features", "paper")  # the observation's encoding (FEATURES)
    return local_feature_size(env, features), global_feature_size(env, features)


def group_table_estimate(
    name: str,
    env: AuctionEnv,
    groups: dict[str, list[int]],
    state_counts: Any,
    settings: dict[str, Any],
    decisions: int,
) -> ResourceEstimate:
    """Joint Q-tables of visited states, one per group (CQL, subG-CQL; ``tabular.qtable``).

    A full row per group and copy of a tick counts up front (``per_copy``): a state is
    enumerated whole on its first visit, and before each tick the table makes room for every
    copy's state of every group to be new (``GroupQLearner._reserve``), so the first tick takes
    that much for sure (a 50-robot random team's 6-robot sub-group with 15 slots and 102 copies:
    15.5 GB; unchecked, an 11-robot one asked numpy for 537 TiB in the middle of a run).

    Args:
        name: The learner class's name.
        env: The probe env.
        groups: Robot indices of each group (:func:`robot_groups`).
        state_counts: ``state_counts(robots) -> |S_g|`` of the learner's group state.
        settings: The learner's settings (``prune_conflicts``).
        decisions: Copy-ticks of training, the most states met.

    Returns:
        The estimate.

    Raises:
        Unfit: if a group's joint actions or states pass the int64 codes.
    """
    A, K = env.n_actions, env.n_slots
    parts: dict[str, int] = {}
    per_copy: dict[str, int] = {}  # the room of a copy's new rows at each tick, taken for sure
    for group, robots in groups.items():
        check_joint_actions(group, len(robots), A)
        states = state_counts(robots)
        if states >= INT64_CODES:
            raise Unfit(f"{group}: {states:.3g} group states do not fit in int64", GROUP_ADVICE)
        per_row = (
            conflict_free_joint_actions(len(robots), K)
            if settings.get("prune_conflicts", True)
            else A ** len(robots)
        )
        rows = min(states, decisions)
        row = per_row * JOINT_ENTRY_BYTES + JOINT_ROW_BYTES
        parts[f"{group} table"] = GROWTH * rows * row
        per_copy[f"{group} row ({per_row:,} joint actions)"] = row
    worst = sum(parts.values())
    return ResourceEstimate(name, 0, worst, parts, per_copy, advice=GROUP_ADVICE)


def machine_memory() -> int:
    """Physical memory of the machine in bytes (``os.sysconf``)."""
    return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))

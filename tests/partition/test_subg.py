"""Tests of the subG-CQL partition (paper §4, spec docs/spec/partition.md)."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from mrta_rl.partition import Partition, format_partition, partition_matrices, subg, subg_partition
from mrta_rl.systems import RobotSystem, build_system, random_system

ROOT = Path(__file__).resolve().parents[2]


def load_system(name: str) -> RobotSystem:
    return build_system(yaml.safe_load((ROOT / "conf" / "system" / f"{name}.yaml").read_text()))


def as_sets(partition: Partition) -> set[frozenset]:
    """Groups as an order-free set of {robot: frozenset(task types)} for comparing with tables."""
    return {
        frozenset((robot, frozenset(tasks)) for robot, tasks in robots.items())
        for robots in partition.groups.values()
    }


def table(*groups: dict[str, list[str]]) -> set[frozenset]:
    return {frozenset((r, frozenset(ts)) for r, ts in g.items()) for g in groups}


# --- paper Tables 3 and 4 (spec "Expected results") ------------------------------------------


def test_system1_reproduces_table3():
    partition = subg_partition(load_system("system1"))
    assert as_sets(partition) == table(
        {"R1": ["T4", "T5"], "R2": ["T2", "T4"], "R4": ["T4", "T5"]},
        {"R3": ["T1", "T3"], "R5": ["T1"], "R6": ["T1", "T3"]},
    )
    assert partition.dropped == [("R1", "T1"), ("R6", "T5")]


def test_system1_exact_layout():
    # Numbering follows creation order (spec step 5): T1 is matched first (largest c_j = 4) to
    # R5 (r = 1), which creates the {R3, R5, R6} group, so it is G1 (the paper prints it second).
    partition = subg_partition(load_system("system1"))
    assert partition.groups == {
        "G1": {"R3": ["T1", "T3"], "R5": ["T1"], "R6": ["T1", "T3"]},
        "G2": {"R1": ["T4", "T5"], "R2": ["T2", "T4"], "R4": ["T4", "T5"]},
    }


def test_system2_reproduces_table4():
    partition = subg_partition(load_system("system2"))
    assert as_sets(partition) == table(
        {"R1": ["T3", "T5"], "R10": ["T3", "T5"]},
        {"R2": ["T1", "T2", "T8"], "R5": ["T2", "T8"], "R6": ["T1", "T2"], "R8": ["T2", "T8"]},
        {"R3": ["T6", "T7"], "R4": ["T4", "T6"], "R7": ["T4", "T6", "T7"], "R9": ["T6", "T7"]},
    )
    # Table 4 vs Table 2: R2 drops T5 and T7 (paper §6), and so on.
    assert partition.dropped == [
        ("R2", "T5"), ("R2", "T7"), ("R3", "T3"), ("R4", "T1"), ("R4", "T3"),
        ("R5", "T5"), ("R5", "T7"), ("R8", "T5"), ("R9", "T2"), ("R10", "T8"),
    ]  # fmt: skip


def test_system2_group_map_and_active_tasks():
    system = load_system("system2")
    partition = subg_partition(system)
    assert partition.group_map() == {
        "G1": ["R2", "R5", "R6", "R8"],
        "G2": ["R1", "R10"],
        "G3": ["R3", "R4", "R7", "R9"],
    }
    active = partition.active_tasks(system)
    assert active.dtype == bool and active.shape == (10, 8)
    assert active[system.robots.index("R2")].tolist() == [1, 1, 0, 0, 0, 0, 0, 1]
    assert active[system.robots.index("R10")].tolist() == [0, 0, 1, 0, 1, 0, 0, 0]
    assert partition.group_tasks() == {
        "G1": ["T1", "T2", "T8"], "G2": ["T3", "T5"], "G3": ["T4", "T6", "T7"],
    }  # fmt: skip


def test_float_willingness_tie_is_exact(monkeypatch):
    # System-I decides R1 on an exact tie of dependencies (T4's group 1/9 vs T5's group 1/9).
    # Give R1 d = 0.3 for T1 and T4 and d = 0.1 + 0.2 (= 0.30000000000000004) for T5: the tie
    # must survive, so the result is still Table 3 (ties go to the lowest group, T4's).
    system = load_system("system1")
    d = system.willingness.copy()
    d[0] = [0.3, 0.0, 0.0, 0.3, 0.1 + 0.2]
    assert partition_matrices(system.rtm, d) == subg_partition(system)
    # Without the rounding of d to a small denominator, T5's group wins by 1e-17 and R1 leaves.
    monkeypatch.setattr(subg, "WILLINGNESS_MAX_DENOMINATOR", 10**30)
    assert partition_matrices(system.rtm, d).group_map()["G3"] == ["R1"]


# --- small hand-computed cases ------------------------------------------------------------


def test_hand_computed_three_robots():
    # R1: {T1, T2}, R2: {T1}, R3: {T2}, all d = 1.
    # Step 1: r0 = (2, 1, 1), c0 = (2, 2); w_11 = w_12 = 1/(2*2) = 1/4, w_21 = w_32 = 1/2.
    # Step 2, iteration 1: c = (2, 2) tie; omega_1 = r1 + r2 = 3, omega_2 = r1 + r3 = 3, tie ->
    #   T1 (lowest index). Robots R1 (r=2), R2 (r=1) -> R2, in no group -> new G1, home(T1) = G1.
    # Iteration 2: c = (1, 2) -> T2; robots R1 (r=2), R3 (r=1) -> R3, new G2, home(T2) = G2.
    # Iteration 3: c = (1, 1), omega = (2, 2) -> T1; R1 joins home(T1) = G1.
    # Iteration 4: T2 -> R1 joins home(T2) = G2; R1 is now in C.
    # Step 3: eta_R1,G1 = 1/4, eta_R1,G2 = 1/4, tie -> G1; R1 keeps T1, drops T2.
    # Step 4: T2 still has R3, no repair. Step 5: no empty group.
    partition = partition_matrices([[1, 1], [1, 0], [0, 1]])
    assert partition.groups == {"G1": {"R1": ["T1"], "R2": ["T1"]}, "G2": {"R3": ["T2"]}}
    assert partition.dropped == [("R1", "T2")]


def test_hand_computed_willingness_breaks_the_tie():
    # As above but d_11 = 0.5: w_11 = 0.5/4 = 1/8 < w_12 = 1/4, so R1 now chooses G2 and keeps T2.
    partition = partition_matrices([[1, 1], [1, 0], [0, 1]], [[0.5, 1.0], [1.0, 0.0], [0.0, 1.0]])
    assert partition.groups == {"G1": {"R2": ["T1"]}, "G2": {"R1": ["T2"], "R3": ["T2"]}}
    assert partition.dropped == [("R1", "T1")]


def test_hand_computed_robot_tie_goes_to_largest_willingness():
    # R1: {T3: 0.5}, R2: {T2: 0.5, T3: 0.5}, R3: {T1: 0.5, T3: 1.0}.
    # Step 1: r0 = (1, 2, 2), c0 = (1, 1, 3); w_13 = 0.5/3 = 1/6, w_22 = 0.5/2 = 1/4,
    #   w_23 = 0.5/6 = 1/12, w_31 = 0.5/2 = 1/4, w_33 = 1/6.
    # Iteration 1: c = (1, 1, 3) -> T3; r = (1, 2, 2) -> R1; new G1 = home(T3).
    # Iteration 2: c = (1, 1, 2) -> T3; R2 and R3 tie on r = 2, d_33 = 1.0 > d_23 = 0.5 -> R3,
    #   who joins G1.
    # Iteration 3: c = (1, 1, 1), omega = (r3, r2, r2) = (1, 2, 2) -> T1; R3 is in G1, so
    #   home(T1) = G1.
    # Iteration 4: c = (0, 1, 1), omega T2 = T3 = 2 -> T2 (lowest index); R2 is in no group ->
    #   new G2 = home(T2).
    # Iteration 5: T3 -> R2 joins home(T3) = G1; R2 is in C.
    # Step 3: R2 has eta G1 = 1/12 < eta G2 = 1/4, so it stays in G2 and drops T3.
    # (Breaking the robot tie the other way picks R2 in iteration 2 and gives another partition.)
    partition = partition_matrices(
        [[0, 0, 1], [0, 1, 1], [1, 0, 1]], [[0, 0, 0.5], [0, 0.5, 0.5], [0.5, 0, 1.0]]
    )
    assert partition.groups == {"G1": {"R1": ["T3"], "R3": ["T1", "T3"]}, "G2": {"R2": ["T2"]}}
    assert partition.dropped == [("R2", "T3")]


def test_rounded_willingness_compares_equal():
    # d_11 = 0.3 and d_12 = 0.1 + 0.2 (= 0.30000000000000004 as a float) are the same willingness;
    # after Fraction.limit_denominator the tie of the first hand case is kept (R1 -> G1, keeps T1).
    # With raw floats T2 would win by 1e-17 and R1 would move to G2.
    partition = partition_matrices([[1, 1], [1, 0], [0, 1]], [[0.3, 0.1 + 0.2], [1, 0], [0, 1]])
    assert partition.groups == {"G1": {"R1": ["T1"], "R2": ["T1"]}, "G2": {"R3": ["T2"]}}


def test_repair_gives_orphan_task_back():
    # System-I step 3 leaves T5 with no robot (R1 and R4 choose T4's group, R6 chooses T1's);
    # step 4 returns T5 to the group of R1 and R4 (w sum 1/9 + 1/6 vs 1/9), and T5's own home
    # group is then empty and deleted (only 2 groups out of 3 created).
    partition = subg_partition(load_system("system1"))
    assert len(partition.groups) == 2
    assert partition.groups["G2"]["R1"] == ["T4", "T5"]
    assert partition.groups["G2"]["R4"] == ["T4", "T5"]


def test_single_robot_and_custom_names():
    partition = partition_matrices([[1, 1, 1]], robots=["R7"], task_types=["T1", "T2", "T3"])
    assert partition.groups == {"G1": {"R7": ["T1", "T2", "T3"]}}
    assert partition.dropped == []


# --- properties over random systems ----------------------------------------------------------


def check_invariants(system: RobotSystem, partition: Partition) -> None:
    names = list(partition.groups)
    assert names == [f"G{k}" for k in range(1, len(names) + 1)]
    robot_group = {}
    task_group = {}
    for name, robots in partition.groups.items():
        assert robots, "empty groups are deleted"
        # robots in system order, task types in numeric order
        assert list(robots) == sorted(robots, key=system.robots.index)
        for robot, kept in robots.items():
            assert robot not in robot_group, f"{robot} in two groups"
            robot_group[robot] = name
            assert kept, f"{robot} keeps no task type"
            assert kept == sorted(kept, key=system.task_types.index)
            gamma = system.task_set(robot)
            assert set(kept) <= set(gamma), "Lambda_i must be a subset of Gamma_i"
            for task in kept:
                assert task_group.setdefault(task, name) == name, f"{task} in two groups"
    assert set(robot_group) == set(system.robots)  # every robot in exactly one group
    assert set(task_group) == set(system.task_types)  # every task type kept by some robot
    expected_dropped = [
        (r, t)
        for r in system.robots
        for t in system.task_types
        if t in system.task_set(r) and t not in partition.groups[robot_group[r]][r]
    ]
    assert partition.dropped == expected_dropped
    active = partition.active_tasks(system)
    assert not (active & (system.rtm == 0)).any()
    assert active.any(axis=1).all() and active.any(axis=0).all()


@settings(max_examples=150, deadline=None)
@given(
    n_robots=st.integers(1, 30),
    n_task_types=st.integers(1, 12),
    density=st.floats(0.0, 1.0),
    seed=st.integers(0, 2**31 - 1),
)
def test_random_system_invariants(n_robots, n_task_types, density, seed):
    system = random_system(n_robots, n_task_types, density, seed)
    partition = subg_partition(system)
    check_invariants(system, partition)
    assert subg_partition(system) == partition  # deterministic


@settings(max_examples=100, deadline=None)
@given(
    n_robots=st.integers(1, 30),
    n_task_types=st.integers(1, 10),
    density=st.floats(0.0, 1.0),
    seed=st.integers(0, 2**31 - 1),
)
def test_random_willingness_invariants(n_robots, n_task_types, density, seed):
    base = random_system(n_robots, n_task_types, density, seed)
    rng = np.random.default_rng(seed)
    levels = rng.choice([0.25, 0.5, 0.9, 1.0], size=base.willingness.shape)  # ties stay likely
    system = RobotSystem("noisy", base.robots, base.task_types, base.willingness * levels)
    check_invariants(system, subg_partition(system))


# --- size bound: partition.max_group_size ---------------------------------------------------


@pytest.mark.parametrize("name", ["system1", "system2"])
@pytest.mark.parametrize("bound", [None, 4, 100])
def test_bound_not_reached_keeps_tables_3_and_4(name, bound):
    # Table 3 and 4 sub-groups have at most 4 robots: a bound of 4 or more changes nothing.
    system = load_system(name)
    assert subg_partition(system, bound) == subg_partition(system)


def test_bound_splits_system2():
    # g = 3: G1 {R2, R5, R6, R8} and G3 {R3, R4, R7, R9} of Table 4 are split, G2 {R1, R10} stays.
    system = load_system("system2")
    partition = subg_partition(system, 3)
    assert max(len(r) for r in partition.groups.values()) <= 3
    assert partition.group_map()["G3"] == ["R1", "R10"]  # untouched, renumbered after G1's chunks
    check_bounded(system, partition, 3)


def test_bound_hand_computed_split():
    # Five robots that can all do T1 and T2; the paper's rule gives one sub-group of five.
    # r0_i = 2, c0_j = 5, so w_ij = d_ij / 10.
    # Anchors (largest w, ties to the lowest type): R1 T1 (.1 > .05), R2 T2 (.1 > .05), R3 T1 (tie),
    #   R4 T1 (tie .05), R5 T1 (.1 > .025). Classes, strongest first: T1 [R1, R3, R5, R4], T2 [R2].
    # g = 2: pieces T1 [R1, R3], T1 [R5, R4], T2 [R2]; first-fit decreasing -> three chunks.
    # Each robot keeps its chunk's types: only its anchor. T1 is shared by the first two chunks.
    d = [[1, 0.5], [0.5, 1], [1, 1], [0.5, 0.5], [1, 0.25]]
    assert partition_matrices(np.ones((5, 2)), d).group_map() == {
        "G1": ["R1", "R2", "R3", "R4", "R5"]
    }
    partition = partition_matrices(np.ones((5, 2)), d, max_group_size=2)
    assert partition.groups == {
        "G1": {"R1": ["T1"], "R3": ["T1"]},
        "G2": {"R4": ["T1"], "R5": ["T1"]},
        "G3": {"R2": ["T2"]},
    }
    assert partition.dropped == [
        ("R1", "T2"),
        ("R2", "T1"),
        ("R3", "T2"),
        ("R4", "T2"),
        ("R5", "T2"),
    ]
    assert not partition.types_disjoint()
    assert partition.group_tasks() == {"G1": ["T1"], "G2": ["T1"], "G3": ["T2"]}


def test_bound_repair_of_a_type_nobody_anchors():
    # R1 {T1, T2}, R2 {T1}, R3 {T1}, d = 1: r0 = (2, 1, 1), c0 = (3, 1).
    # w_11 = 1/6, w_12 = 1/2, w_21 = w_31 = 1/3. Unbounded: one sub-group (R1 keeps both).
    # g = 2: anchors R1 T2 (1/2), R2 T1, R3 T1. Pieces: T1 [R2, R3], T2 [R1] -> two chunks;
    # every type is somebody's anchor, so R1 keeps only T2 and drops T1.
    rtm = [[1, 1], [1, 0], [1, 0]]
    assert partition_matrices(rtm).group_map() == {"G1": ["R1", "R2", "R3"]}
    partition = partition_matrices(rtm, max_group_size=2)
    assert partition.groups == {"G1": {"R2": ["T1"], "R3": ["T1"]}, "G2": {"R1": ["T2"]}}
    # R1 {T1, T2, T3}, R2 {T1}: r0 = (3, 1), c0 = (2, 1, 1); w_11 = 1/6, w_12 = w_13 = 1/3,
    # w_21 = 1/2. g = 1: anchors R1 T2 (tie with T3 -> lowest), R2 T1. Pieces [R2] (T1) and
    # [R1] (T2), equal size -> type order: R2's chunk first. T3 is nobody's anchor: it goes to the
    # chunk whose robots keeping it depend on it most, R1's (1/3 vs 0); R1 drops T1.
    partition = partition_matrices([[1, 1, 1], [1, 0, 0]], max_group_size=1)
    assert partition.groups == {"G1": {"R2": ["T1"]}, "G2": {"R1": ["T2", "T3"]}}
    assert partition.dropped == [("R1", "T1")]


def check_bounded(system: RobotSystem, partition: Partition, bound: int) -> None:
    """At most g robots per group, every type served, every robot in exactly one group."""
    seen = [r for robots in partition.groups.values() for r in robots]
    assert sorted(seen, key=system.robots.index) == list(system.robots)  # each robot exactly once
    assert all(1 <= len(robots) <= bound for robots in partition.groups.values())
    active = partition.active_tasks(system)
    assert active.any(axis=0).all(), "every task type keeps a robot"
    assert active.any(axis=1).all(), "every robot keeps a task type"
    assert not (active & (system.rtm == 0)).any()
    assert list(partition.groups) == [f"G{k}" for k in range(1, len(partition.groups) + 1)]
    expected_dropped = [
        (r, t)
        for name, robots in partition.groups.items()
        for r in robots
        for t in system.task_set(r)
        if t not in partition.groups[name][r]
    ]
    assert sorted(partition.dropped) == sorted(expected_dropped)


@settings(max_examples=150, deadline=None)
@given(
    n_robots=st.integers(1, 80),
    n_task_types=st.integers(1, 15),
    density=st.floats(0.0, 1.0),
    seed=st.integers(0, 2**31 - 1),
    bound=st.integers(1, 8),
)
def test_bounded_random_team_invariants(n_robots, n_task_types, density, seed, bound):
    system = random_system(n_robots, n_task_types, density, seed)
    partition = subg_partition(system, bound)
    check_bounded(system, partition, bound)
    assert subg_partition(system, bound) == partition  # deterministic
    unbounded = subg_partition(system)
    if max(len(r) for r in unbounded.groups.values()) <= bound:
        assert partition == unbounded  # the bound only acts on oversized sub-groups
    else:
        # groups within the bound are kept as they are
        small = [g for g in unbounded.groups.values() if len(g) <= bound]
        assert all(g in partition.groups.values() for g in small)


@pytest.mark.parametrize("bad", [0, -1, 2.5, "4", True])
def test_bound_invalid_names_the_key(bad):
    with pytest.raises(ValueError, match="partition.max_group_size"):
        subg_partition(load_system("system1"), bad)


# --- invalid input ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("rtm", "willingness", "culprit"),
    [
        ([[1, 0], [0, 1], [0, 0]], None, "robot R3 has no task type"),
        ([[1, 0, 0], [1, 0, 1]], None, "task type T2"),
        ([[1, 2], [0, 1]], None, "robot R1"),
        ([[1, 0], [0.5, 1]], None, "robot R2"),
        ([[1, 0], [np.nan, 1]], None, "robot R2"),
        ([[1, 0], [1, 1]], [[1, 0], [1.5, 1]], "robot R2: willingness 1.5 for T1"),
        ([[1, 0], [1, 1]], [[1, 0], [1, 0]], "robot R2: willingness 0.0 for T2"),
        ([[1, 0], [1, 1]], [[-0.1, 0], [1, 1]], "robot R1"),
        ([[1, 0], [1, 1]], [[np.nan, 0], [1, 1]], "robot R1"),
    ],
)
def test_invalid_input_names_culprit(rtm, willingness, culprit):
    with pytest.raises(ValueError, match=culprit):
        partition_matrices(rtm, willingness)


def test_invalid_input_uses_given_names():
    with pytest.raises(ValueError, match="robot R9 has no task type"):
        partition_matrices([[1], [0]], robots=["R4", "R9"], task_types=["T1"])


@pytest.mark.parametrize(
    ("rtm", "willingness", "robots"),
    [
        ([], None, None),
        ([1, 0, 1], None, None),
        ([[1, 1]], [[1, 1, 1]], None),
        ([[1, 1]], None, ["R1", "R2"]),
        ([["a", 1]], None, None),
    ],
)
def test_malformed_shapes_raise(rtm, willingness, robots):
    with pytest.raises(ValueError):
        partition_matrices(rtm, willingness, robots)


def test_active_tasks_rejects_other_system():
    partition = subg_partition(load_system("system1"))
    with pytest.raises(ValueError, match="R7"):
        partition.active_tasks(load_system("system2"))


# --- output formats ----------------------------------------------------------------------------


def test_to_json_schema():
    partition = subg_partition(load_system("system1"))
    data = json.loads(json.dumps(partition.to_json()))
    assert set(data) == {"groups", "dropped"}
    assert [g["name"] for g in data["groups"]] == ["G1", "G2"]
    for group in data["groups"]:
        assert set(group) == {"name", "robots"}
        assert all(isinstance(t, str) for tasks in group["robots"].values() for t in tasks)
    assert data["groups"][0]["robots"] == {"R3": ["T1", "T3"], "R5": ["T1"], "R6": ["T1", "T3"]}
    assert data["dropped"] == [["R1", "T1"], ["R6", "T5"]]


def test_format_partition_lists_every_robot():
    text = format_partition(subg_partition(load_system("system1")))
    lines = text.splitlines()
    assert re.split(r"\s{2,}", lines[0]) == [
        "group",
        "robot",
        "kept task types",
        "dropped task types",
    ]
    assert any(line.split()[:2] == ["G2", "R1"] and line.endswith("T1") for line in lines)
    assert lines[-1] == "2 sub-groups, 6 robots, 2 dropped pairs"


def test_script_prints_only_json(tmp_path):
    result = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "partition.py"), "system=system2", "format=json"],
        cwd=tmp_path, capture_output=True, text=True, check=True, timeout=120,
    )  # fmt: skip
    assert json.loads(result.stdout) == subg_partition(load_system("system2")).to_json()
    assert list(tmp_path.iterdir()) == []  # no outputs/ or .hydra/ written
    bounded = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "partition.py"), "system=system2", "format=json",
         "partition.max_group_size=2"],
        cwd=tmp_path, capture_output=True, text=True, check=True, timeout=120,
    )  # fmt: skip
    assert json.loads(bounded.stdout) == subg_partition(load_system("system2"), 2).to_json()


@pytest.mark.parametrize(("bound", "disjoint"), [(2, True), (1, False)])
def test_training_run_uses_the_bound(bound, disjoint, compose_cfg, tmp_path):
    # partition.max_group_size reaches build_run: subg_greedy on System-II plays on the bounded
    # partition and writes it. g = 2 keeps every task type in one sub-group (R5 and R8 give T2 to
    # {R2, R6}); with g = 1 the robots anchored to T2 share it, and the return is not split.
    from mrta_rl.runners import train

    cfg = compose_cfg(
        [
            "learner=subg_greedy",
            "system=system2",
            "debug=smoke",
            f"partition.max_group_size={bound}",
        ]
    )
    metrics = train(cfg, run_dir=tmp_path)
    expected = subg_partition(load_system("system2"), bound)
    assert json.loads((tmp_path / "partition.json").read_text()) == expected.to_json()
    assert max(len(robots) for robots in expected.groups.values()) == bound
    assert expected.types_disjoint() is disjoint
    split = metrics["eval"].get("return_by_group")
    assert (split is not None) is disjoint
    if disjoint:
        assert list(split) == list(expected.groups)
    assert set(metrics["resources"]) == {"wall_s", "cpu_s", "peak_rss_mb", "peak_rss_scope"}
    assert metrics["resources"]["peak_rss_mb"] > 0

"""System files (paper Tables 1-2, random teams) and their validation errors."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from mrta_rl.envs.auction import AuctionEnv
from mrta_rl.envs.params import AuctionParams
from mrta_rl.systems import SystemConfigError, build_system, random_system

ROOT = Path(__file__).resolve().parents[2]


def load(name: str):
    return build_system(yaml.safe_load((ROOT / "conf" / "system" / f"{name}.yaml").read_text()))


def test_system1_is_paper_table_1():
    s = load("system1")
    assert s.robots == ("R1", "R2", "R3", "R4", "R5", "R6")
    assert s.task_types == ("T1", "T2", "T3", "T4", "T5")
    assert s.task_set("R6") == {"T1": 1.0, "T3": 1.0, "T5": 1.0}
    assert s.rtm.sum(axis=1).tolist() == [3, 2, 2, 2, 1, 3]  # r_i
    assert s.rtm.sum(axis=0).tolist() == [4, 1, 2, 3, 3]  # c_j


def test_system2_is_paper_table_2():
    s = load("system2")
    assert s.n_robots == 10 and s.n_task_types == 8
    assert s.task_set("R2") == {t: 1.0 for t in ("T1", "T2", "T5", "T7", "T8")}
    assert s.rtm.sum(axis=1).tolist() == [2, 5, 3, 4, 4, 2, 3, 3, 3, 3]


def test_willingness_mapping_and_duration_override():
    s = build_system(
        {
            "name": "w",
            "robots": {"R1": {"T1": 0.4, "T2": 1}, "R2": ["T2"]},
            "task_types": {"T2": {"duration_low": [1, 2]}},
        }
    )
    assert s.willingness.tolist() == [[0.4, 1.0], [0.0, 1.0]]
    assert (s.durations["T2"]["duration_low"].lo, s.durations["T2"]["duration_low"].hi) == (1, 2)


@pytest.mark.parametrize(
    "robots, task_types, message",
    [
        ({"R1": ["T1"], "R2": []}, None, "robot R2 has no task type"),
        ({"R1": ["T1"], "R2": None}, None, "robot R2 has no task type"),
        (
            {"R1": ["T1"]},
            {"T9": {"duration_low": [1, 2]}},
            "task_types: task type 'T9' is listed, but no robot in 'robots' can do it",
        ),
        ({"R1": {"T1": 1.5}}, None, r"robot R1: willingness 1.5 for T1 is outside \(0, 1\]"),
        ({"R1": {"T1": 0}}, None, r"robot R1: willingness 0 for T1 is outside \(0, 1\]"),
        ({"R1": {"T1": "high"}}, None, "robot R1: willingness 'high' for T1"),
        ({"R1": ["T1", 1.5]}, None, "robot R1: task type name must be a non-empty string, got 1.5"),
        ({"R1": ["T1", ""]}, None, "robot R1: task type name must be a non-empty string, got ''"),
        ({"R1": ["T1"]}, ["T1"], "'task_types' must be a mapping"),
        ({"R1": ["T1"]}, {"T1": {"duration_low": [5, 2]}}, "task type T1: duration_low must be"),
        ({"R1": ["T1"]}, {"T1": {"duration": [1, 2]}}, "task type T1: unknown key 'duration'"),
    ],
)
def test_malformed_system_is_a_clear_error_naming_the_culprit(robots, task_types, message):
    cfg = {"name": "bad", "robots": robots}
    if task_types:
        cfg["task_types"] = task_types
    with pytest.raises(SystemConfigError, match=message):
        build_system(cfg)


def test_task_and_robot_names_are_labels():
    """Any names; task types in natural order, paper names unchanged."""
    s = build_system(
        {
            "name": "labels",
            "robots": {"R1": ["pick", "T99"], "arm_2": {"T10": 0.5, "T2": 1}},
            "task_types": {"pick": {"duration_high": [2, 4]}},
        }
    )
    assert s.robots == ("R1", "arm_2")
    assert s.task_types == ("T2", "T10", "T99", "pick")  # digits compared as numbers
    assert s.task_set("R1") == {"T99": 1.0, "pick": 1.0}
    assert s.task_set("arm_2") == {"T2": 1.0, "T10": 0.5}
    assert s.durations["pick"]["duration_high"].hi == 4
    # a gap in T1..Tn is no longer a phantom task type nobody can do
    assert build_system({"robots": {"R1": ["T1", "T3"]}}).task_types == ("T1", "T3")


def test_labelled_system_trains_and_reports_by_name(compose_cfg, tmp_path):
    """End to end: a greedy run on a labelled system, CTR keyed by the names."""
    from omegaconf import OmegaConf, open_dict

    from mrta_rl.runners import train

    cfg = compose_cfg(["learner=subg_reserve", "debug=smoke"])
    with open_dict(cfg):
        cfg.system = OmegaConf.create(
            {"name": "labels", "robots": {"R1": ["pick", "T99"], "R2": ["T99"], "R3": ["pick"]}}
        )
    metrics = train(cfg, run_dir=tmp_path)
    assert list(metrics["eval"]["ctr"]) == ["T99", "pick"]
    assert list(metrics["eval"]["itr"]) == ["R1", "R2", "R3"]
    groups = metrics["eval"]["return_by_group"]
    assert sorted(t for g in groups.values() for t in g["types"]) == ["T99", "pick"]


@pytest.mark.parametrize("env", [[1, 2], "ab", 5])
@pytest.mark.parametrize("form", [{"robots": {"R1": ["T1"]}}, {"n_robots": 3}])
def test_an_env_block_that_is_not_a_mapping_is_named(form, env):
    with pytest.raises(SystemConfigError, match="system 'x': env must be a mapping"):
        build_system({"name": "x", **form, "env": env})


def test_unknown_top_level_key_is_named():
    with pytest.raises(SystemConfigError, match="unknown keys \\['robot'\\]"):
        build_system({"name": "x", "robots": {"R1": ["T1"]}, "robot": 3})


def test_bad_system_file_fails_before_any_run_writes_output(tmp_path):
    bad_dir = tmp_path / "systems"
    (bad_dir / "system").mkdir(parents=True)
    (bad_dir / "system" / "broken.yaml").write_text(
        "name: broken\nrobots:\n  R1: [T1]\n  R2: {T1: 2.0}\n"
    )
    run_dir = tmp_path / "run"
    proc = subprocess.run(
        [
            sys.executable,
            str(ROOT / "scripts" / "train.py"),
            "learner=greedy",
            "system=broken",
            f"hydra.searchpath=[file://{bad_dir}]",
            f"hydra.run.dir={run_dir}",
        ],
        capture_output=True,
        text=True,
        cwd=ROOT,
    )
    assert proc.returncode != 0
    assert "robot R2: willingness 2.0 for T1 is outside (0, 1]" in proc.stderr + proc.stdout
    assert not (run_dir / "metrics.json").exists()


@settings(max_examples=40, deadline=None)
@given(
    m=st.integers(1, 40), n=st.integers(1, 15), density=st.floats(0, 1), seed=st.integers(0, 10**6)
)
def test_random_systems_are_valid_and_reproducible(m, n, density, seed):
    s = random_system(m, n, density, seed)
    assert s.rtm.shape == (m, n)
    assert (
        s.rtm.any(axis=1).all() and s.rtm.any(axis=0).all()
    )  # every robot a type, every type a robot
    np.testing.assert_array_equal(s.rtm, random_system(m, n, density, seed).rtm)


def test_random_system_config_and_scaling_size():
    s = build_system(
        {"name": "random", "n_robots": 300, "n_task_types": 30, "density": 0.1, "seed": 4}
    )
    assert s.n_robots == 300 and s.n_task_types == 30
    with pytest.raises(SystemConfigError, match=r"system.density: must be a number in \[0, 1\]"):
        random_system(3, 3, 1.5, 0)


def test_random_system_scales_the_auction_with_the_team():
    # System-I/II per robot: 3 slots, a queue of 32 and one auction zone per 10 robots, rounded up
    assert random_system(10, 4, 0.5, 0).env_overrides == {}
    assert random_system(10, 4, 0.5, 0, scale_auction=True).env_overrides == {
        "slots": 3,
        "queue_capacity": 32,
        "zones": 1,
    }
    assert random_system(55, 4, 0.5, 0, scale_auction=True).env_overrides == {
        "slots": 17,  # ceil(16.5)
        "queue_capacity": 176,
        "zones": 6,  # ceil(5.5)
    }
    s = build_system(
        {"name": "random", "n_robots": 200, "scale_auction": True, "env": {"slots": 25}}
    )
    assert s.env_overrides == {"slots": 25, "queue_capacity": 640, "zones": 20}  # env wins
    with pytest.raises(SystemConfigError, match=r"system.scale_auction"):
        random_system(3, 3, 0.5, 0, scale_auction="yes")


def _greedy_regime(n_robots: int) -> np.ndarray:
    """Greedy's CTR of L and H tasks and share of busy robot-ticks, in percent, on a scaled team."""
    system = random_system(n_robots, 12, 0.25, seed=0, scale_auction=True)
    params = AuctionParams.merged(system.env_overrides, {"horizon": 400})
    stats = AuctionEnv(system, params, batch_size=4, seed=2_000_000).play("greedy", episodes=1)
    assigned, dropped = stats.assigned.sum(axis=(0, 1)), stats.dropped.sum(axis=(0, 1))
    busy = stats.busy_ticks.sum() / (stats.ticks.sum() * n_robots)
    return 100 * np.array([*(assigned / (assigned + dropped)), busy])


def test_scaled_auction_keeps_greedys_regime_per_robot_from_10_to_200_robots():
    # one auction for the whole team serves one task per type and tick under greedy: at 200
    # robots and 12 types it completed 8 % of L tasks (55 % at 10 robots) with every robot busy
    at_10 = _greedy_regime(10)
    assert 45 < at_10[0] < 65 and 60 < at_10[1] < 78 and 70 < at_10[2] < 90
    for n_robots in (50, 200):
        np.testing.assert_allclose(_greedy_regime(n_robots), at_10, atol=6)

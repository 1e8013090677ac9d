"""Training on a family of teams (system.family), and a learned state played on any team (init=)."""

from __future__ import annotations

import json
import signal
from pathlib import Path

import numpy as np
import pytest
import yaml

from mrta_rl.config import ConfigError
from mrta_rl.runners import train
from mrta_rl.systems import SystemConfigError, build_system, system_shape
from mrta_rl.systems.family import EVAL_TEAM, build_family
from tests.runners.test_checkpoint import (
    assert_same_run,
    resumed_run,
    save_hydra_files,
    script,
    wait_for_checkpoint,
)

ROOT = Path(__file__).resolve().parents[2]
FAMILY = yaml.safe_load((ROOT / "conf" / "system" / "family.yaml").read_text())
SMOKE = ["learner=net_es", "system=family", "debug=smoke"]


def saved_theta(run_dir: Path) -> np.ndarray:
    with np.load(run_dir / "learner" / "net_es.npz") as saved:
        return saved["theta"]


def test_teams_are_drawn_in_the_ranges_the_same_every_time():
    family = build_family(FAMILY)
    ranges = FAMILY["family"]
    teams = [family.team(k) for k in range(30)]
    for k, team in enumerate(teams):
        assert team.name == f"family[{k}]"
        assert ranges["n_robots"][0] <= team.n_robots <= ranges["n_robots"][1]
        assert ranges["n_task_types"][0] <= team.n_task_types <= ranges["n_task_types"][1]
        # the scaled auction: 3 slots per 10 robots, rounded up (System-II: 3)
        assert team.env_overrides["slots"] == -(-3 * team.n_robots // 10)
        assert np.array_equal(team.willingness, family.team(k).willingness)
    assert len({t.n_robots for t in teams}) > 5  # the teams differ
    # the run plays team 0; the config's shape is the largest team, for the memory check
    assert build_system(FAMILY).name == f"family[{EVAL_TEAM}]"
    assert system_shape(FAMILY) == (ranges["n_robots"][1], ranges["n_task_types"][1])


def test_willingness_is_drawn_per_pair_in_its_range():
    family = build_family({**FAMILY, "family": {**FAMILY["family"], "willingness": [0.5, 0.8]}})
    d = family.team(3).willingness
    assert ((d == 0) | ((d >= 0.5) & (d <= 0.8))).all() and (d > 0).any()
    assert len(np.unique(d[d > 0])) > 1


@pytest.mark.parametrize(
    ("family", "match"),
    [
        ({"n_robots": [10, 5], "n_task_types": [3, 4], "density": [0.2, 0.3]}, "family.n_robots"),
        ({"n_robots": [5, 10], "n_task_types": [3, 4], "density": [0.2, 1.5]}, "family.density"),
        ({"n_robots": [5.5, 10], "n_task_types": [3, 4], "density": [0.2, 0.3]}, "integers"),
        ({"n_robots": [5, 10], "n_task_types": [3, 4]}, "lacks \\['density'\\]"),
        (
            {"n_robots": [5, 10], "n_task_types": [3, 4], "density": [0.2, 0.3], "size": [1, 2]},
            "unknown keys \\['size'\\]",
        ),
        (
            {
                "n_robots": [5, 10],
                "n_task_types": [3, 4],
                "density": [0.2, 0.3],
                "willingness": [0, 1],
            },
            "family.willingness",
        ),
    ],
)
def test_bad_ranges_are_refused_naming_the_key(family, match):
    with pytest.raises(SystemConfigError, match=match):
        build_family({"name": "family", "family": family})


def test_a_family_run_trains_on_its_teams_and_is_evaluated_on_team_0(compose_cfg, tmp_path):
    metrics = train(compose_cfg([*SMOKE, "train.episodes=3"]), run_dir=tmp_path)
    family = build_family(FAMILY)
    trained_on = json.loads((tmp_path / "learner" / "team.json").read_text())
    assert trained_on["robots"] == list(family.team(3).robots)  # the last episode's team
    assert metrics["system"] == "family" and metrics["train"]["episodes"] == 3
    evaluated = family.team(EVAL_TEAM)
    assert set(metrics["eval"]["ctr"]) == set(evaluated.task_types)


def test_init_plays_a_family_policy_on_another_team(compose_cfg, tmp_path):
    """Zero-shot: the family run's weights, unchanged, on System-I, against greedy as usual."""
    family = compose_cfg([*SMOKE, "train.episodes=3"])
    save_hydra_files(family, tmp_path / "family", "net_es", "family")  # a run dir, as Hydra's
    train(family, run_dir=tmp_path / "family")
    zero = train(
        compose_cfg(
            [
                "learner=net_es",
                "system=system1",
                "debug=smoke",
                "train.episodes=0",
                f"init={tmp_path / 'family'}",
            ]
        ),
        run_dir=tmp_path / "zero",
    )
    assert np.array_equal(saved_theta(tmp_path / "zero"), saved_theta(tmp_path / "family"))
    assert zero["system"] == "system1" and "baseline_greedy" in zero
    train(
        compose_cfg(["learner=net_es", "system=system1", "debug=smoke", "train.episodes=0"]),
        run_dir=tmp_path / "untrained",
    )
    assert not np.array_equal(saved_theta(tmp_path / "untrained"), saved_theta(tmp_path / "zero"))


@pytest.mark.parametrize(
    ("overrides", "match"),
    [
        (["learner=qmix", "system=family"], "qmix .* tied to one team.*net_es"),
        (["learner=qmix", "init=somewhere"], "init: learner qmix .* tied to one team"),
        (["learner=net_es", "init=/nonexistent/run"], "init: /nonexistent/run"),
    ],
)
def test_learners_tied_to_one_team_are_refused_before_any_work(
    compose_cfg, tmp_path, overrides, match
):
    with pytest.raises(ConfigError, match=match):
        train(compose_cfg([*overrides, "debug=smoke"]), run_dir=tmp_path / "run")
    assert not (tmp_path / "run").exists()


def test_init_refuses_a_run_of_another_learner(compose_cfg, tmp_path):
    family = compose_cfg([*SMOKE, "train.episodes=1"])
    save_hydra_files(family, tmp_path / "family", "net_es", "family")
    train(family, run_dir=tmp_path / "family")
    with pytest.raises(ConfigError, match="trained NetESLearner, not ReserveESLearner"):
        train(
            compose_cfg(["learner=reserve_es", "debug=smoke", f"init={tmp_path / 'family'}"]),
            run_dir=tmp_path / "run",
        )
    assert not (tmp_path / "run").exists()


def test_a_family_run_killed_and_resumed_ends_like_an_uninterrupted_run(compose_cfg, tmp_path):
    args = [*SMOKE, "train.episodes=40", "train.checkpoint_every=5"]
    full_dir, cut_dir = tmp_path / "full", tmp_path / "cut"
    cut = script("scripts/train.py", *args, f"hydra.run.dir={cut_dir}")
    killed_after = wait_for_checkpoint(cut, cut_dir / "train.log", 15)
    cut.send_signal(signal.SIGKILL)
    cut.wait()
    resumed = script("scripts/train.py", f"resume={cut_dir}")
    train(compose_cfg(args), run_dir=full_dir)
    assert killed_after <= resumed_run(resumed, cut_dir) < 40
    assert_same_run(full_dir, cut_dir)

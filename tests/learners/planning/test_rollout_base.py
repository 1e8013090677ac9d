"""``rollout`` with a trained run as its base policy (``learner.base=<run dir>``).

The base is a tiny ``reserve_es`` run on System-I; the runner rebuilds it from its run dir and
the planner plays it on its own env and on the rollout copies. Bad bases are refused through
``scripts/train.py``: one ``error:`` line naming ``learner.base`` and the culprit, no run dir.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from mrta_rl.envs import AuctionEnv, AuctionParams
from mrta_rl.learners.planning import rollout
from mrta_rl.learners.planning.rollout import RolloutPlanner, neighbours
from mrta_rl.run_layout import read_metrics
from mrta_rl.runners import train as run_train
from mrta_rl.runners.train import load_base, load_run
from tests.commands.test_cli import assert_user_error, train
from tests.conftest import compose_config, paper_system
from tests.learners.planning.test_rollout import play
from tests.runners.test_checkpoint import save_hydra_files

BASE = ["learner=reserve_es", "system=system1", "debug=smoke", "train.episodes=2"]
BASE += ["train.batch_size=24", "learner.pairs=2"]


def finished_run(run_dir: Path, overrides: list[str], learner: str, system: str) -> Path:
    """A run of ``scripts/train.py`` made in this process (config files as Hydra writes them)."""
    cfg = compose_config(overrides)
    save_hydra_files(cfg, run_dir, learner, system)
    run_train(cfg, run_dir=run_dir)
    return run_dir


@pytest.fixture(scope="module")
def base_run(tmp_path_factory) -> Path:
    """A trained reserve_es run on System-I: 2 ES steps of 2 pairs on 24 copies."""
    return finished_run(tmp_path_factory.mktemp("base") / "run", BASE, "reserve_es", "system1")


def planner_on(run_dir: Path | str, seed: int = 3, **hp) -> tuple[RolloutPlanner, AuctionEnv]:
    """The planner on ``run_dir``'s trained learner, which the runner loads (``load_base``)."""
    env = AuctionEnv(paper_system("system1"), AuctionParams(horizon=60), 3, seed=seed)
    base = load_base(Path(run_dir), env)
    planner = RolloutPlanner(
        env=env, rng=np.random.default_rng(0), base=str(run_dir), base_policy=base, **hp
    )
    return planner, env


def test_without_planning_it_plays_the_trained_base_tick_by_tick(base_run):
    planner, env = planner_on(base_run, horizon=0)
    learned = load_run(base_run).learner  # the base, rebuilt on its own training env
    ours, theirs = play(planner, env, learned)  # the learned policy on the planner's env
    np.testing.assert_array_equal(ours, theirs)
    assert ours.shape == (60, 3, 6)  # every tick of the 3 copies of System-I's 6 robots
    # the trained base is not the default rule base: the equality above is the run's policy
    env = AuctionEnv(paper_system("system1"), AuctionParams(horizon=60), 3, seed=3)
    rule = RolloutPlanner(env=env, rng=np.random.default_rng(0), horizon=0)
    assert (play(rule, env)[0] != ours).any()


class MillisecondClock:
    """A fake clock that moves 1 ms at each reading."""

    def __init__(self) -> None:
        self.readings = 0

    def __call__(self) -> float:
        self.readings += 1
        return self.readings / 1000


def decision_ms(ticks: int, planned: int, encodes: int) -> int:
    """The decision time on :class:`MillisecondClock`, in ms: ``encode`` reads the clock twice
    (1 ms), ``act`` twice around the planning, which reads it twice more when it plans (3 ms)."""
    return encodes + ticks + 2 * planned


def test_planning_on_a_trained_base_is_valid_deterministic_and_timed(base_run, monkeypatch):
    monkeypatch.setattr(rollout, "CLOCK", MillisecondClock())
    planner, env = planner_on(base_run, samples=2, horizon=5)
    first, _ = play(planner, env)  # env.step raises on an invalid action
    timing = planner.decision_time()
    assert timing["ticks"] == 60  # one decision per tick of the episode
    planned = timing["planned_ticks"]
    assert 0 < planned <= 60
    assert timing["total_s"] == decision_ms(60, planned, encodes=60) / 1000
    assert timing["ms_per_tick"] == round(decision_ms(60, planned, encodes=60) / 60, 4)
    again, _ = play(*planner_on(base_run, samples=2, horizon=5))
    np.testing.assert_array_equal(first, again)


def test_neighbours_of_a_trained_base_move_one_bid_of_its_action(base_run):
    """No rule candidates: each tick plays the learned action or one of its neighbours."""
    planner, env = planner_on(
        base_run, samples=2, horizon=5, candidates=[], neighbours=["drop", "add"]
    )
    learned = load_run(base_run).learner
    moved = 0
    while not env.done.all():
        mask = env.action_mask.copy()
        base = learned.act(learned.encode(env), mask, explore=False)
        actions = planner.act(planner.encode(env), mask, explore=False)
        near = neighbours(base, mask, ("drop", "add"))
        assert ((near == actions).all(axis=-1).any(axis=0) | (base == actions).all(axis=-1)).all()
        moved += int((actions != base).any(axis=-1).sum())
        env.step(actions)  # raises on an invalid action
    assert planner.decision_time()["planned_ticks"] > 0 and moved > 0


def test_a_run_with_a_trained_base_records_its_decision_time(base_run, tmp_path, monkeypatch):
    monkeypatch.setattr(rollout, "CLOCK", MillisecondClock())
    overrides = ["learner=rollout", "system=system1", "debug=smoke", f"learner.base={base_run}"]
    overrides += ["learner.horizon=3", "learner.samples=1"]
    run_dir = finished_run(tmp_path / "run", overrides, "rollout", "system1")
    evaluation = json.loads((run_dir / "metrics.json").read_text())["eval"]
    assert read_metrics(run_dir / "metrics.json")["eval"] == evaluation  # reports read it
    timing = evaluation["decision_time"]
    assert timing["ticks"] == 50  # debug=smoke: one round of 2 copies, a horizon of 50 ticks
    planned = timing["planned_ticks"]
    assert 0 <= planned <= 50
    # evaluation also encodes the state the episode ends in
    assert timing["total_s"] == decision_ms(50, planned, encodes=51) / 1000
    assert timing["ms_per_tick"] == round(decision_ms(50, planned, encodes=51) / 50, 4)


def test_a_rule_base_keeps_its_metrics_and_adds_only_its_decision_time(tmp_path):
    """Rule names work as before; the greedy baseline's block has no decision time."""
    overrides = ["learner=rollout", "system=system1", "debug=smoke", "learner.base=greedy"]
    metrics = run_train(compose_config(overrides), run_dir=tmp_path / "run")
    assert metrics["eval"]["decision_time"]["ticks"] == 50
    assert "decision_time" not in metrics["baseline_greedy"]


@pytest.fixture(scope="module")
def other_team_run(tmp_path_factory) -> Path:
    """A finished greedy run on System-II."""
    run_dir = tmp_path_factory.mktemp("other") / "run"
    return finished_run(run_dir, ["system=system2", "debug=smoke"], "greedy", "system2")


@pytest.mark.parametrize(
    ("case", "named"),
    [
        ("missing", ["learner.base", "no such run dir", "nowhere"]),
        ("not_a_run", ["learner.base", "is not a run dir of scripts/train.py", "plain"]),
        ("other_team", ["learner.base", "another team", "robots"]),
        ("unknown_rule", ["learner.base", "'hold_group'", "'hold3'"]),
    ],
)
def test_a_bad_base_is_one_line_naming_the_key_and_leaves_no_run_dir(
    case, named, other_team_run, tmp_path
):
    (tmp_path / "plain").mkdir()
    base = {
        "missing": tmp_path / "nowhere",
        "not_a_run": tmp_path / "plain",
        "other_team": other_team_run,
        "unknown_rule": "hold3",
    }[case]
    run_dir = tmp_path / "run"
    code, _, err = train(run_dir, "learner=rollout", f"learner.base={base}")
    assert_user_error(code, err, *named)
    assert err.count("\n") == 1
    assert not run_dir.exists()

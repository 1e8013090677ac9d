"""The learner benchmark's bookkeeping: which learners a checkout has, and its table."""

from __future__ import annotations

import pytest

from mrta_rl.bench.learners import (
    format_neural_table,
    format_table,
    learners_in,
    search_path,
    trained_learners,
)
from tests.conftest import ROOT


def test_the_benchmarked_learners_are_the_shipped_ones_that_train():
    trained = trained_learners()
    tabular = ["cql", "dql", "semi_cql", "subg_cql"]
    neural = ["expert_iteration", "ippo", "iql", "mappo", "qmix", "subg_dqn", "vdn"]
    assert trained == sorted([*tabular, *neural, "net_es", "reserve_es"])  # no fixed policy
    assert learners_in(ROOT, trained) == trained


def test_a_user_config_dirs_learner_is_composed_and_counted_for_every_checkout(
    tmp_path, compose_cfg
):
    (tmp_path / "mine" / "learner").mkdir(parents=True)
    (tmp_path / "mine" / "learner" / "mine.yaml").write_text(
        "_target_: mrta_rl.learners.fixed.RandomLearner\n_partial_: true\n"
    )
    cfg = compose_cfg(["learner=mine", *search_path([tmp_path / "mine"])])
    assert cfg.learner._target_ == "mrta_rl.learners.fixed.RandomLearner"
    assert learners_in(tmp_path, ["mine", "dql"], [tmp_path / "mine"]) == ["mine"]
    assert trained_learners([tmp_path / "mine"]) == trained_learners()  # a fixed policy


def test_a_checkout_without_a_learner_measures_the_others(tmp_path):
    (tmp_path / "conf" / "learner").mkdir(parents=True)
    (tmp_path / "conf" / "learner" / "dql.yaml").write_text("")
    assert learners_in(tmp_path, ["reserve_es", "dql"]) == ["dql"]


def row(code: str, learner: str, speed: float) -> dict:
    keys = ("ticks_per_s", "cpu_ticks_per_s")
    return {
        "code": code,
        "learner": learner,
        "batch_size": 16,
        **{f"{k}_{stat}": speed for k in keys for stat in ("min", "median")},
        "vs_env_median": 0.5,
        "vs_plain_min": 2.0,
        "vs_plain_median": 2.5,
        "learner_us_per_tick_median": 10.0,
    }


def test_table_speed_up_by_hand_and_dash_without_baseline():
    rows = [
        row("baseline", "dql", 100.0),
        row("this", "dql", 250.0),
        row("this", "reserve_es", 9.0),
    ]
    lines = format_table(rows).splitlines()
    this_dql = next(line for line in lines if "| dql | this |" in line)
    assert "| 2.5x / 2.5x | 2.5x / 2.5x |" in this_dql
    es = next(line for line in lines if "| reserve_es | this |" in line)
    assert "| - / - | - / - |" in es


def test_neural_table_shows_the_teachers_labels_beside_collection_and_training():
    """Rates by hand: min and median, speed-ups of the medians; no teacher: dashes."""
    rates = {"fps_collection": (900, 1000), "fps_training": (15000, 16000)}
    teacher = {"labels_per_s": (180, 200)}
    rows = [
        row("baseline", "qmix", 1) | flat(rates),
        row("this", "qmix", 1) | flat({k: (2 * a, 2 * b) for k, (a, b) in rates.items()}),
        row("this", "expert_iteration", 1) | flat(rates | teacher),
    ]
    lines = format_neural_table(rows).splitlines()
    assert "teacher labels/s min | median |" in lines[0]
    qmix = next(line for line in lines if "| qmix | this |" in line)
    assert qmix.endswith("| 1,800 | 2,000 | 2.0x | 30,000 | 32,000 | 2.0x | - | - |")
    teaching = next(line for line in lines if "| expert_iteration | this |" in line)
    assert teaching.endswith("| 900 | 1,000 | - | 15,000 | 16,000 | - | 180 | 200 |")


def flat(rates: dict) -> dict:
    return {
        f"{k}_{stat}": v
        for k, pair in rates.items()
        for stat, v in zip(("min", "median"), pair, strict=True)
    }


def test_overrides_reach_every_learner_run():
    from mrta_rl.bench.learners import run_worker

    out = run_worker(None, ["dql"], "system1", 1, 0.01, 5, overrides=["train.batch_size=3"])
    assert out["learners"]["dql"]["batch_size"] == 3
    assert out["learners"]["dql"]["ticks"] == 1 * 5 * 3  # episodes x horizon x copies
    with pytest.raises(RuntimeError, match="no_such_key"):
        run_worker(None, ["dql"], "system1", 1, 0.01, 5, overrides=["learner.no_such_key=1"])

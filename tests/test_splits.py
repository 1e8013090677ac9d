"""Evaluation splits: ``eval.split=test`` plays seeds 1,000,000 + b, ``validation`` 2,000,000 + b.

The seeds are written out by hand here (not imported), so a change of the streams fails a test.
"""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from mrta_rl.config import ConfigError
from mrta_rl.envs import AuctionEnv
from mrta_rl.reports import build_report
from mrta_rl.reports.collect import collect_runs, configuration_variants, load_run
from mrta_rl.runners import evaluate_policy
from mrta_rl.runners import train as run_train
from mrta_rl.runners.train import build_run, evaluate_checkpoint
from mrta_rl.runners.validation import validate_config
from tests.commands.test_cli import assert_user_error, script, train
from tests.conftest import compose_config
from tests.runners.test_checkpoint import save_hydra_files

FIRST_SEED = {"test": 1_000_000, "validation": 2_000_000}  # copy 0 of each split, by hand
RUN = ["learner=team_reserve", "system=system1", "debug=smoke", "eval.episodes=3"]
RUN += ["eval.batch_size=3"]  # one round: episode b is copy b's first


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, Path]:
    """A finished team_reserve run per split; the test run sets no eval key (the default)."""
    out = {}
    for split, extra in (("test", []), ("validation", ["eval.split=validation"])):
        run_dir = tmp_path_factory.mktemp(split) / "run"
        cfg = compose_config([*RUN, *extra])
        save_hydra_files(cfg, run_dir, "team_reserve", "system1")
        run_train(cfg, run_dir=run_dir)
        out[split] = run_dir
    return out


def metrics(run_dir: Path, name: str = "metrics.json") -> dict:
    return json.loads((run_dir / name).read_text())


def old_run(source: Path, target: Path) -> Path:
    """A copy of a test run as written before eval.split existed: ``eval.seed: 1000000``."""
    shutil.copytree(source, target)
    config = OmegaConf.load(target / ".hydra" / "config.yaml")
    del config.eval["split"]
    config.eval.seed = 1_000_000
    OmegaConf.save(config, target / ".hydra" / "config.yaml")
    return target


@pytest.mark.parametrize("split", ["test", "validation"])
def test_copy_b_plays_the_stream_of_an_env_seeded_the_splits_seed_plus_b(split, runs):
    recorded = metrics(runs[split])["eval"]
    assert recorded["split"] == split
    run = build_run(compose_config(RUN))  # the rule, built as the run built it
    for b in range(3):  # a single copy seeded by hand plays copy b's episode
        env = AuctionEnv(run.system, run.params, seed=FIRST_SEED[split] + b)
        alone = evaluate_policy(run.learner, env, 1, FIRST_SEED[split] + b)
        assert alone.to_json()["team_return"]["per_episode"] == [
            recorded["team_return"]["per_episode"][b]
        ]
    # the whole block is what evaluation on seeds 1,000,000 + b gave before splits existed
    env = AuctionEnv(run.system, run.params, batch_size=3, seed=FIRST_SEED[split])
    assert recorded == {
        **evaluate_policy(run.learner, env, 3, FIRST_SEED[split]).to_json(),
        "split": split,
    }


@pytest.mark.parametrize("learner", ["reserve_es", "rollout", "dql"])
def test_every_learner_kind_is_evaluated_on_the_split(learner, runs, tmp_path):
    """Policy search, the planner and a trained table: the same validation streams, recorded."""
    cfg = compose_config(
        [f"learner={learner}", *RUN[1:], "eval.split=validation", "eval.episodes=1"]
    )
    save_hydra_files(cfg, tmp_path, learner, "system1")
    result = run_train(cfg, run_dir=tmp_path)
    assert metrics(tmp_path) == json.loads(json.dumps(result))
    assert result["eval"]["split"] == "validation"
    # greedy's return on copy 0 is the stream's: that of the validation run's copy 0
    greedy = metrics(runs["validation"])["baseline_greedy"]["team_return"]["per_episode"]
    assert result["baseline_greedy"]["team_return"]["per_episode"] == greedy[:1]


def test_the_splits_play_different_streams(runs):
    test, validation = (metrics(runs[s])["baseline_greedy"] for s in ("test", "validation"))
    assert test["team_return"]["per_episode"] != validation["team_return"]["per_episode"]


def test_misspelled_split_is_one_line_naming_the_key_and_the_choices(tmp_path):
    run_dir = tmp_path / "run"
    code, _, err = train(run_dir, "learner=greedy", "eval.split=valdation")
    assert_user_error(code, err, "eval.split", "'test', 'validation'", "'valdation'")
    assert err.count("\n") == 1
    assert not run_dir.exists()


@pytest.mark.parametrize(
    ("overrides", "named"),
    [
        (["eval.seed=2000000"], "eval.seed: 2000000 contradicts eval.split=test"),
        (["eval.split=validation", "eval.seed=1000000"], "contradicts eval.split=validation"),
        (["eval.seed=7"], "eval.seed: 7 contradicts eval.split=test"),
        (["eval.batch_size=1000001"], "eval.batch_size: must be <= 1000000"),
        (["train.batch_size=1000001"], "train.batch_size: must be <= 1000000"),
    ],
)
def test_seeds_or_copies_that_would_play_other_streams_are_refused(overrides, named, compose_cfg):
    with pytest.raises(ConfigError, match=re.escape(named)):
        validate_config(compose_cfg(["system=system1", "debug=smoke", *overrides]))


@pytest.mark.parametrize("split", ["test", "validation"])
def test_seed_that_agrees_with_the_split_is_accepted(split, compose_cfg):
    cfg = compose_cfg([f"eval.split={split}", f"eval.seed={FIRST_SEED[split]}", "debug=smoke"])
    validate_config(cfg)


def test_evaluate_script_plays_the_split_it_is_given(runs, tmp_path):
    run_dir = shutil.copytree(runs["test"], tmp_path / "run")
    proc = script("evaluate.py", f"checkpoint={run_dir}", "eval.split=validation")
    out, err = proc.communicate(timeout=300)
    assert proc.returncode == 0, err
    assert "of the validation split" in out
    again = metrics(run_dir, "eval_metrics.json")
    assert again["eval"] == metrics(runs["validation"])["eval"]  # the same streams, the same rule
    assert again["baseline_greedy"] == metrics(runs["validation"])["baseline_greedy"]


def test_evaluate_script_refuses_a_misspelled_split_and_writes_nothing(runs, tmp_path):
    run_dir = shutil.copytree(runs["test"], tmp_path / "run")
    proc = script("evaluate.py", f"checkpoint={run_dir}", "eval.split=valdation")
    _, err = proc.communicate(timeout=300)
    assert_user_error(proc.returncode, err, "eval.split", "'test', 'validation'", "'valdation'")
    assert not (run_dir / "eval_metrics.json").exists()


def test_a_run_written_before_splits_is_evaluated_on_test_or_the_split_asked(runs, tmp_path):
    run_dir = old_run(runs["test"], tmp_path / "old")
    assert evaluate_checkpoint(run_dir)["eval"] == metrics(runs["test"])["eval"]
    on_validation = evaluate_checkpoint(run_dir, split="validation")
    assert on_validation["eval"] == metrics(runs["validation"])["eval"]


def test_reports_keep_the_splits_apart(runs, tmp_path):
    test, validation = load_run(runs["test"]), load_run(runs["validation"])
    before = load_run(old_run(runs["test"], tmp_path / "old"))
    assert configuration_variants([test, validation, before]) == [
        "eval.split=test",
        "eval.split=validation",
        "eval.split=test",
    ]
    assert configuration_variants([test, before]) == ["", ""]  # the same streams, named two ways


def test_tune_sweeps_on_validation(tmp_path):
    """experiment=tune at smoke size: two settings of its grid, both evaluated on validation."""
    sweep = tmp_path / "sweep"
    proc = script(
        "train.py",
        "-m",
        "experiment=tune",
        "debug=smoke",
        "system=system1",
        "learner.reserve=1",
        "learner.hold_level=0,1",
        "learner.hold_scope=robot",
        f"hydra.sweep.dir={sweep}",
    )
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 0, err
    collection = collect_runs([sweep])
    assert not collection.missing
    assert sorted(r.learner for r in collection.runs) == [
        "team_reserve hold_level=0",
        "team_reserve hold_level=1",
    ]
    assert {r.metrics["eval"]["split"] for r in collection.runs} == {"validation"}


def test_a_report_names_the_split_of_every_row(tmp_path):
    """A run written before splits and a validation run: two rows, the setup names both."""
    for split in ("test", "validation"):
        cfg = compose_config(["learner=high_only", *RUN[1:], f"eval.split={split}"])
        save_hydra_files(cfg, tmp_path / split, "high_only", "system1")
        run_train(cfg, run_dir=tmp_path / split)
    old_run(tmp_path / "test", tmp_path / "runs" / "old")
    shutil.copytree(tmp_path / "validation", tmp_path / "runs" / "validation")
    text = build_report([tmp_path / "runs"], tmp_path / "report").report.read_text()
    assert "| `eval.split` | test, validation (differs between runs!) |" in text
    assert "| System-I | high-only eval.split=test |" in text  # the team return table
    assert "| System-I | high-only eval.split=validation |" in text

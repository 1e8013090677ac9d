"""A learner added from outside the package: one module plus one yaml in a user config dir.

The module is ``tests/plugins/toy_learner.py``; the yaml is written here into a temporary config
dir. Nothing else names the learner: it is trained through ``scripts/train.py --config-dir``,
estimated, labelled in a report and listed by ``scripts/bench_learners.py``; its run dir is
evaluated again only by a process that imported the class itself.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from mrta_rl.config import UserError
from mrta_rl.envs import AuctionParams
from mrta_rl.learners.memory import estimate_resources
from mrta_rl.learners.registry import learner_files, learner_named
from mrta_rl.reports import build_report
from mrta_rl.runners import evaluate_checkpoint
from tests.conftest import paper_system

ROOT = Path(__file__).resolve().parents[2]
TOY = {"name": "toy", "label": "Toy bidder", "kind": "tabular"}  # toy_learner.ToyLearner


@pytest.fixture
def config_dir(tmp_path: Path) -> Path:
    """A user config dir holding only ``learner/toy.yaml``."""
    folder = tmp_path / "my_conf"
    (folder / "learner").mkdir(parents=True)
    (folder / "learner" / "toy.yaml").write_text(
        "_target_: tests.plugins.toy_learner.ToyLearner\n_partial_: true\nbid_rate: 0.8\n"
    )
    return folder


def script(name: str, *args: str) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    env["PYTHONPATH"] = str(ROOT)
    return subprocess.run(
        [sys.executable, str(ROOT / "scripts" / name), *args],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )


def test_a_learner_from_a_user_module_and_yaml_is_trained_estimated_labelled_and_listed(
    config_dir, tmp_path
):
    assert "toy" not in learner_files()  # the package's conf does not know it
    run_dir = tmp_path / "run"
    done = script(
        "train.py",
        "--config-dir",
        str(config_dir),
        "learner=toy",
        "system=system1",
        "debug=smoke",
        f"hydra.run.dir={run_dir}",
    )
    assert done.returncode == 0, done.stderr[-3000:]
    metrics = json.loads((run_dir / "metrics.json").read_text())
    assert metrics["learner"] == TOY
    assert metrics["train"]["episodes"] == 2 and metrics["train"]["env_ticks"] == 2 * 50 * 4
    assert metrics["learning_space"] == {"analytic": 6}  # one rate per robot of System-I

    cls = learner_named("toy", [config_dir])
    estimate = estimate_resources(cls, paper_system("system1"), AuctionParams(), batch_size=4)
    assert estimate.parts["bid rates"] == 8 * 6 and estimate.reason is None
    assert estimate.up_front == estimate.parts["env copies"] + 8 * 6

    report = build_report([run_dir], tmp_path / "report").report.read_text()
    assert "| Toy bidder |" in report

    listed = script("bench_learners.py", "--list", "--config-dir", str(config_dir))
    assert listed.returncode == 0, listed.stderr[-3000:]
    assert "toy" in listed.stdout.split()

    # the run dir is data: a process that has not imported the class refuses it, naming the key
    refused = script("evaluate.py", f"checkpoint={run_dir}")
    assert refused.returncode != 0 and "Traceback" not in refused.stderr
    assert "learner._target_: 'tests.plugins.toy_learner.ToyLearner' is not" in refused.stderr
    assert not (run_dir / "eval_metrics.json").exists()
    # the user's code imported it (learner_named above): then it is evaluated, weights and all
    again = evaluate_checkpoint(run_dir)
    assert again["learner"] == TOY and again["eval"] == metrics["eval"]


def test_a_user_learner_extending_a_shipped_one_through_its_defaults_is_listed(tmp_path):
    """``learner/qmix_set.yaml`` with ``defaults: [qmix, _self_]`` is QMIX, as Hydra composes it."""
    folder = tmp_path / "my_conf"
    (folder / "learner").mkdir(parents=True)
    (folder / "learner" / "qmix_set.yaml").write_text(
        "defaults:\n  - qmix\n  - _self_\nnetwork: set\n"
    )
    (folder / "learner" / "orphan.yaml").write_text("defaults:\n  - _self_\nnetwork: set\n")
    assert learner_named("qmix_set", [folder]) is learner_named("qmix")
    with pytest.raises(UserError, match="orphan.yaml: _target_: missing"):
        learner_named("orphan", [folder])

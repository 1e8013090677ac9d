"""The worked examples of docs/extending.md run: each page's code is a file here, trained or played.

The page includes ``tests/plugins/*.py`` and ``tests/plugins/conf/**.yaml`` verbatim; these tests
run them as a user does, with ``scripts/train.py --config-dir tests/plugins/conf``.
"""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from tests.plugins.last_slot import last_slot

ROOT = Path(__file__).resolve().parents[1]
PLUGINS = ROOT / "tests" / "plugins" / "conf"


def train(run_dir: Path, *overrides: str) -> dict:
    """``scripts/train.py --config-dir tests/plugins/conf`` with ``debug=smoke``: metrics.json."""
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    env["PYTHONPATH"] = str(ROOT)
    done = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "train.py"), "--config-dir", str(PLUGINS)]
        + [*overrides, "debug=smoke", f"hydra.run.dir={run_dir}"],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads((run_dir / "metrics.json").read_text())


def test_a_numpy_learner_trains_on_a_team_of_ones_own_with_a_logger_of_ones_own(tmp_path):
    metrics = train(tmp_path, "learner=toy", "system=two_arms", "logger=jsonl")
    assert metrics["learner"] == {"name": "toy", "label": "Toy bidder", "kind": "tabular"}
    assert metrics["system"] == "two_arms"
    assert metrics["learning_space"] == {"analytic": 3}  # one bid rate per robot of the team
    assert set(metrics["eval"]["itr"]) == {"arm_1", "arm_2", "cart"}
    assert set(metrics["eval"]["ctr"]) == {"pick", "place"}
    # smoke: 2 episodes of 50 ticks x 4 copies; the logger got every curve row
    assert metrics["train"]["episodes"] == 2 and metrics["train"]["env_ticks"] == 400
    with (tmp_path / "curve.csv").open() as f:
        rows = [{k: float(v) for k, v in r.items()} for r in csv.DictReader(f)]
    lines = (tmp_path / "curve.jsonl").read_text().splitlines()
    assert [json.loads(line) for line in lines] == rows and len(rows) == 2


def test_a_torch_learner_trains_through_the_torch_loop(tmp_path):
    metrics = train(tmp_path, "learner=toy_pg", "system=system1")
    assert metrics["learner"] == {"name": "toy_pg", "label": "Toy gradient", "kind": "neural"}
    # 2 episodes x 50 ticks x 4 copies, one gradient step per batch of 10 ticks
    assert metrics["train"]["env_ticks"] == 400 and metrics["train"]["gradient_steps"] == 10
    assert (tmp_path / "learner" / "weights.pt").is_file()


def test_a_rule_bids_for_the_last_valid_slot():
    mask = np.array(
        [[1, 1, 0, 1], [1, 0, 0, 0], [1, 1, 1, 0]], bool
    )  # [m=3, K+1=4]: wait always valid
    out = np.full(3, -1, np.int64)
    last_slot(mask, out)
    assert out.tolist() == [3, 0, 2]


def test_a_rule_is_evaluated_as_a_fixed_learner(tmp_path):
    metrics = train(tmp_path, "learner=last_slot", "system=system1")
    assert metrics["learner"] == {"name": "last_slot", "label": "last slot", "kind": "fixed"}
    assert metrics["learning_space"] == {}  # a rule learns nothing
    assert not (tmp_path / "learner").exists() or not any((tmp_path / "learner").iterdir())
    assert len(metrics["eval"]["team_return"]["per_episode"]) == 2  # debug=smoke: 2 episodes

"""What a new user sees: a word while numba compiles, no compile time as training time, one name
for a team file, and no colour codes in redirected output or log files."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
TRAIN = ROOT / "scripts" / "train.py"
ANSI = "\x1b["
COMPILING = re.compile(r"^mrta_rl\.logs: compiling .*\(first run only; cached afterwards\)$", re.M)
TEAM = "robots:             # no name: the file names the team\n  R1: [T1, T2]\n  R2: [T2]\n"
# two small kernels of the env (their first call compiles them on an empty cache)
COMPILE_TWO = """\
import logging
import numpy as np
logging.basicConfig(level=logging.INFO, format="%(name)s: %(message)s")
from mrta_rl.envs import counter_rng
counter_rng.mix64(np.uint64(1))
counter_rng.unit_float(np.uint64(2))
print("done")
"""


def python(code: str, env: dict[str, str]) -> subprocess.CompletedProcess:
    done = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 0 and done.stdout.strip() == "done", done.stderr
    return done


def test_the_log_says_once_that_numba_compiles_and_not_when_it_loads(tmp_path):
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba_cache")}  # empty: cold
    first = python(COMPILE_TWO, env)
    assert len(COMPILING.findall(first.stderr)) == 1, first.stderr  # two kernels, one line
    again = python(COMPILE_TWO, env)  # both loaded from the cache
    assert not COMPILING.findall(again.stderr), again.stderr


def train_redirected(run_dir: Path, cwd: Path, *overrides: str) -> str:
    """``scripts/train.py`` with stdout and stderr redirected to a file, as in a batch job."""
    output = cwd / "output.txt"
    with output.open("w") as handle:
        done = subprocess.run(
            [sys.executable, str(TRAIN), "debug=smoke", f"hydra.run.dir={run_dir}", *overrides],
            cwd=cwd,
            stdout=handle,
            stderr=subprocess.STDOUT,
            timeout=300,
        )
    text = output.read_text()
    assert done.returncode == 0, text
    return text


@pytest.fixture(scope="module")
def team_run(tmp_path_factory) -> tuple[Path, str]:
    """greedy on a team file without a name (``system=./my_team.yaml``): run dir and output."""
    work = tmp_path_factory.mktemp("team")
    (work / "my_team.yaml").write_text(TEAM)
    run_dir = work / "run"
    output = train_redirected(run_dir, work, "learner=greedy", "system=./my_team.yaml")
    return run_dir, output


def test_a_team_file_is_called_by_one_name(team_run):
    run_dir, output = team_run
    log = (run_dir / "train.log").read_text()
    metrics = json.loads((run_dir / "metrics.json").read_text())
    assert metrics["system"] == "my_team"
    assert "learner greedy (GreedyLearner) on my_team, seed 0" in log
    assert "unnamed" not in log + output + (run_dir / ".hydra" / "config.yaml").read_text()


def test_a_fixed_policy_reports_no_training_time(team_run):
    """A fixed policy trains for no time: its training line says 0.0 s, whatever the build or
    compiling took."""
    run_dir, output = team_run
    metrics = json.loads((run_dir / "metrics.json").read_text())
    assert metrics["train"] == {"env_ticks": 0, "wall_s": 0.0, "episodes": 0}
    assert "training: 0 episodes, 0 env ticks, 0.0 s" in output


def test_no_colour_codes_in_redirected_output_or_the_run_log(tmp_path):
    """qmix logs through TorchRL (its replay buffer): the lines reach train.log, plain."""
    run_dir = tmp_path / "run"
    output = train_redirected(run_dir, tmp_path, "learner=qmix", "system=system1")
    log = (run_dir / "train.log").read_text()
    assert ANSI not in output and ANSI not in log
    assert "[torchrl][INFO] - Initialized LazyTensorStorage" in log  # Hydra's format, plain

"""The scripts on bad input: one message, an exit code, no run dir left.

Each case runs the real script in a subprocess, as a user would. A user error prints one
``error: ...`` line naming the culprit on stderr and exits 2; Ctrl-C exits 130 with
``interrupted``; neither prints a traceback nor leaves the run directory Hydra made. A real bug
keeps its traceback, and so does a user error under ``HYDRA_FULL_ERROR=1``.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mrta_rl.learners import GreedyLearner

ROOT = Path(__file__).resolve().parents[2]
MARKER = "MRTA_TEST_MARKER"
HERE = "tests.commands.test_cli"  # this module, as the subprocess imports it


class SleepyLearner(GreedyLearner):
    """Signals that the run got as far as building the learner, then waits (for Ctrl-C)."""

    label = "sleepy"

    def __init__(self, **kwargs) -> None:
        super().__init__(**kwargs)
        Path(os.environ[MARKER]).write_text("building")
        time.sleep(60)


class BuggyLearner(GreedyLearner):
    """A learner with a bug: a real traceback must survive."""

    label = "buggy"

    def act(self, view, mask, *, explore):
        raise ZeroDivisionError("a bug, not a user error")


def script(name: str, *args: str, env: dict | None = None, **kw) -> subprocess.Popen:
    environ = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    environ.update({"PYTHONPATH": str(ROOT), **(env or {})})
    return subprocess.Popen(
        [sys.executable, str(ROOT / "scripts" / name), *args],
        cwd=kw.get("cwd", ROOT),
        env=environ,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def train(run_dir: Path, *overrides: str, env: dict | None = None) -> tuple[int, str, str]:
    proc = script(
        "train.py", "debug=smoke", "system=system1", *overrides, f"hydra.run.dir={run_dir}", env=env
    )
    out, err = proc.communicate(timeout=300)
    return proc.returncode, out, err


def assert_user_error(code: int, err: str, *named: str) -> None:
    assert code == 2, err
    assert "Traceback" not in err and "HYDRA_FULL_ERROR" not in err, err
    assert err.startswith("error: "), err
    for culprit in named:
        assert culprit in err, err


def write_system(tmp_path: Path, text: str) -> str:
    folder = tmp_path / "search" / "system"
    folder.mkdir(parents=True)
    (folder / "mine.yaml").write_text(text)
    return f"hydra.searchpath=[file://{tmp_path / 'search'}]"


@pytest.mark.parametrize(
    ("overrides", "named"),
    [
        (["learner.alpha_power=-2"], ["error: learner.alpha_power: must be a number >= 0, got -2"]),
        (["learner=nope"], ["error: learner=nope: no such option (available: ", "more)"]),
        (["train.episodes=["], ["error: train.episodes=[: no viable alternative at input '['"]),
    ],
)
def test_bad_override_is_one_message_and_no_run_dir(overrides, named, tmp_path):
    run_dir = tmp_path / "run"
    code, _, err = train(run_dir, *overrides)
    assert_user_error(code, err, *named)
    assert err.count("\n") == 1  # one line
    assert not run_dir.exists()


def test_malformed_system_file_is_one_message_and_no_run_dir(tmp_path):
    search = write_system(tmp_path, "name: mine\nrobots:\n  R1: [T1]\n  R2: {T1: 2.0}\n")
    run_dir = tmp_path / "run"
    code, _, err = train(run_dir, "learner=greedy", "system=mine", search)
    assert_user_error(code, err, "system mine", "robot R2: willingness 2.0 for T1")
    assert not run_dir.exists()


def test_yaml_syntax_error_names_the_file_and_line(tmp_path):
    search = write_system(tmp_path, "name: mine\nrobots:\n  R1: [T1\n  R2: [T1]\n")
    run_dir = tmp_path / "run"
    code, _, err = train(run_dir, "learner=greedy", "system=mine", search)
    assert_user_error(code, err, "YAML syntax error", "mine.yaml", "line 3")
    assert not run_dir.exists()


def test_bad_checkpoint_path_is_one_message(tmp_path):
    proc = script("evaluate.py", f"checkpoint={tmp_path / 'nowhere'}")
    _, err = proc.communicate(timeout=300)
    assert_user_error(proc.returncode, err, f"{tmp_path / 'nowhere'} is not a run dir")


def test_default_run_dirs_are_removed_up_to_the_working_dir(tmp_path):
    proc = script("train.py", "debug=smoke", "env.horizon=abc", cwd=tmp_path)
    _, err = proc.communicate(timeout=300)
    assert_user_error(proc.returncode, err, "env.horizon: must be an integer >= 1, got 'abc'")
    assert list(tmp_path.iterdir()) == []  # no outputs/<date>/<time>, no empty outputs/


def test_ctrl_c_before_training_exits_130_and_leaves_nothing(tmp_path):
    run_dir, marker = tmp_path / "run", tmp_path / "marker"
    proc = script(
        "train.py",
        "debug=smoke",
        "learner=greedy",
        f"learner._target_={HERE}.SleepyLearner",
        f"hydra.run.dir={run_dir}",
        env={MARKER: str(marker)},
    )
    deadline = time.monotonic() + 240
    while not marker.exists() and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.1)
    assert marker.exists(), proc.communicate()[1]
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    assert err.strip().splitlines()[-1] == "interrupted" and "Traceback" not in err, err
    assert not run_dir.exists()


def test_a_previous_runs_data_is_never_removed(tmp_path):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "notes.txt").write_text("{}")  # a finished run's dir is refused up front
    code, _, err = train(run_dir, "learner.alpha=2")
    assert_user_error(code, err, "learner.alpha: must be a number in (0, 1], got 2")
    assert (run_dir / "notes.txt").read_text() == "{}"


def test_bugs_and_full_error_keep_the_traceback(tmp_path):
    bug = f"learner._target_={HERE}.BuggyLearner"
    code, _, err = train(tmp_path / "bug", "learner=greedy", bug)
    assert code == 1 and "Traceback" in err and "ZeroDivisionError: a bug" in err
    code, _, err = train(tmp_path / "full", "learner.alpha=2", env={"HYDRA_FULL_ERROR": "1"})
    assert code != 0 and "Traceback" in err and "learner.alpha: must be" in err


# ------------------------------------------------------------------ fuzz through the script
@settings(max_examples=5, deadline=None, derandomize=True)
@given(
    key=st.sampled_from(
        ["learner.reserve", "learner.hold_level", "env.p_high", "env.slots", "seed", "+eval.x"]
    ),
    value=st.sampled_from(["-1", "0", "2", "0.5", "abc", "null", "[1,2]", "true", "{a: 1}"]),
)
def test_fuzz_overrides_through_the_script(key, value, tmp_path_factory):
    """The config fuzz through the real script: accepted and run, or one message naming the key."""
    run_dir = tmp_path_factory.mktemp("fuzz") / "run"
    code, out, err = train(run_dir, "learner=subg_reserve", f"{key}={value}")
    if code == 0:
        assert "CTR %" in out and (run_dir / "metrics.json").is_file()
    else:
        assert_user_error(code, err, key.lstrip("+"))
        assert not run_dir.exists()

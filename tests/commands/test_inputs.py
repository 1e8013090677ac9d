"""Bad inputs refused up front by the scripts: one ``error:`` line naming the file, exit 2.

Oversized teams and hostile system files are refused before Hydra composes them or anything is
built, and leave no run dir (``mrta_rl/config_guard.py``, ``runners/validation.py``).
"""

from __future__ import annotations

import json
import os
import re
import shutil
from pathlib import Path

import pytest
from hydra.core.hydra_config import HydraConfig

from mrta_rl.config import UserError
from mrta_rl.reports import build_report
from mrta_rl.runners import train as run_train
from mrta_rl.runners.validation import check_evaluate_config
from tests.commands.test_cli import assert_user_error, script, train, write_system
from tests.conftest import compose_config
from tests.runners.test_checkpoint import save_hydra_files


def billion_laughs() -> str:
    lines = ['  a: &a ["lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol"]']
    for previous, name in zip("abcdefgh", "bcdefghi", strict=True):
        lines.append(f"  {name}: &{name} [" + ", ".join([f"*{previous}"] * 9) + "]")
    return "name: mine\nrobots: {R1: [T1]}\nlaughs:\n" + "\n".join(lines) + "\n"


def many_robots(size: int) -> str:
    rows = [f"  R{i}: [T1, T2, T3]" for i in range(size // 16)]  # >= 17 bytes a row
    return "name: mine\nrobots:\n" + "\n".join(rows) + "\n"


SYSTEM_FILES = {
    "billion_laughs": (billion_laughs(), "YAML aliases"),
    "nested_lists": ("name: mine\nrobots: " + "[" * 5000 + "]" * 5000 + "\n", "nested deeper"),
    "binary": (None, "not UTF-8"),
    "two_megabytes": (many_robots(2_000_000), "more than the limit of 1,048,576 bytes"),
}


@pytest.mark.parametrize("case", sorted(SYSTEM_FILES))
def test_hostile_system_file_is_refused_before_it_is_read(case, tmp_path):
    text, reason = SYSTEM_FILES[case]
    search = write_system(tmp_path, "")
    path = tmp_path / "search" / "system" / "mine.yaml"
    if text is None:
        path.write_bytes(b"\xc0\xff" + os.urandom(998))
    else:
        path.write_text(text)
    run_dir = tmp_path / "run"
    code, _, err = train(run_dir, "learner=greedy", "system=mine", search)
    assert_user_error(code, err, str(path), reason)
    assert err.count("\n") == 1
    assert not run_dir.exists()


@pytest.mark.parametrize("n_robots", [10_000_000, 100_000_000])
def test_huge_random_team_is_refused_before_it_is_drawn(n_robots, tmp_path):
    run_dir = tmp_path / "run"
    code, _, err = train(run_dir, "system=random", f"system.n_robots={n_robots}")
    assert_user_error(code, err, "system random", f"{n_robots:,} robots x 20 task types", "limit")
    assert not run_dir.exists()


def test_team_of_a_thousand_robots_is_not_refused(tmp_path):
    run_dir = tmp_path / "run"
    code, out, err = train(
        run_dir, "learner=greedy", "system=random", "system.n_robots=1000", "eval.episodes=1"
    )
    assert code == 0, err
    assert (run_dir / "metrics.json").is_file()


# ---------------------------------------------------------------------------------- arguments
@pytest.mark.parametrize(
    ("overrides", "named"),
    [
        ([], "checkpoint: missing"),
        (["checkpoint=x", "episodes=abc"], "episodes: must be an integer >= 1 or null, got 'abc'"),
        (["checkpoint=x", "episodes=1e400"], "episodes: must be an integer >= 1 or null, got inf"),
        (["checkpoint=x", "episodes=1.7"], "episodes: must be an integer >= 1 or null, got 1.7"),
        (["checkpoint=x", "episodes=true"], "episodes: must be an integer >= 1 or null, got True"),
        (["checkpoint=x", "batch_size=0"], "batch_size: must be an integer >= 1 or null, got 0"),
    ],
)
def test_evaluate_arguments_are_checked_like_train_settings(overrides, named, compose_cfg):
    cfg = compose_cfg(overrides, config_name="evaluate")
    with pytest.raises(UserError, match=re.escape(named)):
        check_evaluate_config(cfg)


def test_evaluate_without_checkpoint_is_one_message():
    proc = script("evaluate.py")
    _, err = proc.communicate(timeout=300)
    assert_user_error(proc.returncode, err, "checkpoint: missing")


def test_undeclared_key_is_refused_naming_it(tmp_path):
    run_dir = tmp_path / "run"
    code, _, err = train(run_dir, "learner=greedy", "+foo=1")
    assert_user_error(code, err, "foo: unknown setting")
    assert not run_dir.exists()


# ---------------------------------------------------------------------------------- report.py
@pytest.fixture(scope="module")
def finished_run(tmp_path_factory) -> Path:
    run_dir = tmp_path_factory.mktemp("finished") / "run"
    cfg = compose_config(["learner=greedy", "system=system1", "debug=smoke", "eval.episodes=1"])
    save_hydra_files(cfg, run_dir, "greedy", "system1")
    run_train(cfg, run_dir=run_dir)
    HydraConfig.instance().cfg = None  # the next test composes its own config
    return run_dir


def copy_run(source: Path, target: Path) -> Path:
    shutil.copytree(source, target)
    return target


def test_report_on_an_empty_dir_is_one_message(tmp_path):
    proc = script("report.py", str(tmp_path))
    _, err = proc.communicate(timeout=300)
    assert_user_error(proc.returncode, err, "no finished run", str(tmp_path))
    assert list(tmp_path.iterdir()) == []


def test_report_names_a_truncated_metrics_json(finished_run, tmp_path):
    run_dir = copy_run(finished_run, tmp_path / "runs" / "a")
    path = run_dir / "metrics.json"
    path.write_text(path.read_text()[:100])
    with pytest.raises(UserError, match=re.escape(f"{path}: not valid JSON")):
        build_report([tmp_path / "runs"])
    assert not (tmp_path / "runs" / "report").exists()


def test_report_of_a_system_in_a_config_subfolder_is_whole(finished_run, tmp_path):
    run_dir = copy_run(finished_run, tmp_path / "runs" / "a")
    metrics = json.loads((run_dir / "metrics.json").read_text())
    (run_dir / "metrics.json").write_text(json.dumps({**metrics, "system": "sub/nested"}))
    files = build_report([tmp_path / "runs"])
    assert files.report.is_file()
    assert all(p.parent == files.out_dir and p.is_file() for p in files.figures.values())


def test_report_names_the_duplicate_it_leaves_out(finished_run, tmp_path):
    first = copy_run(finished_run, tmp_path / "runs" / "a")
    again = copy_run(finished_run, tmp_path / "runs" / "b")
    longer = copy_run(finished_run, tmp_path / "runs" / "c")
    config = longer / ".hydra" / "config.yaml"
    config.write_text(
        config.read_text().replace("train:\n  episodes: 2\n", "train:\n  episodes: 1500\n")
    )
    files = build_report([tmp_path / "runs"])
    report = files.report.read_text()
    assert "## Duplicate runs left out" in report
    assert f"`{again}` | `{first}`" in report  # left out, kept
    assert len(files.collection.runs) == 2  # the 1,500-episode run is a configuration of its own
    assert f"`{longer}`" not in report.split("## Duplicate runs left out")[1].split("##")[0]


# ---------------------------------------------------------------------------------- sweeps
def test_sweep_names_every_failed_job_and_the_report_calls_them_refused(tmp_path):
    sweep_dir = tmp_path / "sweep"
    proc = script(
        "train.py",
        "-m",
        "debug=smoke",
        "learner=greedy",
        "system=system1",
        "eval.episodes=0,-1,1",
        f"hydra.sweep.dir={sweep_dir}",
    )
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 2, err
    assert "error: 2 jobs of the sweep failed" in err
    assert "eval.episodes: must be an integer >= 1, got 0" in err
    assert "eval.episodes: must be an integer >= 1, got -1" in err
    assert "Traceback" not in err
    files = build_report([sweep_dir])
    reasons = sorted(m.reason for m in files.collection.missing)
    assert reasons == [
        "refused: eval.episodes: must be an integer >= 1, got -1",
        "refused: eval.episodes: must be an integer >= 1, got 0",
    ]
    assert "refused: eval.episodes: must be an integer >= 1, got 0" in files.report.read_text()

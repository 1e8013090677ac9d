"""Every command checks its arguments before any work: one ``error:`` line naming it, exit 2.

The commands run as a user runs them (``scripts/*.py`` in a subprocess). A bad number, an
output path that could not be written, a team training would refuse, or a key or option Hydra
does not know is refused before any benchmark, partition, evaluation or report is made, and
nothing is written. Each refusal comes within seconds: the cases whose work would take minutes
(or forever) are bounded by a timeout.
"""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

from tests.commands.test_cli import assert_user_error, script, train
from tests.commands.test_inputs import copy_run, finished_run  # noqa: F401 (a fixture)

FAST = 60  # seconds: a refusal takes one or two, the work it prevents minutes or forever


def run(name: str, *args: str, cwd: Path | None = None) -> tuple[int | None, str, str]:
    """``(exit code, stdout, stderr)`` of a script; the code is None if it outlived :data:`FAST`."""
    proc = script(name, *args, **({"cwd": cwd} if cwd else {}))
    try:
        out, err = proc.communicate(timeout=FAST)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
        return None, out, err
    return proc.returncode, out, err


def assert_one_line(code: int | None, err: str, *named: str) -> None:
    """Exit 2, and stderr is exactly one ``error: ...`` line naming each of ``named``."""
    assert code is not None, f"still running after {FAST} s: {err[-500:]}"
    assert_user_error(code, err, *named)
    assert err.count("\n") == 1, err


# ---------------------------------------------------------------------------------- mrta-bench
# a tiny benchmark: what the original code ran before failing or ignoring the bad value
BENCH = {
    "--systems": ["system1"],
    "--paths": ["step"],
    "--batch-sizes": ["1"],
    "--threads": ["1"],
    "--repeats": ["1"],
    "--seconds": ["0.01"],
}


def bench(tmp_path: Path, **bad: list[str]) -> tuple[int | None, str, str, Path]:
    args = {**BENCH, **{f"--{k.replace('_', '-')}": v for k, v in bad.items()}}
    out = Path(args.pop("--out", [str(tmp_path / "bench.json")])[0])
    flat = [part for key, values in args.items() for part in (key, *values)]
    return (*run("bench_env.py", *flat, "--out", str(out), cwd=tmp_path), out)


@pytest.mark.parametrize(
    ("option", "values", "named"),
    [
        ("--batch-sizes", ["0"], "--batch-sizes: must be a list, each item an integer >= 1, got"),
        ("--batch-sizes", ["4", "-5"], "--batch-sizes: must be a list, each item an integer >= 1"),
        ("--seconds", ["nan"], "--seconds: must be a number > 0, got nan"),
        ("--seconds", ["-1"], "--seconds: must be a number > 0, got -1.0"),
        ("--seconds", ["inf"], "--seconds: must be a number > 0, got inf"),
        ("--repeats", ["0"], "--repeats: must be an integer >= 1, got 0"),
        ("--threads", ["0"], "--threads: must be a list, each item an integer >= 1, got [0]"),
        ("--repeats", ["x"], "argument --repeats: invalid int value: 'x'"),
    ],
)
def test_bench_refuses_a_bad_number_before_any_work(option, values, named, tmp_path):
    code, out, err, written = bench(tmp_path, **{option[2:].replace("-", "_"): values})
    assert_one_line(code, err, named)
    assert out == "" and not written.exists()  # no table: nothing was measured


def test_bench_refuses_an_output_in_a_missing_folder_before_any_work(tmp_path):
    target = tmp_path / "missing" / "bench.json"
    code, out, err, _ = bench(tmp_path, out=[str(target)])
    assert_one_line(code, err, f"--out: {target}: the folder {target.parent} does not exist")
    assert out == "" and not target.parent.exists()


def test_bench_refuses_an_output_onto_a_folder_before_any_work(tmp_path):
    folder = tmp_path / "results"
    folder.mkdir()
    code, out, err, _ = bench(tmp_path, out=[str(folder)])
    assert_one_line(code, err, f"--out: {folder} is a folder; name a file")
    assert out == "" and list(folder.iterdir()) == []


@pytest.mark.parametrize(
    ("option", "value", "named"),
    [
        ("--repeats", "0", "--repeats: must be an integer >= 1, got 0"),
        ("--seconds", "nan", "--seconds: must be a number > 0, got nan"),
        ("--episodes", "0", "--episodes: must be an integer >= 1, got 0"),
        ("--horizon", "-1", "--horizon: must be an integer >= 0, got -1"),
    ],
)
def test_learner_bench_refuses_a_bad_number_before_any_work(option, value, named, tmp_path):
    out = tmp_path / "bench.json"
    args = ["--learners", "dql", "--episodes", "1", "--repeats", "1", "--seconds", "0.01"]
    code, _, err = run("bench_learners.py", *args, option, value, "--out", str(out))
    assert_one_line(code, err, named)
    assert not out.exists()


# ---------------------------------------------------------------------------------- partition
def test_partition_refuses_a_team_training_refuses_before_partitioning_it():
    code, out, err = run("partition.py", "system=random", "system.n_robots=100000")
    assert_one_line(code, err, "system random, 100,000 robots", "exceeds the environment's limit")
    assert out == ""


def test_partition_refuses_a_team_file_training_refuses_before_hydra_reads_it(tmp_path):
    team = tmp_path / "big.yaml"  # 7,000 robots: partitioning them takes minutes
    rows = "".join(f"  R{i}: [T{i % 20 + 1}]\n" for i in range(1, 7001))
    team.write_text(f"name: big\nrobots:\n{rows}")
    code, out, err = run("partition.py", f"system={team}")
    assert_one_line(code, err, f"{team}: env:", "system big, 7,000 robots")
    assert out == ""


def test_partition_refuses_an_empty_sub_group_bound_as_training_does(tmp_path):
    code, out, err = run("partition.py", "system=system1", "partition.max_group_size=0")
    assert_one_line(code, err, "partition.max_group_size: must be an integer >= 1 or null, got 0")
    code, _, train_err = train(tmp_path / "run", "learner=subg_cql", "partition.max_group_size=0")
    assert_one_line(code, train_err, "partition.max_group_size: must be an integer >= 1")


def test_partition_of_a_shipped_system_is_printed():
    code, out, err = run("partition.py", "system=system1", "format=json")
    assert code == 0, err
    assert '"name": "G1"' in out


# ---------------------------------------------------------------------------------- report
def test_report_refuses_a_file_in_the_way_of_its_output_before_reading_the_runs(
    finished_run,  # noqa: F811 (the fixture)
    tmp_path,
):
    blocker = tmp_path / "passwd"
    blocker.write_text("not a folder\n")
    code, out, err = run("report.py", str(finished_run), "--out", str(blocker / "x"))
    assert_one_line(code, err, f"--out: {blocker / 'x'}: {blocker} is a file, not a folder")
    assert out == "" and blocker.read_text() == "not a folder\n"
    assert not (finished_run / "report").exists()


def test_report_checks_its_output_before_it_reads_the_runs(tmp_path):
    (tmp_path / "runs").mkdir()  # no run: reading them would refuse the report
    blocker = tmp_path / "file"
    blocker.write_text("")
    code, _, err = run("report.py", str(tmp_path / "runs"), "--out", str(blocker / "report"))
    assert_one_line(code, err, "--out:", "is a file, not a folder")


# ---------------------------------------------------------------------------------- evaluate
def test_evaluate_blames_a_bad_batch_size_on_the_command_line(
    finished_run,  # noqa: F811 (the fixture)
    tmp_path,
):
    run_dir = copy_run(finished_run, tmp_path / "run")
    code, out, err = run("evaluate.py", f"checkpoint={run_dir}", "batch_size=100000000")
    assert_one_line(code, err, "error: batch_size: must be <= 1000000 (the seeds of one split)")
    assert "config.yaml" not in err and out == ""
    assert not (run_dir / "eval_metrics.json").exists()


def test_evaluate_names_an_unknown_key_in_one_line(finished_run):  # noqa: F811 (the fixture)
    code, _, err = run("evaluate.py", f"checkpoint={finished_run}", "eval.batch_size=3")
    assert_one_line(code, err, "error: eval.batch_size: unknown key (known: split)")


def test_evaluate_with_its_arguments_is_not_refused(finished_run, tmp_path):  # noqa: F811
    run_dir = copy_run(finished_run, tmp_path / "run")
    code, out, err = run("evaluate.py", f"checkpoint={run_dir}", "episodes=3", "batch_size=2")
    assert code == 0, err
    assert "3 evaluation episodes" in out and (run_dir / "eval_metrics.json").is_file()


# ---------------------------------------------------------------------------------- Hydra
@pytest.mark.parametrize(
    ("override", "named"),
    [
        ("train.workers=2", "error: train.workers: unknown key (known: episodes, batch_size"),
        ("learner.nope=3", "error: learner.nope: unknown key (known: alpha"),
        ("learner=nope", "error: learner=nope: no such option (available: cql, dql"),
        ("hydra/launcher=nope", "error: hydra/launcher=nope: no such option (available: basic"),
    ],
)
def test_hydras_errors_are_one_line_naming_the_key_or_option(override, named, tmp_path):
    run_dir = tmp_path / "run"
    code, _, err = train(run_dir, "learner=subg_cql", override)
    assert_one_line(code, err, named)
    assert "full_key" not in err and "object_type" not in err and "search path" not in err
    assert not run_dir.exists()


def test_a_long_list_of_options_is_cut_with_a_count(tmp_path):
    code, _, err = train(tmp_path / "run", "learner=nope")
    assert_one_line(code, err, "more)")
    options = err.split("available: ")[1].rstrip(")\n")
    shown, more = options.split(" and ")
    assert len(shown.split(", ")) == 5
    learners = len(list((Path(__file__).parents[2] / "conf" / "learner").glob("*.yaml")))
    assert more == f"{learners - 5} more"

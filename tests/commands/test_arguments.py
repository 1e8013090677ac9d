"""Every command checks its arguments before any work: one ``error:`` line naming it, exit 2.

The commands run as a user runs them (``scripts/*.py`` in a subprocess). A bad number, an
output path that could not be written, a team training would refuse, or a key or option Hydra
does not know is refused before any benchmark, partition, evaluation or report is made, and
nothing is written. Each refusal comes within seconds: the cases whose work would take minutes
(or forever) are bounded by a timeout.
"""

from __future__ import annotations

import contextlib
import importlib.util
import io
import logging
import logging.config
import math
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from hydra.core.global_hydra import GlobalHydra
from hydra.core.hydra_config import HydraConfig
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.errors import HydraException
from hypothesis import example, given, settings
from hypothesis import strategies as st

from mrta_rl.commands import bench as bench_command
from mrta_rl.commands import evaluate as evaluate_command
from mrta_rl.commands import partition as partition_command
from mrta_rl.commands import report as report_command
from mrta_rl.errors import MAX_LINE
from mrta_rl.runners import cli
from mrta_rl.splits import SPLIT_WIDTH
from mrta_rl.systems import MAX_PAIRS
from tests.commands.test_cli import ROOT, assert_user_error, script, train
from tests.commands.test_inputs import copy_run, finished_run  # noqa: F401 (a fixture)
from tests.test_run_layout import digest

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
        ("train.nope=2", "error: train.nope: unknown key (known: episodes, batch_size"),
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


# ---------------------------------------------------------------------------------- the fuzz
# The commands' main() in this process (a subprocess per case would take seconds), their work
# replaced by a function that stops them: each drawn argument is either accepted (the command
# got to its work) or refused in one ``error:`` line, exit 2, before any work, with nothing
# written. Which is right is decided here from what the user typed: the option's declared range
# read through Python's int() and float() (argparse's types) or Hydra's override parser.
class Accepted(Exception):  # noqa: N818 - not an error: the command got to its work
    """Raised where a command's work starts: its arguments were accepted."""


def stop_work(*args, **kwargs):
    raise Accepted


def in_process(main, argv: list[str], work: tuple) -> tuple[int | None, str, str]:
    """``(exit code, stdout, stderr)`` of ``main()`` run here with ``sys.argv = argv``; the code
    is None if the command got to its work (``work``: the module and name of its function)."""
    out, err = io.StringIO(), io.StringIO()
    loggers = logging.root.manager.loggerDict
    disabled = {name for name, lg in loggers.items() if getattr(lg, "disabled", False)}
    with (
        pytest.MonkeyPatch.context() as patch,
        contextlib.redirect_stdout(out),
        contextlib.redirect_stderr(err),
    ):
        patch.setattr(sys, "argv", argv)
        patch.setenv("HYDRA_FULL_ERROR", "0")  # cli.run sets it to 1 for Hydra: undone after
        patch.setattr(logging.FileHandler, "handleError", logging.FileHandler.handleError)
        patch.setattr(*work, stop_work)
        try:
            main()
        except SystemExit as exit_:
            return exit_.code, out.getvalue(), err.getvalue()
        except Accepted:
            return None, out.getvalue(), err.getvalue()
        finally:
            GlobalHydra.instance().clear()
            HydraConfig.instance().cfg = None
            for name, lg in list(loggers.items()):  # Hydra's job logging (disabled) silences
                if isinstance(lg, logging.Logger) and name not in disabled:  # every logger
                    lg.disabled = False
    raise AssertionError(f"{argv}: ended without an error and without its work")


def assert_refused_in_one_line(code: int | None, out: str, err: str, argument: str) -> None:
    """Exit 2, one short ``error:`` line naming the argument (its block at least: ``system``),
    and no output."""
    assert code == 2, f"exit {code}: {err[-500:]}"
    assert err.startswith("error: ") and err.count("\n") == 1, err
    assert argument.split(".")[0] in err, f"{err!r} does not name {argument}"
    assert len(err) <= len("error: \n") + MAX_LINE, f"{len(err)} characters: {err}"
    assert out == "", "output before the refusal"


ARGUMENT_TEXT = st.one_of(
    st.integers(-3, 3).map(str),
    st.integers().map(str),
    st.floats().map(repr),  # nan, inf, -0.0, 1e+300, 5e-324
    st.sampled_from(
        ["", " ", " 3", "+5", "-0", "0x10", "0b1", "1_000", "1e400", "-1e400", "1e3", "3.", ".5"]
    ),
    st.sampled_from(["١٢", "true", "null", "None", "[1]", "[1, 2]", "{a: 1}", "'3'", "1,2"]),
    st.sampled_from(["${x}", "${oc.env:NOPE}", "abc", "~", "-", "--", "-x", "test", "validation"]),
    st.text(st.characters(exclude_characters="\x00", exclude_categories=("Cs",)), max_size=6),
    st.integers(300, 6000).map(lambda n: "9" * n),  # past Python's 4,300 digits too
    st.integers(100, 3000).map(lambda n: "[" * n + "]" * n),  # past the recursion limit too
)
FUZZ_ARGUMENTS = settings(max_examples=40, deadline=None, derandomize=True)


def parsed(value: str, kind: type) -> float | None:
    """``kind(value)`` (argparse's conversion of the option's type), None if it fails."""
    if value.startswith("-") and value != "-" and " " not in value:
        if not re.fullmatch(r"-\d+|-\d*\.\d+", value):
            return None  # argparse reads it as another option: the option lacks its value
    try:
        return kind(value)
    except (ValueError, OverflowError):
        return None


def accepts(number: float | None, low: float, low_open: bool = False) -> bool:
    """Whether a number is in its declared range: finite, and an integer within 64 bits."""
    if number is None or (isinstance(number, float) and not math.isfinite(number)):
        return False
    if isinstance(number, int) and number >= 2**63:
        return False
    return number > low if low_open else number >= low


# options of mrta-bench and scripts/bench_learners.py: (type, least value, least excluded)
BENCH_OPTIONS = {
    "--batch-sizes": (int, 1, False),
    "--threads": (int, 1, False),
    "--repeats": (int, 1, False),
    "--seconds": (float, 0, True),
}
LEARNER_BENCH_OPTIONS = {
    "--episodes": (int, 1, False),
    "--horizon": (int, 0, False),
    "--repeats": (int, 1, False),
    "--seconds": (float, 0, True),
}


@FUZZ_ARGUMENTS
@given(option=st.sampled_from(sorted(BENCH_OPTIONS)), value=ARGUMENT_TEXT)
@example(option="--repeats", value="x" * 400)  # argparse quoted it whole: 470 characters
def test_fuzz_bench_numbers_are_accepted_in_range_or_refused_before_any_work(
    option, value, tmp_path_factory
):
    out = tmp_path_factory.mktemp("bench") / "bench.json"
    args = {**BENCH, option: [value], "--out": [str(out)]}
    argv = ["mrta-bench", *(part for key, values in args.items() for part in (key, *values))]
    code, printed, err = in_process(bench_command.main, argv, (bench_command, "_system"))
    kind, low, low_open = BENCH_OPTIONS[option]
    if accepts(parsed(value, kind), low, low_open):
        assert code is None, f"{option} {value!r} refused: {err}"
    else:
        assert_refused_in_one_line(code, printed, err, option)
    assert not out.exists()


@FUZZ_ARGUMENTS
@given(option=st.sampled_from(sorted(LEARNER_BENCH_OPTIONS)), value=ARGUMENT_TEXT)
@example(option="--repeats", value="9" * 300)  # accepted; OverflowError in tqdm(range(...))
def test_fuzz_learner_bench_numbers_are_accepted_in_range_or_refused_before_any_work(
    option, value, tmp_path_factory, learner_bench
):
    out = tmp_path_factory.mktemp("bench") / "bench.json"
    argv = ["bench_learners.py", "--learners", "dql", option, value, "--out", str(out)]
    code, printed, err = in_process(
        lambda: cli.run(learner_bench.main), argv, (learner_bench, "run_worker")
    )
    kind, low, low_open = LEARNER_BENCH_OPTIONS[option]
    if accepts(parsed(value, kind), low, low_open):
        assert code is None, f"{option} {value!r} refused: {err}"
    else:
        assert_refused_in_one_line(code, printed, err, option)
    assert not out.exists()


@pytest.fixture(scope="module")
def learner_bench():
    """``scripts/bench_learners.py`` as a module."""
    spec = importlib.util.spec_from_file_location(
        "bench_learners", ROOT / "scripts" / "bench_learners.py"
    )
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclass looks its module up
    spec.loader.exec_module(module)
    yield module
    del sys.modules[spec.name]


UNREADABLE = object()  # what Hydra's parser refuses


def hydra_value(override: str):
    """The value Hydra reads from ``key=value`` on the command line (:data:`UNREADABLE`)."""
    try:
        return OverridesParser.create().parse_override(override).value()
    except (HydraException, ValueError, RecursionError):
        return UNREADABLE


def is_int(value, low: int, high: float = 2**63 - 1) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and low <= value <= high


@settings(FUZZ_ARGUMENTS, max_examples=20)  # a Hydra job each: 0.1 to 0.3 s
@given(
    key=st.sampled_from(["partition.max_group_size", "system.n_robots", "system.n_task_types"]),
    value=ARGUMENT_TEXT,
)
@example(key="system.n_robots", value="${x}")  # InterpolationKeyError
@example(key="partition.max_group_size", value="9" * 4400)  # ValueError: 4,300 digits
@example(key="partition.max_group_size", value="[" * 400 + "]" * 400)  # RecursionError
def test_fuzz_partition_arguments_are_accepted_or_refused_before_partitioning(key, value):
    system = "system=system1" if key.startswith("partition") else "system=random"
    override = f"{key}={value}"
    code, printed, err = in_process(
        partition_command.main,
        ["mrta-partition", system, override],
        (partition_command, "subg_partition"),
    )
    read = hydra_value(override)
    if key.startswith("partition"):
        expected = read is None or is_int(read, 1)
    else:  # a team of up to 2,000 robots of 20 task types is partitioned in seconds
        if is_int(read, 1, 2_000):
            expected = True
        elif is_int(read, 1) and read * 20 <= MAX_PAIRS:
            expected = code is None  # the env's limits decide
        else:
            expected = False
    if expected:
        assert code is None, f"{override!r} refused: {err}"
    else:
        assert_refused_in_one_line(code, printed, err, key)


@settings(FUZZ_ARGUMENTS, max_examples=20)  # a Hydra job each: 0.1 to 0.3 s
@given(key=st.sampled_from(["episodes", "batch_size", "eval.split"]), value=ARGUMENT_TEXT)
@example(key="episodes", value="[" * 1500 + "]" * 1500)  # RecursionError in Hydra's parser
@example(key="batch_size", value="a" * 400)  # a line of 460 characters
def test_fuzz_evaluate_arguments_are_accepted_or_refused_before_evaluating(
    key,
    value,
    finished_run,  # noqa: F811 (the fixture)
    tmp_path_factory,
):
    run_dir = copy_run(finished_run, tmp_path_factory.mktemp("evaluate") / "run")
    before = digest(run_dir)
    override = f"{key}={value}"
    code, printed, err = in_process(
        evaluate_command.main,
        ["mrta-evaluate", f"checkpoint={run_dir}", override],
        (sys.modules["mrta_rl.runners.train"], "evaluate_run"),
    )
    read = hydra_value(override)
    if key == "eval.split":
        expected = read in (None, "test", "validation")
    else:  # a batch of evaluation copies plays the seeds of one split at most
        expected = read is None or is_int(
            read, 1, SPLIT_WIDTH if key == "batch_size" else 2**63 - 1
        )
    if expected:
        assert code is None, f"{override!r} refused: {err}"
    else:
        assert_refused_in_one_line(code, printed, err, key)
    assert digest(run_dir) == before


# where --out may point, in a folder of: a folder, a file, links (to them, to nothing, in a loop)
# and a FIFO; "long" is a name longer than the system takes
OUT_PLACES = [
    "new",
    "new/a/b",
    "folder",
    "folder/new",
    "file",
    "file/x",
    "fifo",
    "link_to_folder",
    "link_to_folder/x",
    "link_to_file",
    "link_to_new_file",
    "link_to_nothing",
    "link_to_nothing/x",
    "loop",
    "long",
    "long/x",
    "",
]


def out_place(root: Path, name: str) -> str:
    """The --out of ``name`` in a fresh ``root``, made to hold what :data:`OUT_PLACES` names."""
    (root / "folder").mkdir()
    (root / "file").write_text("kept\n")
    os.mkfifo(root / "fifo")
    for link, target in {
        "link_to_folder": root / "folder",
        "link_to_file": root / "file",
        "link_to_new_file": root / "folder" / "new.json",
        "link_to_nothing": root / "missing" / "x",
        "loop": root / "loop",
    }.items():
        (root / link).symlink_to(target)
    return str(root / name.replace("long", "a" * 300)) if name else ""


def writes(out: str, folder: bool) -> bool:
    """Whether the command's write would succeed: a file written through ``out`` (a FIFO without
    a reader is not waited for), or the folder made and a file written in it."""
    if not out:
        return False  # no place: the working directory is no one's output
    try:
        path = Path(out) / "report.md" if folder else Path(out)
        if folder:
            Path(out).mkdir(parents=True, exist_ok=True)
        flags = os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_NONBLOCK
        os.close(os.open(path, flags))
    except OSError:
        return False
    return True


@pytest.mark.parametrize("name", OUT_PLACES)
@pytest.mark.parametrize("command", ["mrta-bench", "mrta-report"])
def test_out_is_accepted_where_it_can_be_written_or_refused_before_any_work(
    command, name, tmp_path
):
    """Every kind of place --out names, exhaustively: before the fixes, a name too long was a
    traceback, and a link to nothing, a loop of links and an empty --out of mrta-report were
    accepted (the write failed after the work, or went to the working directory)."""
    root = tmp_path
    out = out_place(root, name)
    before = digest(root)
    if command == "mrta-bench":
        argv = ["mrta-bench", *(p for k, v in BENCH.items() for p in (k, *v)), "--out", out]
        code, printed, err = in_process(bench_command.main, argv, (bench_command, "_system"))
    else:
        argv = ["mrta-report", str(root / "folder"), "--out", out]
        code, printed, err = in_process(report_command.main, argv, (report_command, "build_report"))
    assert digest(root) == before, "the check wrote something"
    if code is not None:
        assert_refused_in_one_line(code, printed, err, "--out")
    assert (code is None) == writes(out, folder=command == "mrta-report"), err


@pytest.mark.parametrize(
    ("value", "named"),
    [
        ("9" * 4400, "Exceeds the limit (4300 digits) for integer string conversion"),
        ("[" * 400 + "]" * 400, "nested too deeply"),
    ],
)
def test_an_override_past_python_s_limits_is_one_line_from_the_script(value, named):
    """What the fuzz found, as a user meets it: a traceback before, one short line now."""
    code, out, err = run("partition.py", "system=system1", f"partition.max_group_size={value}")
    assert_one_line(code, err, "error: partition.max_group_size=", named)
    assert len(err) <= len("error: \n") + MAX_LINE and out == ""

"""The report stays true to what it is given: run dirs that are not one sweep expect no other runs,
a run whose files cannot be read is named and left out, and every table counts a seed once."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from mrta_rl.reports import build_report, collect_runs, figures
from mrta_rl.reports.collect import BASIC_SWEEPER
from tests.reports.test_collect import write_run

ROOT = Path(__file__).resolve().parents[2]
TRAIN, REPORT = ROOT / "scripts" / "train.py", ROOT / "scripts" / "report.py"


def train_run(run_dir: Path, *overrides: str) -> Path:
    """One ``scripts/train.py`` call of its own (debug=smoke), in ``run_dir``."""
    done = subprocess.run(
        [sys.executable, str(TRAIN), "debug=smoke", f"hydra.run.dir={run_dir}", *overrides],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    return run_dir


@pytest.fixture(scope="module")
def two_runs(tmp_path_factory) -> tuple[Path, Path]:
    """greedy seed 0 and random seed 1 on System-I, from two separate train.py calls."""
    root = tmp_path_factory.mktemp("runs")
    return (
        train_run(root / "runA", "learner=greedy", "system=system1", "seed=0"),
        train_run(root / "runB", "learner=random", "system=system1", "seed=1"),
    )


def report(*inputs: Path, out: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, str(REPORT), *map(str, inputs), "--out", str(out)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )


def copies(runs: tuple[Path, Path], tmp_path: Path) -> tuple[Path, Path]:
    return tuple(Path(shutil.copytree(r, tmp_path / r.name)) for r in runs)  # type: ignore[return-value]


def test_run_dirs_of_separate_train_calls_are_reported_as_runs(two_runs, tmp_path):
    """Two runs, two learners, two seeds: no "missing" greedy seed 1 or random seed 0."""
    done = report(*two_runs, out=tmp_path / "report")
    assert done.returncode == 0, done.stderr
    assert "(2 runs, 0 missing; " in done.stdout
    text = (tmp_path / "report" / "report.md").read_text()
    assert "**2 finished runs** (run dirs, not a sweep: no expected grid)" in text
    assert "## Missing jobs" not in text
    assert (tmp_path / "report" / "missing.csv").read_text().strip() == (
        "learner,system,seed,reason,job_dir,overrides"
    )


def sweep(root: Path, learner: str, seed: int) -> Path:
    """A sweep dir of one job as Hydra's BasicSweeper leaves it (multirun.yaml, job dir 0)."""
    sweeper = {"_target_": BASIC_SWEEPER, "params": {"learner": learner, "seed": str(seed)}}
    hydra = {"sweeper": sweeper, "overrides": {"task": []}, "runtime": {"choices": {}}}
    root.mkdir(parents=True)
    OmegaConf.save(OmegaConf.create({"seed": 0, "hydra": hydra}), root / "multirun.yaml")
    job = write_run(root / "0", learner, seed)
    OmegaConf.save(
        OmegaConf.create([f"learner={learner}", f"seed={seed}"]), job / ".hydra" / "overrides.yaml"
    )
    return root


def test_two_sweeps_in_one_folder_expect_their_own_jobs_only(tmp_path):
    """A folder of two sweeps (cql seed 0, dql seed 1): each sweep expects its one job."""
    sweep(tmp_path / "sweeps" / "a", "cql", 0)
    sweep(tmp_path / "sweeps" / "b", "dql", 1)
    collection = collect_runs([tmp_path / "sweeps"])
    assert [r.key for r in collection.runs] == [("cql", "system1", 0), ("dql", "system1", 1)]
    assert collection.missing == [] and collection.expected_jobs == 2
    # their job dirs given one by one are runs: nothing expected
    collection = collect_runs([tmp_path / "sweeps" / "a" / "0", tmp_path / "sweeps" / "b" / "0"])
    assert collection.missing == [] and collection.expected_jobs == 0


def left_out_lines(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if "left out of the report" in line]


def test_a_curve_row_that_does_not_parse_leaves_its_run_out_by_name(two_runs, tmp_path):
    run_a, run_b = copies(two_runs, tmp_path)
    curve = run_a / "curve.csv"
    with curve.open("a") as handle:
        handle.write("1,1,abc\n")  # line 2, under the header of a fixed policy's empty curve
    done = report(run_a, run_b, out=tmp_path / "report")
    assert done.returncode == 0, done.stderr
    assert "Traceback" not in done.stderr
    assert "(1 runs, 0 missing, 1 left out; " in done.stdout
    (line,) = left_out_lines(done.stderr)  # one log line, naming the run, the file and the line
    assert f"{run_a} left out of the report: {curve}: line 2:" in line and "'abc'" in line
    text = (tmp_path / "report" / "report.md").read_text()
    assert "**1 left out** (unreadable files)" in text and "## Runs left out" in text
    assert re.search(rf"\| `{re.escape(str(run_a))}` \| {re.escape(str(curve))}: line 2: ", text)
    runs = (tmp_path / "report" / "runs.csv").read_text()
    assert str(run_b) in runs and str(run_a) not in runs  # the other run is reported


def test_a_damaged_metrics_json_leaves_its_run_out_by_name(two_runs, tmp_path):
    run_a, run_b = copies(two_runs, tmp_path)
    metrics = run_b / "metrics.json"
    metrics.write_text(metrics.read_text()[:100])  # cut short
    done = report(run_a, run_b, out=tmp_path / "report")
    assert done.returncode == 0, done.stderr
    assert "(1 runs, 0 missing, 1 left out; " in done.stdout
    (line,) = left_out_lines(done.stderr)
    assert f"{run_b} left out of the report: {metrics}: not valid JSON" in line
    text = (tmp_path / "report" / "report.md").read_text()
    assert f"| `{run_b}` | {metrics}: not valid JSON" in text
    # nothing readable at all: one error line naming what was left out
    done = report(run_b, out=tmp_path / "nothing")
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert done.stderr.splitlines()[-1].startswith("error: no finished run")
    assert f"left out: {metrics}: not valid JSON" in done.stderr.splitlines()[-1]


@pytest.mark.parametrize(
    ("row", "culprit"),
    [
        ("1,1,abc", "'abc'"),
        ("x,1,5.0", "'x'"),
        ("10,1,nan", "'nan'"),
        ("10,1", "(empty)"),
    ],
)
def test_curve_rows_are_numbers_or_refused_naming_the_line(tmp_path, row, culprit):
    run = write_run(tmp_path / "run", "cql", 0, curve=[(10, 1.0)])
    with (run / "curve.csv").open("a") as handle:
        handle.write(row + "\n")
    collection = collect_runs([run])
    assert collection.runs == []
    (left_out,) = collection.unreadable
    assert left_out.reason.startswith(f"{run / 'curve.csv'}: line 3: ")
    assert culprit in left_out.reason


def yardstick_runs(root: Path) -> None:
    """reserve_es seeds 0 and 1, seed 1 again (a duplicate), and one team_reserve run."""
    episodes = [100.0, 100.0]
    space = {"analytic": 400}
    for name, seed in (("a", 0), ("b", 1), ("c", 1)):
        write_run(
            root / name, "reserve_es", seed, space=space, per_episode=episodes, curve=[(10, 1.0)]
        )
    write_run(root / "d", "team_reserve", 0, per_episode=episodes)


def test_every_table_counts_a_seed_once(tmp_path):
    """The team return table and "Learning against the rules" give reserve_es 2 seeds: the
    duplicate of seed 1 is left out of both."""
    yardstick_runs(tmp_path / "runs")
    text = build_report([tmp_path / "runs"], tmp_path / "report").report.read_text()
    assert "| System-I | reserve_es | 2 | 100.0 ± 0.0 |" in text  # team return
    rules = text[text.index("## Learning against the rules") :]
    assert re.search(r"\| reserve_es \| 2 \| 100\.0 ± 0\.0 \|", rules), rules[:1500]
    assert "| System-I | reserve_es | 2 | 100 ± 0 |" in text  # training time


def test_the_curve_legend_says_how_many_seeds_have_a_curve(tmp_path, monkeypatch):
    """Three seeds in the tables, two with a curve: the legend says "2 of 3"."""
    for seed, curve in enumerate([[(10, 1.0)], [(10, 2.0)], []]):
        write_run(tmp_path / "runs" / str(seed), "dql", seed, curve=curve)
    drawn = []
    line_figure = figures.line_figure
    monkeypatch.setattr(
        figures,
        "line_figure",
        lambda panels, *args, **kw: drawn.extend(panels) or line_figure(panels, *args, **kw),
    )
    text = build_report([tmp_path / "runs"], tmp_path / "report").report.read_text()
    assert "| System-I | dql | 3 |" in text
    (panel,) = [p for p in drawn if "learning curves" in p.title]
    assert list(panel.lines) == ["dql (2 of 3 seeds have a curve)"]


def test_metrics_json_refusal_names_it(tmp_path):
    """The report reads metrics.json through the checked reader (a key of the wrong type)."""
    run = write_run(tmp_path / "run", "cql", 0)
    metrics = json.loads((run / "metrics.json").read_text())
    metrics["seed"] = "zero"
    (run / "metrics.json").write_text(json.dumps(metrics))
    write_run(tmp_path / "other", "cql", 1)
    collection = collect_runs([tmp_path])
    assert [r.seed for r in collection.runs] == [1]
    assert collection.unreadable[0].reason.startswith(f"{run / 'metrics.json'}: seed: ")

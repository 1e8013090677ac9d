"""A tiny sweep (debug=smoke, 2 seeds, fixed policies) through scripts/report.py, checked number by
number against the runs' metrics.json; a failed job is listed as missing; the joblib launcher."""

from __future__ import annotations

import csv
import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

from mrta_rl.reports import t_quantile

ROOT = Path(__file__).resolve().parents[2]
TRAIN, REPORT = ROOT / "scripts" / "train.py", ROOT / "scripts" / "report.py"
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def run_sweep(sweep_dir: Path, *overrides: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [
            sys.executable,
            str(TRAIN),
            "-m",
            "experiment=paper",
            "debug=smoke",
            f"hydra.sweep.dir={sweep_dir}",
            *overrides,
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )


def read_csv(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as handle:
        return list(csv.DictReader(handle))


def check_stat(row: dict[str, str], values: list[float]) -> None:
    """A CSV row's mean/ci95 against the per-seed values (t interval, ddof=1)."""
    assert int(row["n_seeds"]) == len(values)
    mean = sum(values) / len(values)
    std = math.sqrt(sum((v - mean) ** 2 for v in values) / (len(values) - 1))
    assert float(row["mean"]) == pytest.approx(mean)
    assert float(row["ci95"]) == pytest.approx(t_quantile(len(values) - 1) * std / math.sqrt(2))


@pytest.fixture(scope="module")
def sweep(tmp_path_factory) -> tuple[Path, subprocess.CompletedProcess]:
    """2 fixed policies x 2 systems x seeds {0, 1, -1}: the 4 jobs of seed -1 fail validation."""
    sweep_dir = tmp_path_factory.mktemp("sweep")
    result = run_sweep(sweep_dir, "learner=greedy,random", "system=system1,system2", "seed=0,1,-1")
    return sweep_dir, result


def test_sweep_continues_after_a_failed_job(sweep):
    sweep_dir, result = sweep
    assert result.returncode != 0  # Hydra reports the failure once every job has run
    assert "seed: must be an integer in [0, 2147483647], got -1" in result.stderr
    finished = sorted(sweep_dir.glob("*/metrics.json"))
    assert len(finished) == 8  # the 8 good jobs ran and kept their results
    assert (sweep_dir / "multirun.yaml").is_file()


def test_report_files_and_numbers(sweep, tmp_path):
    sweep_dir, _ = sweep
    out = tmp_path / "report"
    done = subprocess.run(
        [sys.executable, str(REPORT), str(sweep_dir), "--out", str(out)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    assert "8 runs, 4 missing" in done.stdout

    for stem in ("runs", "ctr", "itr", "team_return", "learning_space", "claims", "missing"):
        assert (out / f"{stem}.csv").is_file(), stem
    report = (out / "report.md").read_text()
    pngs = sorted(out.glob("*.png"))
    assert {p.stem for p in pngs} == {
        "ctr_system1_L",
        "ctr_system1_H",
        "ctr_system2_L",
        "ctr_system2_H",
        "itr_system1",
        "itr_system2",
        "team_return",  # fixed policies do not train: no learning curves
        "performance_profile",  # IQM / profiles of the return relative to greedy
    }
    for png in pngs:
        assert png.read_bytes()[:8] == PNG_MAGIC and png.stat().st_size > 10_000
        assert f"]({png.name})" in report  # every figure is linked from report.md

    metrics = [json.loads(p.read_text()) for p in sorted(sweep_dir.glob("*/metrics.json"))]
    by_cell: dict[tuple[str, str], list[dict]] = {}
    for m in metrics:
        by_cell.setdefault((m["system"], m["learner"]["name"]), []).append(m)
    assert all(len(runs) == 2 for runs in by_cell.values()) and len(by_cell) == 4

    ctr = {
        (r["system"], r["learner"], r["task_type"], r["priority"]): r
        for r in read_csv(out / "ctr.csv")
    }
    itr = {(r["system"], r["learner"], r["robot"]): r for r in read_csv(out / "itr.csv")}
    returns = {(r["system"], r["learner"]): r for r in read_csv(out / "team_return.csv")}
    for (system, learner), runs in by_cell.items():
        evals = [m["eval"] for m in runs]
        for task in evals[0]["ctr"]:
            for p in ("L", "H"):
                values = [e["ctr"][task][p] for e in evals]
                if None not in values:
                    check_stat({**ctr[(system, learner, task, p)]}, values)
        for p in ("L", "H"):
            check_stat(ctr[(system, learner, "all", p)], [e["ctr_overall"][p] for e in evals])
        for robot in evals[0]["itr"]:
            check_stat(itr[(system, learner, robot)], [e["itr"][robot] for e in evals])
        row = returns[(system, learner)]
        mean = sum(e["team_return"]["mean"] for e in evals) / 2
        assert float(row["team_return_mean"]) == pytest.approx(mean)
        greedy = sum(m["baseline_greedy"]["team_return"]["mean"] for m in runs) / 2
        assert float(row["gain_mean"]) == pytest.approx(mean - greedy)
    # greedy evaluated as a learner equals its own baseline on the same streams
    assert float(returns[("system1", "greedy")]["gain_mean"]) == pytest.approx(0.0)

    assert len(read_csv(out / "runs.csv")) == 8
    missing = read_csv(out / "missing.csv")
    assert sorted((m["learner"], m["system"], m["seed"]) for m in missing) == [
        ("greedy", "system1", "-1"),
        ("greedy", "system2", "-1"),
        ("random", "system1", "-1"),
        ("random", "system2", "-1"),
    ]
    assert "**8 finished runs** of 12 expected" in report and "## Missing jobs" in report
    # a markdown cell is the CSV's mean ± ci95 rounded to one decimal
    cell = ctr[("system2", "random", "all", "H")]
    assert f"{float(cell['mean']):.1f} ± {float(cell['ci95']):.1f}" in report
    # claims about the tabular learners cannot be judged from fixed policies alone
    claims = read_csv(out / "claims.csv")
    assert {c["verdict"] for c in claims} == {"not evaluable"}


def test_joblib_launcher(tmp_path, compiled_env):
    sweep_dir = tmp_path / "sweep"
    result = run_sweep(
        sweep_dir,
        "hydra/launcher=joblib",
        "hydra.launcher.n_jobs=2",
        "learner=greedy",
        "system=system1",
        "seed=0,1",
    )
    assert result.returncode == 0, result.stderr
    assert "Joblib.Parallel" in result.stdout + result.stderr
    done = subprocess.run(
        [sys.executable, str(REPORT), str(sweep_dir)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    assert "2 runs, 0 missing" in done.stdout
    assert (sweep_dir / "report" / "report.md").is_file()

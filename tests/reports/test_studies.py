"""Study report sections: field statistics, swept dimensions, refused runs."""

from __future__ import annotations

import csv
import itertools
import json
import math
from pathlib import Path

import numpy as np
import pytest
from omegaconf import OmegaConf
from scipy import stats as scipy_stats

from mrta_rl.reports import build_report
from mrta_rl.reports.collect import collect_runs
from mrta_rl.reports.experiments import study_points, swept_dimensions
from mrta_rl.reports.stats import iqm_ci, performance_profile, probability_of_improvement
from mrta_rl.reports.study import study_of
from tests.reports.test_collect import write_run

# --- statistics on small fixed arrays, against values computed independently -------------------


def exact_bootstrap_iqm(tasks: list[np.ndarray]) -> np.ndarray:
    """IQM of every stratified resample of tiny tasks, enumerated (each equally likely)."""
    per_task = [np.array(list(itertools.product(t, repeat=len(t)))) for t in tasks]  # [n^n, n]
    grids = np.meshgrid(*[np.arange(len(r)) for r in per_task], indexing="ij")
    pooled = np.concatenate(
        [r[g.ravel()] for r, g in zip(per_task, grids, strict=True)], axis=1
    )  # [all resamples, runs of all tasks]
    return scipy_stats.trim_mean(pooled, 0.25, axis=1)


def test_iqm_by_hand_and_its_interval():
    # IQM of 1..8: drop 1, 2 and 7, 8 -> mean(3, 4, 5, 6) = 4.5
    assert iqm_ci([[8, 1, 7, 2, 6, 3, 5, 4]]).value == pytest.approx(4.5)
    # two tasks of 4 runs: 256 * 256 equally likely stratified resamples, enumerated exactly
    tasks = [np.array([0.8, 0.9, 1.0, 1.3]), np.array([1.1, 1.2, 1.2, 2.0])]
    est = iqm_ci(tasks)
    assert est.value == pytest.approx(np.mean([1.0, 1.1, 1.2, 1.2]))  # pooled 8 runs, middle 4
    exact = exact_bootstrap_iqm(tasks)
    assert exact.size == 256 * 256
    low, high = np.quantile(exact, [0.025, 0.975])
    assert est.low == pytest.approx(low, abs=0.03)
    assert est.high == pytest.approx(high, abs=0.03)
    assert est.n == 8


def test_probability_of_improvement_by_hand():
    # task 1: X (1, 2, 3) vs Y (2, 2, 0): 5 of 9 pairs X > Y, 2 ties -> 5/9 + 1/9 = 2/3
    # task 2: X (5, 6) vs Y (1, 7): X > Y in 2 of 4 pairs -> 1/2; mean over tasks 7/12
    est = probability_of_improvement([[1, 2, 3], [5, 6]], [[2, 2, 0], [1, 7]])
    assert est.value == pytest.approx(7 / 12)
    # independently: Mann-Whitney U / (n m) per task
    u1 = scipy_stats.mannwhitneyu([1, 2, 3], [2, 2, 0]).statistic / 9
    u2 = scipy_stats.mannwhitneyu([5, 6], [1, 7]).statistic / 4
    assert est.value == pytest.approx((u1 + u2) / 2)
    assert 0.0 <= est.low <= est.value <= est.high <= 1.0
    swapped = probability_of_improvement([[2, 2, 0], [1, 7]], [[1, 2, 3], [5, 6]])
    assert swapped.value == pytest.approx(1 - 7 / 12)


def test_performance_profile_by_hand():
    # task 1 (0.9, 1.0, 1.1), task 2 (1.2, 0.8, 1.0); tau = 0.95: 2/3 and 2/3; tau = 1.05: 1/3, 1/3
    profile = performance_profile([[0.9, 1.0, 1.1], [1.2, 0.8, 1.0]], [0.5, 0.95, 1.05, 1.5])
    assert profile.fraction.tolist() == pytest.approx([1.0, 2 / 3, 1 / 3, 0.0])
    assert (profile.low <= profile.fraction + 1e-12).all()
    assert (profile.high >= profile.fraction - 1e-12).all()
    assert profile.low[0] == profile.high[0] == 1.0  # every resample is above 0.5


def test_undefined_intervals():
    one = iqm_ci([[3.0]])
    assert one.value == 3.0 and math.isnan(one.low) and one.format() == "3.00"
    assert iqm_ci([]).format() == "–"
    same = iqm_ci([[1.0, 1.0], [1.0, 1.0, 1.0]])
    assert (same.value, same.low, same.high) == (1.0, 1.0, 1.0)
    with pytest.raises(ValueError, match="tasks"):
        probability_of_improvement([[1, 2]], [])


# --- swept dimensions and refused runs, on fabricated run dirs ---------------------------------


def study_run(
    path: Path,
    learner: str,
    seed: int,
    settings: dict,
    team_return: float,
    *,
    space: dict | None = None,
    wall: float = 2.0,
    peak: float = 100.0,
) -> Path:
    """A run dir of a swept config: write_run plus the swept settings and resources."""
    write_run(path, learner, seed, team_return=team_return, space=space, system="random")
    config = OmegaConf.load(path / ".hydra" / "config.yaml")
    for key, value in settings.items():
        OmegaConf.update(config, key, value, force_add=True)
    OmegaConf.save(config, path / ".hydra" / "config.yaml")
    overrides = [f"{k}={v}" for k, v in settings.items()] + [f"learner={learner}", f"seed={seed}"]
    OmegaConf.save(OmegaConf.create(overrides), path / ".hydra" / "overrides.yaml")
    metrics = json.loads((path / "metrics.json").read_text())
    metrics["resources"] = {"wall_s": wall, "peak_rss_mb": peak, "peak_rss_scope": "run"}
    (path / "metrics.json").write_text(json.dumps(metrics))
    return path


def refused_run(path: Path, learner: str, seed: int, settings: dict, reason: str) -> Path:
    (path / ".hydra").mkdir(parents=True)
    config = OmegaConf.create({"seed": seed})
    for key, value in settings.items():
        OmegaConf.update(config, key, value, force_add=True)
    OmegaConf.save(config, path / ".hydra" / "config.yaml")
    record = {"learner": learner, "system": "random", "seed": seed, "reason": reason}
    (path / "refused.json").write_text(json.dumps(record))
    return path


def test_scaling_report_from_fabricated_runs(tmp_path):
    runs = tmp_path / "scaling"
    sizes = (10, 20, 50)
    for m, team, seed in itertools.product(sizes, (0, 1), (0,)):
        base = {"system.n_robots": m, "system.seed": team}
        # greedy-normalized: greedy's own baseline is 90 in write_run
        study_run(runs / f"g{m}_{team}", "greedy", seed, base, 90.0, wall=0.1 * m, peak=50 + m)
        study_run(
            runs / f"s{m}_{team}", "subg_cql", seed, {**base, "partition.max_group_size": 4},
            99.0 + m / 10, space={"analytic": 10 ** (m // 2), "visited": 5 * m}, wall=m,
        )  # fmt: skip
        if m < 50:
            study_run(runs / f"c{m}_{team}", "cql", seed, base, 95.0, space={"analytic": 4**m})
        else:
            refused_run(runs / f"c{m}_{team}", "cql", seed, base, "needs 3.1e+28 GB, limit 8 GB")
    study = study_of([])  # the swept settings of conf/experiment/scaling.yaml, switch_cost.yaml
    points = study_points(collect_runs([runs]).runs, [runs], study)
    assert swept_dimensions(points, study) == ["system.n_robots"]
    assert len(points) == 18 and (points["refused"] != "").sum() == 2
    files = build_report([runs], tmp_path / "out")
    text = files.report.read_text()
    assert "## Against the team size (robots) (`system.n_robots`)" in text
    section = text[text.index("## Against the team size") :]
    row = next(line for line in section.splitlines() if line.startswith("| cql |"))
    assert "refused: needs 3.1e+28 GB, limit 8 GB" in row  # shown as refused, not as missing
    assert row.count("0.056") == 2  # (95 - 90) / 90 at 10 and 20 robots
    assert "subg_cql (g=4)" in text  # no label recorded: the learner's name
    for stem in ("team_size_return", "team_size_space", "team_size_cost", "performance_profile"):
        assert files.figures[stem].is_file() and files.figures[stem].stat().st_size > 1000
    with files.csvs["study"].open() as handle:
        rows = list(csv.DictReader(handle))
    assert {
        r["refused"] for r in rows if r["learner"] == "cql" and r["system.n_robots"] == "50"
    } == {"refused: needs 3.1e+28 GB, limit 8 GB"}
    big = next(r for r in rows if r["learner"] == "cql" and r["system.n_robots"] == "20")
    assert int(big["space_analytic"]) == 4**20  # exact
    with files.csvs["field_stats"].open() as handle:
        field = {(r["statistic"], r["x"], r["y"]): r for r in csv.DictReader(handle)}
    assert float(field["iqm", "greedy", ""]["value"]) == pytest.approx(0.0)
    # subG-CQL (g=4) beats greedy in every run of every task: P = 1
    improvement = field["probability_of_improvement", "subg_cql (g=4)", "greedy"]
    assert float(improvement["value"]) == pytest.approx(1.0)
    assert "Probability of improvement" in text and "IQM" in text


def test_a_learner_with_two_settings_draws_two_lines(tmp_path):
    """QMIX with its two networks: two study lines, the team size on the x axis of both."""
    runs = tmp_path / "scaling"
    for m, network in itertools.product((10, 20), ("mlp", "set")):
        settings = {"system.n_robots": m, "learner.network": network}
        study_run(runs / f"q{m}{network}", "qmix", 0, settings, 95.0 + (network == "set"))
    points = study_points(collect_runs([runs]).runs, [runs], study_of([]))
    lines = points.groupby("series")["system.n_robots"].apply(sorted).to_dict()
    assert lines == {"qmix network=mlp": [10, 20], "qmix network=set": [10, 20]}


def test_switch_cost_claims_along_the_dimension(tmp_path):
    runs = tmp_path / "switch"
    for s, seed in itertools.product((0, 4, 8), (0, 1)):
        # CQL's CTR falls below DQL's from s = 4 on: the "CQL best" claims hold only at s = 0
        best = 90.0 if s == 0 else 30.0
        for learner, ctr in (("cql", best), ("semi_cql", 60.0), ("dql", 50.0), ("subg_cql", 55.0)):
            study_run(
                runs / f"{learner}{s}_{seed}", learner, seed, {"env.switch_ticks": s}, 100.0 - s
            )
            metrics = json.loads((runs / f"{learner}{s}_{seed}" / "metrics.json").read_text())
            metrics["eval"]["ctr_overall"] = {"L": ctr + seed, "H": ctr + 10 + seed}
            (runs / f"{learner}{s}_{seed}" / "metrics.json").write_text(json.dumps(metrics))
    files = build_report([runs], tmp_path / "out")
    text = files.report.read_text()
    assert "## Against the task-switch setup ticks s (`env.switch_ticks`)" in text
    line = next(row for row in text.splitlines() if row.startswith("| cql_best_ctr |"))
    cells = [c.strip() for c in line.strip("|").split("|")]
    assert cells[2:4] == ["0", "4, 8"]  # holds at s = 0, does not hold at 4 and 8
    assert files.figures["switch_ticks_return"].is_file()
    assert "team_size_return" not in files.figures

"""Reports without Hydra runs: t quantiles, collection of hand-written run dirs, the long table and
its summary, claims, CSVs, the marl-eval JSON, and what the package imports."""

from __future__ import annotations

import csv
import json
import math
import subprocess
import sys
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from mrta_rl.reports import build_report, collect_runs, long_table, mean_ci, summarize, t_quantile
from mrta_rl.reports.claims import check_claims
from mrta_rl.reports.collect import RunRecord, configuration_variants, expected_sweep_jobs
from mrta_rl.reports.frame import stat, summarize_curve
from mrta_rl.reports.study import study_of

TYPES, ROBOTS = ("T1", "T2", "T3"), ("R1", "R2")
ROBOT_TABLE = {"R1": ["T1", "T2", "T3"], "R2": ["T1"]}  # T1: 2 robots, T2/T3: 1


def write_run(
    run_dir: Path,
    learner: str,
    seed: int,
    *,
    ctr_l: float = 50.0,
    ctr_h: float = 80.0,
    itr: float = 20.0,
    team_return: float = 100.0,
    space: dict[str, int] | None = None,
    curve: list[tuple[int, float]] | None = None,
    system: str = "system1",
    groups: dict[str, tuple[list[str], float, float]] | None = None,
    settings: dict | None = None,
    per_episode: list[float] | None = None,
) -> Path:
    """A run dir as scripts/train.py writes it (metrics.json, curve.csv, .hydra/config.yaml).

    ``groups``: sub-group -> (task types, learner's part, greedy's part) of a partitioned run;
    ``settings``: learner hyperparameters of the run's config; ``per_episode``: the evaluation
    team return of each episode.
    """

    def block(ret: float, low: float, high: float, idle: float) -> dict:
        return {
            "episodes": 2,
            "team_return": {"mean": ret, "std": 1.0},
            "ctr": {t: {"L": low + j, "H": high + j} for j, t in enumerate(TYPES)},
            "ctr_overall": {"L": low + 1, "H": high + 1},
            "itr": {r: idle + i for i, r in enumerate(ROBOTS)},
        }

    run_dir.mkdir(parents=True)
    metrics = {
        "learner": {"name": learner, "label": learner, "kind": "tabular"},
        "system": system,
        "seed": seed,
        "eval": block(team_return, ctr_l, ctr_h, itr),
        "baseline_greedy": block(90.0, 40.0, 70.0, 30.0),
        "train": {"env_ticks": 100, "wall_s": 1.5, "episodes": 2},
        "learning_space": space or {},
    }
    if per_episode is not None:
        metrics["eval"]["team_return"]["per_episode"] = per_episode
    for group, (types, mine, greedy) in (groups or {}).items():
        for key, part in (("eval", mine), ("baseline_greedy", greedy)):
            split = metrics[key].setdefault("return_by_group", {})
            split[group] = {"types": types, "return": part}
    (run_dir / "metrics.json").write_text(json.dumps(metrics))
    with (run_dir / "curve.csv").open("w") as handle:
        handle.write("env_ticks,episode,team_return_mean\n")
        for k, (ticks, ret) in enumerate(curve or []):
            handle.write(f"{ticks},{k + 1},{ret}\n")
    (run_dir / ".hydra").mkdir()
    OmegaConf.save(
        OmegaConf.create(
            {
                "seed": seed,
                "system": {"name": system, "robots": ROBOT_TABLE},
                "learner": {"_target_": "x.Y", "_partial_": True, "alpha": 0.1, **(settings or {})},
                "env": {"horizon": 50},
                "train": {"episodes": 2},
                "eval": {"episodes": 2},
            }
        ),
        run_dir / ".hydra" / "config.yaml",
    )
    return run_dir


@pytest.mark.parametrize(
    ("df", "expected"), [(1, 12.7062), (2, 4.3027), (4, 2.7764), (9, 2.2622), (30, 2.0423)]
)
def test_t_quantile_matches_tables(df, expected):
    assert t_quantile(df) == pytest.approx(expected, abs=1e-4)


def test_mean_ci_ignores_undefined_values():
    stat = mean_ci([1.0, 2.0, 3.0, None, math.nan])
    assert (stat.n, stat.mean, stat.std) == (3, 2.0, 1.0)
    assert stat.ci95 == pytest.approx(t_quantile(2) / math.sqrt(3))
    assert mean_ci([5.0]).format() == "5.0" and mean_ci([]).format() == "–"
    with pytest.raises(ValueError):
        t_quantile(0)


def test_collect_reports_duplicates_and_expects_nothing_of_run_dirs(tmp_path):
    write_run(tmp_path / "a", "cql", 0)
    write_run(tmp_path / "b", "cql", 1)
    write_run(tmp_path / "c", "dql", 0)  # no dql seed 1: run dirs outside a sweep expect none
    write_run(tmp_path / "d", "dql", 0)  # same cell again: counted once
    collection = collect_runs([tmp_path])
    assert [r.key for r in collection.runs] == [
        ("cql", "system1", 0),
        ("cql", "system1", 1),
        ("dql", "system1", 0),
    ]
    assert collection.missing == [] and collection.expected_jobs == 0
    assert len(collection.duplicates) == 1


def test_runs_differing_in_hyperparameters_are_separate_configurations(tmp_path):
    """Issue 9 defect 1: a reserve x hold_level sweep is four rows, not one run and 3 dropped."""
    returns = {}
    for i, (reserve, hold) in enumerate([(0, 0), (0, 1), (1, 0), (1, 1)]):
        returns[reserve, hold] = 100.0 + 10 * i
        write_run(
            tmp_path / str(i),
            "subg_reserve",
            0,
            team_return=100.0 + 10 * i,
            settings={"reserve": reserve, "hold_level": hold},
        )
    write_run(tmp_path / "again", "subg_reserve", 0, settings={"reserve": 1, "hold_level": 0})
    write_run(
        tmp_path / "seed1",
        "subg_reserve",
        1,
        team_return=returns[1, 0],
        settings={"reserve": 1, "hold_level": 0},
    )
    write_run(tmp_path / "greedy", "greedy", 0)  # nothing differs among greedy runs: plain name
    collection = collect_runs([tmp_path])
    variants = [f"subg_reserve reserve={a} hold_level={b}" for a in (0, 1) for b in (0, 1)]
    assert [(r.learner, r.seed) for r in collection.runs] == [
        ("greedy", 0),
        *((v, 0) for v in variants[:2]),
        (variants[2], 0),
        (variants[2], 1),
        (variants[3], 0),
    ]
    # only the same configuration with the same seed is a duplicate
    assert [d.run_dir.name for d in collection.duplicates] == ["again"]
    frame = long_table(collection.runs)
    summary = summarize(frame, study_of([]).learners)
    assert list(dict.fromkeys(summary["learner"])) == ["greedy", *variants]  # paper order, values
    for (reserve, hold), value in returns.items():
        cell = summary[summary["learner"] == f"subg_reserve reserve={reserve} hold_level={hold}"]
        assert stat(cell, "team_return").mean == value
    seeds = frame[frame["learner"] == "subg_reserve reserve=1 hold_level=0"]["seed"]
    assert sorted(set(seeds)) == [0, 1]
    report = build_report([tmp_path], tmp_path / "report").report.read_text()
    assert "| subg_reserve reserve=1 hold_level=0 |" in report  # no label recorded: the name


def test_expected_jobs_follow_the_basic_sweeper(tmp_path):
    OmegaConf.save(
        OmegaConf.create(
            {
                "seed": 0,
                "hydra": {
                    "sweeper": {
                        "_target_": "hydra._internal.core_plugins.basic_sweeper.BasicSweeper",
                        "max_batch_size": None,
                        "params": {"learner": "cql,dql", "seed": "0,1,2"},
                    },
                    "overrides": {
                        "task": ["experiment=paper", "seed=3,4"]
                    },  # the command line wins
                },
            }
        ),
        tmp_path / "multirun.yaml",
    )
    jobs = expected_sweep_jobs(tmp_path / "multirun.yaml")
    assert jobs[0] == ["learner=cql", "seed=3", "experiment=paper"]
    assert len(jobs) == 4 and {j[1] for j in jobs} == {"seed=3", "seed=4"}
    collection = collect_runs([tmp_path])  # no job dir at all: every job is missing
    assert len(collection.missing) == 4 and collection.missing[0].reason.startswith("never")


def test_summaries_and_claims(tmp_path):
    # CQL best CTR, subG-CQL a bit lower and lowest ITR, DQL lowest L CTR and highest ITR
    spec = {
        "cql": dict(ctr_l=70, ctr_h=90, itr=20, space={"analytic": 2**70, "visited": 10}),
        "semi_cql": dict(ctr_l=60, ctr_h=80, itr=25, space={"analytic": 400, "visited": 5}),
        "dql": dict(ctr_l=50, ctr_h=85, itr=30, space={"analytic": 400, "visited": 7}),
        "subg_cql": dict(ctr_l=65, ctr_h=86, itr=10, space={"analytic": 5000, "visited": 8}),
    }
    for learner, kwargs in spec.items():
        for seed in (0, 1):
            shift = {"ctr_l": kwargs["ctr_l"] + seed, "ctr_h": kwargs["ctr_h"] + seed}
            write_run(tmp_path / f"{learner}{seed}", learner, seed, **{**kwargs, **shift})
    study = study_of([])  # the paper's row order and claims (conf/experiment/paper.yaml)
    summary = summarize(long_table(collect_runs([tmp_path]).runs), study.learners)
    cells = list(dict.fromkeys(zip(summary["system"], summary["learner"], strict=True)))
    assert cells == [("system1", n) for n in ("cql", "semi_cql", "dql", "subg_cql")]
    cql = summary[summary["learner"] == "cql"]
    assert stat(cql, "ctr", "T2", "L").mean == pytest.approx(71.5)  # (70 + 1 + 71 + 1) / 2
    half = t_quantile(1) * math.sqrt(0.5) / math.sqrt(2)
    assert stat(cql, "ctr", "T2", "L").ci95 == pytest.approx(half)
    assert stat(cql, "itr", "mean").mean == pytest.approx(20.5)
    assert stat(cql, "gain").mean == 10.0
    verdicts = {(r.claim, r.system): r.verdict for r in check_claims(summary, study)}
    for claim in (
        "h_above_l",
        "cql_best_ctr",
        "cql_best_each_type",
        "subg_ctr_bit_lower",
        "dql_lowest_ctr_l",
        "subg_lowest_itr",
        "dql_highest_itr",
        "semi_itr_between",
        "space_order",
        "space_semi_eq_dql",
    ):
        assert verdicts[(claim, "system1")] == "holds", claim
    # semi-CQL H (80) is below DQL H (85) and its L above: holds; our capable-robot count is
    # 2 for T1 and 1 for T2/T3 while CTR grows with the type index: does not hold
    assert verdicts[("semi_vs_dql_ctr", "system1")] == "holds"
    assert verdicts[("more_robots_higher_ctr", "system1")] == "does not hold"
    assert verdicts[("space_system2_larger", "all")] == "not evaluable"

    without_dql = summary[summary["learner"] != "dql"]  # comparisons over all four cannot be made
    verdicts = {(r.claim, r.system): r.verdict for r in check_claims(without_dql, study)}
    assert verdicts[("cql_best_ctr", "system1")] == "not evaluable"
    assert verdicts[("subg_ctr_bit_lower", "system1")] == "holds"


def test_curves_keep_the_common_prefix(tmp_path):
    runs = collect_runs(
        [
            write_run(tmp_path / "a", "cql", 0, curve=[(10, 1.0), (20, 3.0), (30, 5.0)]),
            write_run(tmp_path / "b", "cql", 1, curve=[(10, 3.0), (20, 5.0)]),
        ]
    ).runs
    curve, seeds = summarize_curve(runs)
    assert curve["x"].tolist() == [10, 20] and curve["mean"].tolist() == [2.0, 4.0]
    assert seeds == 2 and curve["high"][0] > curve["mean"][0] > curve["low"][0]
    assert summarize_curve(collect_runs([write_run(tmp_path / "c", "greedy", 0)]).runs) is None


def test_report_keeps_big_learning_spaces_exact(tmp_path):
    for seed in (0, 1):
        write_run(
            tmp_path / "runs" / f"s{seed}",
            "cql",
            seed,
            space={"analytic": 2**70 + 1, "visited": 3 + seed},
            curve=[(10, 1.0 + seed), (20, 2.0)],
        )
    files = build_report([tmp_path / "runs"])
    assert files.out_dir == (tmp_path / "runs" / "report").resolve()
    with files.csvs["learning_space"].open() as handle:
        rows = {row["key"]: row for row in csv.DictReader(handle)}
    assert rows["analytic"]["exact"] == str(2**70 + 1) and rows["visited"]["exact"] == ""
    text = files.report.read_text()
    assert "1.181e+21" in text and "![System-I learning curves](curve_system1.png)" in text
    assert set(files.figures) >= {
        "ctr_system1_L",
        "ctr_system1_H",
        "itr_system1",
        "curve_system1",
        "team_return",
    }


def test_report_splits_the_return_by_sub_group(tmp_path):
    for seed, (g1, g2) in enumerate([(60.0, 40.0), (64.0, 42.0)]):
        groups = {"G1": (["T1"], g1, 50.0), "G2": (["T2", "T3"], g2, 40.0)}
        write_run(tmp_path / "runs" / f"s{seed}", "subg_cql", seed, groups=groups)
    write_run(tmp_path / "runs" / "plain", "cql", 0)  # not partitioned: no row
    files = build_report([tmp_path / "runs"])
    text = files.report.read_text()
    assert "| learner | G1 (T1) | G2 (T2 T3) | team |" in text
    # means over the two seeds: G1 (60 + 64) / 2, G2 (40 + 42) / 2; greedy's parts as written
    assert "| subg_cql | 62.0 ± 25.4 | 41.0 ± 12.7 | 100.0 ± 0.0 |" in text
    assert "| greedy, full team | 50.0 ± 0.0 | 40.0 ± 0.0 | 90.0 ± 0.0 |" in text
    with files.csvs["group_return"].open() as handle:
        rows = list(csv.DictReader(handle))
    assert [(r["learner"], r["group"], r["task_types"]) for r in rows] == [
        ("subg_cql", "G1", "T1"),
        ("subg_cql", "G2", "T2 T3"),
    ]
    assert float(rows[0]["return_mean"]) == 62.0 and float(rows[1]["greedy_return_mean"]) == 40.0


def test_runs_are_compared_on_the_settings_they_record():
    """A setting one run records and another does not differs (``null``): the report does not
    load the learner to guess a default."""
    learner = {"_target_": "mrta_rl.learners.tabular.dql.DQLLearner", "_partial_": True}
    old = {"learner": {**learner, "alpha": 0.1}, "eval": {"episodes": 20}}
    same = {"learner": {**learner, "alpha": 0.1, "prior": "greedy", "features": "paper"}}
    new = {"learner": {**learner, "alpha": 0.1, "prior": "greedy", "features": "time_to_free"}}
    records = [
        RunRecord(Path(f"/x/{i}"), "dql", "system2", 0, {}, (), config, ())
        for i, config in enumerate((old, same, new))
    ]
    assert configuration_variants(records) == [
        "eval.episodes=20 prior=null features=null",
        "eval.episodes=null prior=greedy features=paper",
        "eval.episodes=null prior=greedy features=time_to_free",
    ]
    assert configuration_variants(records[1:]) == ["features=paper", "features=time_to_free"]


def test_labels_come_from_the_learner_block_of_metrics_json(tmp_path):
    """metrics.json's ``{"name", "label", "kind"}`` block names and labels the run."""
    run = collect_runs([write_run(tmp_path / "a", "subg_cql", 0)]).runs[0]
    block = {"name": "subg_cql", "label": "subG-CQL", "kind": "tabular"}
    labelled = RunRecord(
        run.run_dir,
        "subg_cql",
        "system1",
        0,
        {**run.metrics, "learner": block},
        (),
        run.config,
        (),
        variant="alpha=0.2",
    )
    frame = long_table([run, labelled])
    assert (run.name, run.label, labelled.name, labelled.label) == (
        "subg_cql",
        "subg_cql",
        "subg_cql",
        "subG-CQL",
    )
    assert list(dict.fromkeys(frame["label"])) == ["subg_cql", "subG-CQL alpha=0.2"]
    assert list(dict.fromkeys(frame["kind"])) == ["tabular"]


def test_runs_csv_is_the_long_table_pivoted(tmp_path):
    write_run(tmp_path / "a", "cql", 0, ctr_l=40.0, space={"analytic": 2**70 + 1})
    write_run(tmp_path / "b", "cql", 1, ctr_l=44.0, space={"analytic": 2**70 + 1})
    files = build_report([tmp_path], tmp_path / "report")
    with files.csvs["runs"].open() as handle:
        rows = list(csv.DictReader(handle))
    assert [(r["learner"], r["seed"]) for r in rows] == [("cql", "0"), ("cql", "1")]
    assert [float(r["ctr_T2_L"]) for r in rows] == [41.0, 45.0]  # low + index of the type
    assert [float(r["ctr_all_L"]) for r in rows] == [41.0, 45.0]  # low + 1
    assert rows[0]["learning_space_analytic"] == str(2**70 + 1)  # exact
    with files.csvs["ctr"].open() as handle:
        ctr = [r for r in csv.DictReader(handle) if r["priority"] == "L"]
    assert [r["task_type"] for r in ctr] == ["T1", "T2", "T3", "all"]  # the overall CTR last
    assert float(ctr[1]["mean"]) == 43.0 and float(ctr[1]["ci95"]) == pytest.approx(
        t_quantile(1) * math.sqrt(8) / math.sqrt(2)
    )


def test_marl_eval_json_loads_back_with_every_run(tmp_path):
    """The format of marl-eval (BenchMARL's and Mava's JSON loggers): env, task, algorithm,
    ``seed_<n>``, one step with ``step_count`` and the per-episode returns, absolute metrics."""
    write_run(tmp_path / "runs" / "a", "cql", 0, per_episode=[90.0, 110.0])
    write_run(tmp_path / "runs" / "b", "cql", 1, per_episode=[95.0, 105.0])
    write_run(tmp_path / "runs" / "c", "greedy", 0, system="system2")  # no per-episode returns
    files = build_report([tmp_path / "runs"], tmp_path / "report")
    data = json.loads(files.marl_eval.read_text())
    assert list(data) == ["auction"]
    assert {task: sorted(algos) for task, algos in data["auction"].items()} == {
        "system1": ["cql"],
        "system2": ["greedy"],
    }
    cql = data["auction"]["system1"]["cql"]
    assert sorted(cql) == ["seed_0", "seed_1"]
    assert cql["seed_0"] == {
        "step_0": {"step_count": 100, "return": [90.0, 110.0]},  # train.env_ticks of the run
        "absolute_metrics": {"return": [90.0, 110.0]},
    }
    assert cql["seed_1"]["absolute_metrics"]["return"] == [95.0, 105.0]
    greedy = data["auction"]["system2"]["greedy"]["seed_0"]
    assert greedy["step_0"]["return"] == [100.0]  # the mean, for a run without per-episode values


def test_reports_import_no_runner_learner_or_torch(tmp_path):
    """Making a report reads run dirs only: in a fresh process, the report command and building
    a report load no torch, no mrta_rl.runners and no mrta_rl.learners."""
    write_run(tmp_path / "runs" / "a", "cql", 0, curve=[(10, 1.0), (20, 2.0)])
    code = (
        "import sys\n"
        "import mrta_rl.commands.report\n"
        "from mrta_rl.reports import build_report\n"
        f"build_report([{str(tmp_path / 'runs')!r}])\n"
        "bad = sorted(m for m in sys.modules if m.split('.')[0] == 'torch'"
        " or m.startswith(('mrta_rl.runners', 'mrta_rl.learners')))\n"
        "print(bad)\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "[]"
    assert (tmp_path / "runs" / "report" / "report.md").is_file()

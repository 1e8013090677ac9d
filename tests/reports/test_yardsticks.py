"""The report section "Learning against the rules" (mrta_rl/reports/experiments.py), by hand."""

from __future__ import annotations

import csv
import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from mrta_rl.reports.collect import RunRecord
from mrta_rl.reports.experiments import (
    collect_policies,
    section_rows,
    start_comparisons,
    write_section,
)
from mrta_rl.reports.frame import long_table, runs_wide
from mrta_rl.reports.stats import t_quantile
from mrta_rl.reports.study import Prose, study_of

STUDY, PROSE = study_of([]), Prose.shipped()  # the shipped experiments' report blocks
BEST_RESERVE = "team_reserve (best)"  # the best setting of conf/experiment/yardsticks.yaml's rule

GREEDY = [10.0, 20.0, 30.0]  # per evaluation episode, shared by every run
LABELS = {
    "subg_cql": "subG-CQL",
    "cql": "CQL",
    "qmix": "QMIX",
    "reserve_es": "reserve-ES",
    "net_es": "net-ES",
}  # metrics.json's learner block


def record(learner, seed, returns, *, episodes=0, space=None, learner_cfg=None):
    block = {"team_return": {"mean": float(np.mean(returns)), "per_episode": list(returns)}}
    greedy = {"team_return": {"mean": float(np.mean(GREEDY)), "per_episode": GREEDY}}
    metrics = {
        "learner": {"name": learner, "label": LABELS.get(learner, learner), "kind": "tabular"},
        "system": "system2",
        "seed": seed,
        "eval": block,
        "baseline_greedy": greedy,
        "train": {"episodes": episodes},
        "learning_space": space or {},
    }
    config = {"learner": learner_cfg or {}}
    return RunRecord(Path(f"/x/{learner}{seed}"), learner, "system2", seed, metrics, (), config, ())


RUNS = [
    record("team_reserve", 0, [11.0, 22.0, 33.0], learner_cfg={"reserve": 0, "hold_level": 1}),
    record("team_reserve", 0, [9.0, 20.0, 31.0], learner_cfg={"reserve": 1, "hold_level": 1}),
    record("rollout", 0, [14.0, 26.0, 36.0]),
    record("subg_cql", 0, [12.0, 21.0, 33.0], episodes=30, space={"analytic": 5}),
    record("subg_cql", 1, [12.0, 23.0, 33.0], episodes=30, space={"analytic": 5}),
    record("subg_cql", 0, [10.0, 20.0, 30.0], episodes=0, space={"analytic": 5}),
    record(
        "subg_cql",
        0,
        [13.0, 24.0, 36.0],
        episodes=30,
        space={"analytic": 9},
        learner_cfg={"features": "time_to_free"},
    ),
]


def test_policies_and_paired_differences_by_hand(tmp_path):
    policies = collect_policies(RUNS, STUDY)["system2"]
    names = [p.name for p in policies]
    assert names[:3] == ["greedy", BEST_RESERVE, "rollout"]
    assert set(names[3:]) == {"subG-CQL", "subG-CQL untrained", "subG-CQL [time_to_free]"}
    best = policies[1]
    assert best.note == "reserve=0, hold_level=1"  # the better of the two settings (22 vs 20)
    trained = next(p for p in policies if p.name == "subG-CQL")
    np.testing.assert_array_equal(trained.per_episode, [12.0, 22.0, 33.0])  # mean of 2 seeds
    md, files = write_section(RUNS, tmp_path, STUDY, PROSE)
    assert "## Learning against the rules" in md and files["yardsticks_png"].is_file()
    rows = list(csv.DictReader(files["yardsticks"].open()))
    row = next(r for r in rows if r["policy"] == "subG-CQL" and r["versus"] == BEST_RESERVE)
    # paired differences per episode: (12 - 11, 22 - 22, 33 - 33) = (1, 0, 0)
    half = t_quantile(2) * np.std([1.0, 0.0, 0.0], ddof=1) / np.sqrt(3)
    assert float(row["diff"]) == pytest.approx(1 / 3, abs=1e-3)
    assert float(row["diff_ci95"]) == pytest.approx(half, abs=1e-3)
    start = next(r for r in rows if r["policy"] == "subG-CQL" and r["versus"].endswith("untrained"))
    assert float(start["diff"]) == pytest.approx((2 + 2 + 3) / 3, abs=1e-3)
    ttf = next(
        r
        for r in rows
        if r["policy"] == "subG-CQL [time_to_free]" and r["versus"] == "subG-CQL untrained"
    )
    assert float(ttf["diff"]) == pytest.approx((3 + 4 + 6) / 3, abs=1e-3)


def test_the_trained_best_learner_is_a_yardstick_of_every_policy(tmp_path):
    """conf/experiment/yardsticks.yaml names net_es the best learner, as the README does."""
    assert STUDY.best_learner == "net_es"
    runs = [
        *RUNS,
        record("net_es", 0, [13.0, 22.0, 35.0], episodes=100, space={"parameters": 9}),
        record("net_es", 1, [13.0, 24.0, 35.0], episodes=100, space={"parameters": 9}),
        record("reserve_es", 0, [13.0, 22.0, 35.0], episodes=100, space={"analytic": 20}),
    ]
    md, files = write_section(runs, tmp_path, STUDY, PROSE)
    assert "vs net-ES" in md and "vs reserve-ES" not in md
    assert "the trained `net_es` runs" in md
    rows = list(csv.DictReader(files["yardsticks"].open()))
    row = next(r for r in rows if r["policy"] == "rollout" and r["versus"] == "net-ES")
    # rollout (14, 26, 36) against the mean of the two seeds (13, 23, 35): (1, 3, 1)
    assert float(row["diff"]) == pytest.approx(5 / 3, abs=1e-3)
    assert not [r for r in rows if r["policy"] == r["versus"]]  # never against itself
    # the best learner is data: a study that names reserve_es compares every policy to it
    study = dataclasses.replace(STUDY, best_learner="reserve_es")
    md, _ = write_section(runs, tmp_path, study, PROSE)
    assert "vs reserve-ES" in md and "vs net-ES" not in md


def test_no_section_without_rules_or_untrained_runs(tmp_path):
    md, files = write_section([RUNS[3], RUNS[4]], tmp_path, STUDY, PROSE)
    assert md == "" and files == {}


def test_untrained_run_is_found_when_the_collection_names_configurations():
    """collect names a learner's runs by what differs (``cql train.episodes=0``): still paired."""
    runs = [
        record("cql", 0, [10.0, 20.0, 30.0], space={"analytic": 5}, learner_cfg={"alpha": 0.1}),
        record("cql", 0, [12.0, 23.0, 31.0], episodes=30, space={"analytic": 5}),
        record("cql", 1, [14.0, 21.0, 35.0], episodes=30, space={"analytic": 5}),
    ]
    labels = ["cql train.episodes=0 alpha=0.1", "cql train.episodes=30", "cql train.episodes=30"]
    runs = [dataclasses.replace(r, learner=label) for r, label in zip(runs, labels, strict=True)]
    policies = collect_policies(runs, STUDY)["system2"]
    assert [p.name for p in policies] == ["greedy", "CQL untrained", "CQL"]
    rows = [r for r in section_rows({"system2": policies}) if r[1] == "CQL"]
    assert rows[0][5] == "CQL untrained"
    assert rows[0][6] == pytest.approx(8 / 3, abs=1e-3)  # (13, 22, 33) - (10, 20, 30), rounded


def test_start_table_by_hand(tmp_path):
    """Acceptance 2: trained - untrained paired over episodes and over seeds, with its verdict."""
    by_system = collect_policies(RUNS, STUDY)
    comparisons = dict((c.trained.name, c) for _, c in start_comparisons(by_system))
    c = comparisons["subG-CQL"]
    # per episode: mean of the seeds (12, 22, 33) - untrained (10, 20, 30) = (2, 2, 3)
    assert c.paired.mean == pytest.approx(7 / 3)
    assert c.paired.ci95 == pytest.approx(t_quantile(2) * np.sqrt(1 / 3) / np.sqrt(3))
    assert c.paired.n == 3
    # per seed: 22 - 20 = 2 and 68/3 - 20 = 8/3
    assert c.over_seeds.mean == pytest.approx(7 / 3)
    assert c.over_seeds.ci95 == pytest.approx(
        t_quantile(1) * np.std([2, 8 / 3], ddof=1) / np.sqrt(2)
    )
    assert c.verdict == "yes"  # 7/3 - 1.434 > 0
    assert comparisons["subG-CQL [time_to_free]"].over_seeds.n == 1  # one seed: no interval
    md, files = write_section(RUNS, tmp_path, STUDY, PROSE)
    assert "### Does training beat its own start?" in md
    assert "| +2.3 ± 4.2 | yes |" in md  # over seeds: 7/3 ± 12.706 * 0.4714 / sqrt(2)
    assert files["yardsticks_start_png"].is_file() and "(yardsticks_start.png)" in md
    rows = list(csv.DictReader(files["yardsticks_start"].open()))
    assert [r["policy"] for r in rows] == ["subG-CQL", "subG-CQL [time_to_free]"]
    assert float(rows[0]["untrained"]) == 20.0 and rows[0]["met"] == "yes"
    assert float(rows[1]["paired_diff"]) == pytest.approx(13 / 3, abs=1e-3)


@pytest.mark.parametrize(
    ("trained", "verdict"),
    [
        # paired (10, 0, -10); each seed's mean is 20, the untrained mean: 0 ± 0 over seeds
        ([[30.0, 20.0, 10.0], [10.0, 20.0, 30.0]], "no"),
        # paired (-1, -1, -0.75): -0.917 ± 0.359, below zero
        ([[9.0, 19.0, 29.0], [9.0, 19.0, 29.5]], "no (below)"),
        # paired (1.25, 9.75, -9.5) holds zero; both seeds' means are 20.5: +0.5 ± 0 over seeds
        ([[11.0, 30.0, 20.5], [11.5, 29.5, 20.5]], "over seeds only"),
    ],
)
def test_start_verdicts(trained, verdict):
    space = {"analytic": 5}
    runs = [record("cql", 0, [10.0, 20.0, 30.0], space=space)]
    runs += [record("cql", s, r, episodes=30, space=space) for s, r in enumerate(trained)]
    [(_, c)] = start_comparisons(collect_policies(runs, STUDY))
    assert c.verdict == verdict


def reevaluated(tmp_path, name, learner, returns, greedy, *, episodes=0, space=None):
    """A run dir whose metrics.json holds 3 episodes and whose eval_metrics.json holds more."""
    run = record(learner, 0, [1.0, 2.0, 3.0], episodes=episodes, space=space)
    run_dir = tmp_path / name
    run_dir.mkdir()
    blocks = {
        "eval": {"team_return": {"mean": float(np.mean(returns)), "per_episode": returns}},
        "baseline_greedy": {"team_return": {"mean": float(np.mean(greedy)), "per_episode": greedy}},
    }
    (run_dir / "eval_metrics.json").write_text(json.dumps(blocks))
    return dataclasses.replace(run, run_dir=run_dir)


def test_reevaluated_runs_are_scored_on_their_reevaluation(tmp_path):
    """eval_metrics.json (scripts/evaluate.py episodes=N) replaces the 3-episode evaluation."""
    greedy5 = [10.0, 20.0, 30.0, 40.0, 50.0]
    space = {"parameters": 7}
    runs = [
        record("team_reserve", 0, [11.0, 22.0, 33.0]),  # 3 episodes: not paired with the rest
        reevaluated(tmp_path, "u", "qmix", greedy5, greedy5, space=space),
        reevaluated(
            tmp_path, "t", "qmix", [12.0, 21.0, 33.0, 41.0, 53.0], greedy5, episodes=6, space=space
        ),
    ]
    policies = collect_policies(runs, STUDY)["system2"]
    greedy = policies[0]
    np.testing.assert_array_equal(greedy.per_episode, greedy5)  # the run with the most episodes
    qmix = next(p for p in policies if p.name == "QMIX")
    assert qmix.means == [pytest.approx(32.0)]
    [(_, c)] = start_comparisons({"system2": policies})
    assert c.paired.n == 5 and c.paired.mean == pytest.approx(2.0)  # (2, 1, 3, 1, 3)
    md, _ = write_section(runs, tmp_path, STUDY, PROSE)
    row = next(line for line in md.splitlines() if line.startswith("| QMIX |"))
    assert row.split("|")[6].strip() == "–"  # vs team_reserve: 5 episodes against 3, unpaired


def test_a_reevaluation_without_its_blocks_is_refused(tmp_path):
    run = reevaluated(tmp_path, "r", "qmix", [1.0], [1.0], space={"parameters": 7})
    (run.run_dir / "eval_metrics.json").write_text(json.dumps({"eval": {}}))
    with pytest.raises(ValueError, match=r"eval_metrics.json.*baseline_greedy"):
        collect_policies([RUNS[0], run], STUDY)


def test_runs_on_other_task_streams_are_refused(tmp_path):
    """Same number of episodes, other streams (greedy differs): pairing them would be wrong."""
    other = record("qmix", 0, [12.0, 21.0, 33.0], episodes=6, space={"parameters": 7})
    other.metrics["baseline_greedy"]["team_return"]["per_episode"] = [10.0, 20.0, 31.0]
    with pytest.raises(ValueError, match=r"different task streams.*eval.batch_size"):
        collect_policies([*RUNS, other], STUDY)


def test_a_planner_on_a_trained_base_is_its_own_policy_with_its_decision_time(tmp_path):
    """Two seeds' rollouts on reserve_es runs form one policy; ms per tick is their mean."""
    planners = []
    for seed, (returns, ms) in enumerate([([15.0, 27.0, 36.0], 30.0), ([13.0, 25.0, 36.0], 50.0)]):
        base = tmp_path / f"reserve_es{seed}"
        base.mkdir()
        (base / "metrics.json").write_text(json.dumps({"learner": {"label": "reserve_es"}}))
        run = record("rollout", seed, returns, learner_cfg={"base": str(base)})
        run.metrics["eval"]["decision_time"] = {"ms_per_tick": ms, "total_s": ms, "ticks": 1000}
        planners.append(run)
    policies = collect_policies([*RUNS, *planners], STUDY)["system2"]
    learned = next(p for p in policies if p.name == "rollout [base=reserve_es]")
    assert learned.decision_ms == 40.0 and len(learned.means) == 2
    assert next(p for p in policies if p.name == "rollout").decision_ms is None
    md, files = write_section([*RUNS, *planners], tmp_path, STUDY, PROSE)
    rows = list(csv.DictReader(files["yardsticks"].open()))
    row = next(r for r in rows if r["policy"] == "rollout [base=reserve_es]")
    assert float(row["decision_ms_per_tick"]) == 40.0
    # per episode: mean of the seeds (14, 26, 36) - rollout's (14, 26, 36) = 0
    versus = next(
        r for r in rows if r["policy"] == "rollout [base=reserve_es]" and r["versus"] == "rollout"
    )
    assert float(versus["diff"]) == 0.0
    assert "| ms per tick |" in md and "| 40.0 |" in md


def test_the_decision_time_is_a_metric_of_the_long_table_and_runs_csv():
    rule, planner = record("team_reserve", 0, [11.0]), record("rollout", 0, [14.0])
    for run in (rule, planner):
        run.metrics["eval"].update(ctr_overall={}, ctr={}, itr={})
    planner.metrics["eval"]["decision_time"] = {"ms_per_tick": 12.5, "total_s": 25.0, "ticks": 2000}
    frame = long_table([rule, planner])
    rows = frame[frame["metric"] == "decision_time"]
    assert list(rows["run"]) == [1, 1, 1]  # the planner's only: the rule reports none
    assert dict(zip(rows["item"], rows["value"], strict=True)) == {
        "ms_per_tick": 12.5,
        "total_s": 25.0,
        "ticks": 2000,
    }
    wide = runs_wide(frame)
    assert wide.loc[1, "decision_time_ms_per_tick"] == 12.5


def random_team(run: RunRecord, m: int, team_seed: int, greedy: list[float]) -> RunRecord:
    """``run`` as played on the random team of ``m`` robots and team seed ``team_seed``."""
    metrics = json.loads(json.dumps(run.metrics))
    metrics["baseline_greedy"]["team_return"]["per_episode"] = greedy
    config = {**run.config, "system": {"name": "random", "n_robots": m, "seed": team_seed}}
    return dataclasses.replace(run, system="random", metrics=metrics, config=config)


def test_each_random_team_is_a_team_of_its_own_and_an_init_run_is_trained(tmp_path):
    """Random teams share the system name; each size and team seed has its own best rule."""
    family = tmp_path / "family"
    family.mkdir()
    (family / "metrics.json").write_text(json.dumps({"system": "family"}))
    runs = []
    for m, rule, greedy in ((10, [11.0, 22.0, 33.0], GREEDY), (200, [5.0, 6.0, 7.0], [4.0] * 3)):
        runs.append(random_team(record("team_reserve", 0, rule), m, 0, greedy))
        policy = record("reserve_es", 0, [x + 1 for x in rule], space={"analytic": 20})
        policy = dataclasses.replace(policy, config={"init": str(family)})
        runs.append(random_team(policy, m, 0, greedy))
    by_team = collect_policies(runs, STUDY)
    assert set(by_team) == {"random (10 robots, team seed 0)", "random (200 robots, team seed 0)"}
    for team, rule in (
        ("random (10 robots, team seed 0)", 22.0),
        ("random (200 robots, team seed 0)", 6.0),
    ):
        names = {p.name: p for p in by_team[team]}
        assert names[BEST_RESERVE].means == [pytest.approx(rule)]
        # played zero-shot (train.episodes=0) from a run trained on the family: a trained policy
        assert names["reserve-ES [init=family]"].kind == "trained"

"""The report section "Learning against the rules" (mrta_rl/reports/yardsticks.py), by hand."""

from __future__ import annotations

import csv
import dataclasses
from pathlib import Path

import numpy as np
import pytest

from mrta_rl.reports.collect import RunRecord
from mrta_rl.reports.stats import t_quantile
from mrta_rl.reports.yardsticks import BEST_RESERVE, collect_policies, section_rows, write_section

GREEDY = [10.0, 20.0, 30.0]  # per evaluation episode, shared by every run


def record(learner, seed, returns, *, episodes=0, space=None, learner_cfg=None):
    block = {"team_return": {"mean": float(np.mean(returns)), "per_episode": list(returns)}}
    greedy = {"team_return": {"mean": float(np.mean(GREEDY)), "per_episode": GREEDY}}
    metrics = {
        "learner": learner,
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
    policies = collect_policies(RUNS)["system2"]
    names = [p.name for p in policies]
    assert names[:3] == ["greedy", BEST_RESERVE, "rollout"]
    assert set(names[3:]) == {"subG-CQL", "subG-CQL untrained", "subG-CQL [time_to_free]"}
    best = policies[1]
    assert best.note == "reserve=0, hold_level=1"  # the better of the two settings (22 vs 20)
    trained = next(p for p in policies if p.name == "subG-CQL")
    np.testing.assert_array_equal(trained.per_episode, [12.0, 22.0, 33.0])  # mean of 2 seeds
    md, files = write_section(RUNS, tmp_path)
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


def test_no_section_without_rules_or_untrained_runs(tmp_path):
    md, files = write_section([RUNS[3], RUNS[4]], tmp_path)
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
    policies = collect_policies(runs)["system2"]
    assert [p.name for p in policies] == ["greedy", "CQL untrained", "CQL"]
    rows = [r for r in section_rows({"system2": policies}) if r[1] == "CQL"]
    assert rows[0][5] == "CQL untrained"
    assert rows[0][6] == pytest.approx(8 / 3, abs=1e-3)  # (13, 22, 33) - (10, 20, 30), rounded

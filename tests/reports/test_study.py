"""What a report makes of its runs is data: the report blocks of the experiments, and a template."""

from __future__ import annotations

import csv
import re
import subprocess
import sys
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from mrta_rl.config import ConfigError
from mrta_rl.reports import build_report
from mrta_rl.reports.study import Prose, study_of
from tests.reports.test_collect import write_run

ROOT = Path(__file__).resolve().parents[2]
CONF = ROOT / "conf"


def record_block(run_dir: Path, block: dict) -> None:
    """The run's config as an experiment with a ``report:`` block leaves it."""
    config = OmegaConf.load(run_dir / ".hydra" / "config.yaml")
    config.report = block
    OmegaConf.save(config, run_dir / ".hydra" / "config.yaml")


def test_the_shipped_study_is_the_experiments_report_blocks():
    """The README names net_es the best learner; the row order lists every neural learner."""
    study = study_of([])
    paper = OmegaConf.load(CONF / "experiment" / "paper.yaml").report
    assert study.learners == tuple(paper.learners)
    assert {"mappo", "ippo", "net_es"} <= set(study.learners)
    assert study.learners.index("iql") < study.learners.index("mappo")
    assert [c.id for c in study.claims] == [c.id for c in paper.claims]
    assert study.best_learner == "net_es" and study.rules == ("team_reserve", "rollout")
    assert list(study.along) == ["system.n_robots", "env.switch_ticks"]


def yardstick_runs(root: Path) -> list[Path]:
    """reserve_es and net_es (2 seeds each) trained, and a team_reserve rule."""
    runs = []
    for learner, returns in (("reserve_es", [110.0, 112.0]), ("net_es", [120.0, 118.0])):
        for seed, ret in enumerate(returns):
            space = {"analytic": 400} if learner == "reserve_es" else {"parameters": 90}
            run = write_run(root / f"{learner}{seed}", learner, seed, team_return=ret, space=space)
            runs.append(run)
    runs.append(write_run(root / "rule", "team_reserve", 0))
    return runs


def test_the_best_learner_and_the_row_order_of_a_recorded_block_come_first(tmp_path):
    """A sweep that recorded its own study (best learner reserve_es, team_reserve first)."""
    runs = yardstick_runs(tmp_path / "runs")
    text = build_report([tmp_path / "runs"], tmp_path / "shipped").report.read_text()
    assert "| vs net_es |" in text and "| vs reserve_es |" not in text
    ours = {"best_learner": "reserve_es", "learners": ["team_reserve", "reserve_es"]}
    for run in runs:
        record_block(run, ours)
    text = build_report([tmp_path / "runs"], tmp_path / "own").report.read_text()
    assert "| vs reserve_es |" in text and "| vs net_es |" not in text
    assert "the trained `reserve_es` runs" in text
    team_return = text[text.index("## Team return") : text.index("## Learning against")]
    rows = [line.split("|")[2].strip() for line in team_return.splitlines() if "System-I" in line]
    assert rows == ["team_reserve", "reserve_es", "net_es"]  # then the shipped order


def test_a_claim_is_data(tmp_path):
    """A claim a sweep recorded is checked beside the paper's, on its learners and values."""
    runs = yardstick_runs(tmp_path / "runs")
    claim = {
        "id": "net_es_beats_reserve_es",
        "statement": "net_es returns more than reserve_es",
        "check": "order",
        "values": {"team return": "team_return"},
        "order": ["net_es > reserve_es"],
    }
    for run in runs:
        record_block(run, {"claims": [claim]})
    files = build_report([tmp_path / "runs"], tmp_path / "report")
    with files.csvs["claims"].open() as handle:
        rows = {row["claim"]: row for row in csv.DictReader(handle)}
    row = rows["net_es_beats_reserve_es"]
    # means 119 and 111, each ± t(1) * sqrt(2) / sqrt(2) = 12.7: the intervals overlap
    assert (row["verdict"], row["separation"]) == ("holds", "CIs overlap")
    assert row["evidence"] == "team return: net_es 119.0 ± 12.7 > reserve_es 111.0 ± 12.7"
    assert "h_above_l" in rows  # the paper's claims too


@pytest.mark.parametrize(
    ("block", "culprit"),
    [
        ({"best_lerner": "x"}, "report.best_lerner: unknown setting"),
        ({"claims": [{"id": "a", "statement": "b", "check": "nope"}]}, "report.claims[0].check"),
        ({"claims": [{"id": "a", "statement": "b", "check": "gap"}]}, "check gap needs learners"),
        ({"along": {"x": {"label": "x"}}}, "report.along.x.stem: missing"),
    ],
)
def test_a_recorded_block_that_is_no_study_is_refused_naming_its_file(tmp_path, block, culprit):
    run = write_run(tmp_path / "run", "cql", 0)
    record_block(run, block)
    config = re.escape(str(run / ".hydra" / "config.yaml"))
    with pytest.raises(ConfigError, match=rf"{config}: .*{re.escape(culprit)}"):
        build_report([run], tmp_path / "report")
    assert not (tmp_path / "report").exists()  # nothing written


def test_the_command_refuses_a_broken_block_in_one_line(tmp_path):
    run = write_run(tmp_path / "run", "cql", 0)
    record_block(run, {"claims": [{"id": "a", "statement": "b", "check": "best", "group": "g"}]})
    done = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "report.py"), str(run)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 2 and "Traceback" not in done.stderr
    (line,) = done.stderr.strip().splitlines()
    assert line.startswith("error: ") and "check best needs learner, values" in line


def test_the_prose_is_the_template(tmp_path, monkeypatch):
    """report.md's text comes from conf/report/report.md, its blocks filled by name."""
    shipped = Prose.shipped()
    assert shipped.text("rules_title") == "Learning against the rules"
    assert shipped.text("expected", jobs=3, source="s", missing=1).startswith(" of 3 expected")
    edited = Prose(
        (CONF / "report" / "report.md")
        .read_text()
        .replace("## Setup", "## How the runs were set up")
    )
    monkeypatch.setattr(Prose, "shipped", classmethod(lambda cls: edited))
    write_run(tmp_path / "runs" / "a", "cql", 0)
    text = build_report([tmp_path / "runs"], tmp_path / "report").report.read_text()
    assert "## How the runs were set up" in text and "## Setup" not in text

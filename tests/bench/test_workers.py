"""The step-time model of ES on workers (mrta_rl/bench/workers.py), against hand-computed steps."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from mrta_rl.bench.workers import fit_model, format_model, read_result

# one worker: 24 members x 24 copies x 1,000 ticks at 288,000 copy-ticks/s play in 2.0 s; 1.25 MB
# of messages at 1 Gbit/s take 0.01 s, two messages 1 ms: the process's own work is 0.1 s
MEASURED = {
    "rates": {1: [1.0], 2: [1.9]},
    "ratios": {1: [1.0], 2: [1.9]},
    "step_s": {1: [2.111], 2: [1.2]},
    "worker_rate": {1: [288_000.0], 2: [288_000.0]},
    "bytes": {1: {"sent_per_step": 1_249_000, "received_per_step": 1_000, "team_recipe": 9}}
    | {2: {"sent_per_step": 2_498_000, "received_per_step": 2_000, "team_recipe": 9}},
    "members": 24,
    "copies": 24,
    "horizon": 1000,
}


def test_the_model_fits_the_one_worker_run_and_extends_it():
    model = fit_model(MEASURED)
    assert model.own_s == pytest.approx(0.1)
    assert model.step_s(1, 24) == pytest.approx(2.111)  # the measured point itself
    # 12 members each: 1.0 s of play, two workers' messages
    assert model.step_s(2, 24) == pytest.approx(0.1 + 1.0 + 2 * 0.011)
    # 24 members bound the useful workers: 1,000 workers act as 24
    assert model.step_s(1000, 24) == pytest.approx(0.1 + 24_000 / 288_000 + 24 * 0.011)
    # a member per worker: the messages, sent in turn, dominate
    assert model.step_s(1000, 1000) == pytest.approx(0.1 + 24_000 / 288_000 + 1000 * 0.011)


def test_a_saved_measurement_prints_its_tables(tmp_path):
    path = tmp_path / "bench_workers.json"
    path.write_text(json.dumps(MEASURED))  # JSON makes the worker counts strings
    table = format_model(read_result(path), (1, 2, 1000))
    assert " 1.200 (1.76x)" in table  # measured with 2 workers: 2.111 / 1.2
    assert "-" in table.splitlines()[-1]  # no measurement with 1,000 workers
    (tmp_path / "bad.json").write_text("{}")
    with pytest.raises(ValueError, match="bad.json: not a bench_workers measurement"):
        read_result(tmp_path / "bad.json")


def test_the_measurement_the_cluster_page_reports_reads():
    """docs/guide/cluster.md's tables come from this file (``--from``)."""
    docs = Path(__file__).resolve().parents[2] / "docs"
    path = docs / "results" / "cluster" / "bench_workers.json"
    result = read_result(path)
    assert result["members"] == 24 and result["copies"] == 24 and result["horizon"] == 1000
    assert min(result["ratios"][2]) >= 1.6  # the bar, measured alone on 2 cores
    assert "1.81x" in format_model(result, (1, 2))

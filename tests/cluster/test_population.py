"""An ES population on Ray workers (train.workers): a local multi-node Ray cluster of two worker
processes plays the members; the run ends bit-identical to the run in one process, a worker
killed during a step included; without Ray, train.workers is refused in one line."""

from __future__ import annotations

import contextlib
import json
import logging
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from mrta_rl.cluster import population
from mrta_rl.cluster.workers import WorkerFailure
from mrta_rl.reports import collect_runs
from mrta_rl.runners.train import train
from tests.conftest import compose_config
from tests.runners.test_checkpoint import resumed_run, save_hydra_files, script

ROOT = Path(__file__).resolve().parents[2]
TRAIN = ROOT / "scripts" / "train.py"
# 4 members (2 antithetic pairs) x 2 copies, 4 ES steps of 50 ticks
SMALL = ["debug=smoke", "train.episodes=4", "learner.pairs=2",
         "train.batch_size=8", "train.checkpoint_every=0"]  # fmt: skip

# a sitecustomize that makes ``ray`` unfindable, as where it is not installed
HIDE_RAY = """
import importlib.machinery, sys

class NoRay(importlib.machinery.PathFinder):
    @classmethod
    def find_spec(cls, name, path=None, target=None):
        if name == "ray" or name.startswith("ray."):
            return None
        return super().find_spec(name, path, target)

sys.meta_path = [NoRay if f is importlib.machinery.PathFinder else f for f in sys.meta_path]
"""


@pytest.fixture
def while_waiting(monkeypatch):
    """``while_waiting(act)``: ``act(pool)`` runs each time the ES pool waits for its workers
    (just after a step's chunks are submitted): the seam to kill workers during a step."""
    pools: list[population.PopulationWorkers] = []
    enter, wait_for = population.PopulationWorkers.__enter__, population.wait_for

    def keep(self):
        pools.append(self)
        return enter(self)

    def install(act):
        def waiting(refs):
            act(pools[-1])
            return wait_for(refs)

        monkeypatch.setattr(population.PopulationWorkers, "__enter__", keep)
        monkeypatch.setattr(population, "wait_for", waiting)

    return install


def run(tmp_path: Path, name: str, learner: str, *overrides: str) -> dict:
    """Train in this process; :func:`outputs` of the run."""
    cfg = compose_config([f"learner={learner}", *SMALL, *overrides])
    run_dir = tmp_path / name
    train(cfg, run_dir=run_dir)
    return outputs(run_dir)


def outputs(run_dir: Path) -> dict:
    """metrics.json, the weights and curve.csv of a finished run."""
    return {
        "metrics": json.loads((run_dir / "metrics.json").read_text()),
        "weights": next((run_dir / "learner").glob("*.npz")).read_bytes(),
        "curve": (run_dir / "curve.csv").read_text(),
    }


def train_script(*overrides: str, run_dir: Path, env: dict | None = None):
    """``scripts/train.py`` on a small net_es run of System-I in a new process."""
    return subprocess.run(
        [sys.executable, str(TRAIN), "learner=net_es", "system=system1", *SMALL, *overrides,
         f"hydra.run.dir={run_dir}"],
        capture_output=True, text=True, timeout=600, cwd=run_dir.parent,
        env=env or {**os.environ, "PYTHONPATH": str(ROOT)},
    )  # fmt: skip


def same_run(a: dict, b: dict) -> None:
    assert a["weights"] == b["weights"]
    assert a["curve"] == b["curve"]
    assert a["metrics"]["eval"] == b["metrics"]["eval"]


@pytest.mark.slow  # a Ray cluster starts in about 20 s on 2 cores
@pytest.mark.parametrize(
    ("learner", "system"),
    [("net_es", "system1"), ("reserve_es", "system1"), ("net_es", "family")],  # a team per step
)
def test_workers_end_bit_identical(cluster, tmp_path, learner, system):
    team = f"system={system}"
    alone = run(tmp_path, "alone", learner, team)
    at = f"train.ray_address={cluster.address}"
    one = run(tmp_path, "one", learner, team, "train.workers=1", at)
    two = run(tmp_path, "two", learner, team, "train.workers=2", at)
    same_run(alone, one)
    same_run(alone, two)
    assert "workers" not in alone["metrics"]["train"]
    record = two["metrics"]["train"]["workers"]
    # a report reads them as one run (workers change where it runs, not what), the others kept
    # as its duplicates
    collection = collect_runs([tmp_path])
    assert [run.run_dir.name for run in collection.runs] == ["alone"]
    assert sorted(run.run_dir.name for run in collection.duplicates) == ["one", "two"]
    assert record["count"] == 2 and record["nodes"] == 2  # one worker on each node
    assert record["retries"] == []
    # every step sends the population and the streams' start state, and gets returns back
    assert record["bytes"]["sent_per_step"] > record["bytes"]["received_per_step"] > 0


@pytest.mark.slow
def test_without_an_address_workers_start_a_ray_of_their_own_beside_a_running_one(
    cluster, tmp_path
):
    """The run is a new process (as a user's), on a machine where the test cluster runs: its
    own local instance, not the cluster it would have joined, and the run of no Ray."""
    assert cluster.address  # a Ray instance runs on this machine, which ray.init would join
    alone = run(tmp_path, "alone", "net_es", "system=system1")
    done = train_script("train.workers=2", run_dir=tmp_path / "local")
    assert done.returncode == 0, done.stderr[-2000:]
    local = outputs(tmp_path / "local")
    same_run(alone, local)
    record = local["metrics"]["train"]["workers"]
    assert record["address"] == "local" and record["count"] == 2 and record["nodes"] == 1


@pytest.mark.slow
def test_a_killed_worker_is_replaced_and_the_run_ends_the_same(
    cluster, tmp_path, while_waiting, caplog
):
    alone = run(tmp_path, "alone", "net_es", "system=system1")
    killed = []

    def kill_in_step_2(pool):
        if pool.steps == 2 and not killed:
            killed.append(pool.workers[1].pid)
            os.kill(pool.workers[1].pid, signal.SIGKILL)  # its chunk was just submitted

    while_waiting(kill_in_step_2)
    with caplog.at_level(logging.WARNING, logger=population.__name__):
        killed = run(
            tmp_path,
            "killed",
            "net_es",
            "system=system1",
            "train.workers=2",
            f"train.ray_address={cluster.address}",
        )
    same_run(alone, killed)
    retries = killed["metrics"]["train"]["workers"]["retries"]
    assert len(retries) == 1
    assert retries[0].startswith("worker 1 (pid ") and "lost in ES step 2" in retries[0]
    assert "members 2-3 re-run on worker 0" in retries[0]
    assert any("retry: worker 1" in record.getMessage() for record in caplog.records)


def test_without_ray_workers_are_refused_in_one_line(tmp_path):
    """Python started with Ray hidden from its import system stands for the base install without
    the extra: the refusal names the extra, and a run without workers trains."""
    site = tmp_path / "no_ray"
    site.mkdir()
    (site / "sitecustomize.py").write_text(HIDE_RAY)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(site), str(ROOT)])}
    refused = train_script("train.workers=2", run_dir=tmp_path / "refused", env=env)
    assert refused.returncode != 0
    lines = refused.stderr.strip().splitlines()
    assert lines == [
        "error: train.workers=2 needs Ray, which is not installed: pip install 'mrta_rl[cluster]'"
    ]
    assert not (tmp_path / "refused").exists()
    alone = train_script(run_dir=tmp_path / "alone", env=env)
    assert alone.returncode == 0, alone.stderr[-2000:]
    assert json.loads((tmp_path / "alone" / "metrics.json").read_text())["train"]["episodes"] == 4


def test_workers_are_refused_for_a_learner_without_a_population(compose_cfg, tmp_path):
    from mrta_rl.config import ConfigError

    cfg = compose_cfg(["learner=greedy", "system=system1", "debug=smoke", "train.workers=2"])
    with pytest.raises(ConfigError, match="train.workers: .* GreedyLearner spreads neither"):
        train(cfg, run_dir=tmp_path / "run")
    assert not (tmp_path / "run").exists()


@pytest.mark.slow
def test_a_worker_that_fails_for_good_stops_the_run_and_its_checkpoint_resumes(
    cluster, tmp_path, monkeypatch, while_waiting
):
    """Every worker is killed whenever step 2 waits: the chunk fails 3 times, the run stops with
    one line naming a worker, and the checkpoint of step 1 resumes to the run's own end."""
    alone = run(tmp_path, "alone", "net_es", "system=system1")

    def kill_all_in_step_2(pool):
        if pool.steps == 2:
            for worker in pool.workers:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(worker.pid, signal.SIGKILL)

    while_waiting(kill_all_in_step_2)
    at = f"train.ray_address={cluster.address}"
    every = [a for a in SMALL if not a.startswith("train.checkpoint_every")]
    args = ["learner=net_es", "system=system1", *every, "train.checkpoint_every=1"]
    cfg = compose_config([*args, "train.workers=2", at])
    save_hydra_files(cfg, tmp_path / "cut", "net_es", "system1")  # a run dir to resume
    with pytest.raises(WorkerFailure) as failure:
        train(cfg, run_dir=tmp_path / "cut")
    message = str(failure.value)
    assert "\n" not in message
    assert re.fullmatch(
        r"worker \d \(pid \d+ on .*\): members \d-\d of ES step 2 failed 3 times .*", message
    )
    monkeypatch.undo()
    resumed = script("scripts/train.py", f"resume={tmp_path / 'cut'}")
    assert resumed_run(resumed, tmp_path / "cut") == 1
    metrics = json.loads((tmp_path / "cut" / "metrics.json").read_text())
    assert metrics["eval"] == alone["metrics"]["eval"]
    assert (tmp_path / "cut" / "learner" / "net_es.npz").read_bytes() == alone["weights"]

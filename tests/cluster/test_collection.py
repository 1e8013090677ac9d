"""A torch learner's collection on Ray workers: two workers of a local multi-node cluster collect,
the run checkpoints, is killed, resumes in a new process and ends as the uninterrupted run."""

from __future__ import annotations

import json

import pytest

from mrta_rl.runners.train import train
from tests.conftest import compose_config
from tests.runners.test_checkpoint import (
    assert_same_learner_state,
    killed_at_checkpoint,
    resumed_run,
    script,
    without_timings,
)

RUN = ["learner=vdn", "system=system1", "debug=smoke", "train.episodes=8",
       "train.checkpoint_every=1", "train.workers=2"]  # fmt: skip


@pytest.mark.slow  # three processes start torch and join Ray
def test_collection_on_workers_checkpoints_and_resumes_in_a_new_process(cluster, tmp_path):
    args = [*RUN, f"train.ray_address={cluster.address}"]
    cut_dir, full_dir = tmp_path / "cut", tmp_path / "full"
    killed_after = killed_at_checkpoint(args, cut_dir, 3)
    resumed = script("scripts/train.py", f"resume={cut_dir}")
    assert killed_after <= resumed_run(resumed, cut_dir) < 8
    train(compose_config(args), run_dir=full_dir)
    # the same run: metrics (timings and the processes that ran it aside), curve and weights
    full, cut = (json.loads((d / "metrics.json").read_text()) for d in (full_dir, cut_dir))
    record = cut["train"].pop("workers")
    full["train"].pop("workers")
    assert without_timings(cut) == without_timings(full)
    assert (cut_dir / "curve.csv").read_text() == (full_dir / "curve.csv").read_text()
    assert_same_learner_state(full_dir, cut_dir)
    assert record["count"] == 2 and record["nodes"] == 2
    assert record["frames_per_s"][0] > 0 and record["frames_per_s"][1] > 0


def test_collection_on_workers_refuses_a_family_and_uneven_copies(compose_cfg, tmp_path):
    """Refused from the config alone, before the machine is asked for Ray (with or without it)."""
    from mrta_rl.config import ConfigError

    for overrides, match in [
        (["system=family", "learner.network=set"], "collection on workers plays one team"),
        (["system=system1", "train.batch_size=5"], "train.batch_size 5 must be a multiple of"),
        (["system=system1", "learner=expert_iteration"], "ExpertIteration.* spreads neither"),
    ]:
        cfg = compose_cfg(["learner=vdn", "debug=smoke", "train.workers=2", *overrides])
        with pytest.raises(ConfigError, match=match):
            train(cfg, run_dir=tmp_path / "run")
        assert not (tmp_path / "run").exists()

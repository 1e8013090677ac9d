"""The examples of docs/guide/cluster.md: the local cluster runs, the cluster files parse."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "examples"


@pytest.mark.slow
def test_the_local_cluster_example_runs(tmp_path):
    """docs/guide/cluster.md's example: a 2-node cluster on this machine, same weights."""
    pytest.importorskip("ray")
    done = subprocess.run(
        [sys.executable, str(EXAMPLES / "local_cluster.py"), "--out", str(tmp_path)],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.strip().endswith("2 workers and one process: same weights: True")
    assert (tmp_path / "workers" / "metrics.json").is_file()


def test_the_ray_cluster_file_names_what_ray_up_needs():
    config = yaml.safe_load((EXAMPLES / "ray_cluster.yaml").read_text())
    assert config["provider"]["type"] == "local"
    assert config["min_workers"] == config["max_workers"] == len(config["provider"]["worker_ips"])
    assert any("mrta_rl[cluster]" in command for command in config["setup_commands"])
    assert "ray start --head" in " ".join(config["head_start_ray_commands"])


def test_the_slurm_script_parses_and_joins_the_head():
    script = EXAMPLES / "ray_on_slurm.sh"
    assert subprocess.run(["bash", "-n", str(script)], capture_output=True).returncode == 0
    text = script.read_text()
    assert 'train.ray_address="$head_ip:$port"' in text and "train.workers=$workers" in text

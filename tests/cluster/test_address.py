"""``train.ray_address`` where no Ray cluster answers is refused at once, in one line, before the
run dir exists (``ray.init`` would retry it for minutes)."""

from __future__ import annotations

import socket
import subprocess
import sys
from pathlib import Path

import pytest

from mrta_rl.cluster import unreachable

ROOT = Path(__file__).resolve().parents[2]


def test_an_address_that_accepts_a_connection_may_be_joined():
    with socket.create_server(("127.0.0.1", 0)) as server:
        port = server.getsockname()[1]
        assert unreachable(f"127.0.0.1:{port}") is None
        assert unreachable(f"ray://127.0.0.1:{port}") is None  # Ray client's form


def test_a_closed_port_or_a_malformed_address_says_why():
    with socket.create_server(("127.0.0.1", 0)) as server:
        port = server.getsockname()[1]  # closed when the block ends: nothing listens on it
    assert unreachable(f"127.0.0.1:{port}").startswith(f"nothing answers at 127.0.0.1:{port} (")
    malformed = "not an address of the form host:port, ray://host:port or auto"
    assert unreachable("head-node") == unreachable("ray://head:port") == malformed


def test_the_script_refuses_it_in_one_line_and_leaves_no_run_dir(tmp_path):
    pytest.importorskip("ray")  # without it, the missing extra is refused first
    with socket.create_server(("127.0.0.1", 0)) as server:
        port = server.getsockname()[1]
    run_dir = tmp_path / "run"
    done = train_script(
        "learner=net_es",
        "system=system1",
        "debug=smoke",
        "train.workers=2",
        f"train.ray_address=127.0.0.1:{port}",
        run_dir=run_dir,
    )
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(
        f"error: train.ray_address=127.0.0.1:{port}: nothing answers at 127.0.0.1:{port} ("
    ), done.stderr[-2000:]
    assert not run_dir.exists()


def test_a_finished_run_of_a_cluster_that_is_gone_is_still_evaluated(tmp_path):
    """Whether workers can be had is asked of a run about to train, not of a saved config: a
    run trained on a cluster is re-evaluated (and serves as a base or a start) without it."""
    with socket.create_server(("127.0.0.1", 0)) as server:
        port = server.getsockname()[1]
    run_dir = tmp_path / "run"
    done = train_script("learner=net_es", "system=system1", "debug=smoke", run_dir=run_dir)
    assert done.returncode == 0, done.stderr[-2000:]
    config = run_dir / ".hydra" / "config.yaml"  # as the cluster's run wrote it
    text = config.read_text()
    assert "  workers: 0\n" in text and "  ray_address: null\n" in text
    text = text.replace("  workers: 0\n", "  workers: 2\n")
    config.write_text(text.replace("  ray_address: null\n", f"  ray_address: 127.0.0.1:{port}\n"))
    evaluated = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "evaluate.py"), f"checkpoint={run_dir}"],
        capture_output=True, text=True, timeout=300, cwd=tmp_path,
    )  # fmt: skip
    assert evaluated.returncode == 0, evaluated.stderr[-2000:]
    assert (run_dir / "eval_metrics.json").is_file()


def train_script(*args: str, run_dir: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "train.py"), *args, f"hydra.run.dir={run_dir}"],
        capture_output=True, text=True, timeout=300, cwd=run_dir.parent,
    )  # fmt: skip

"""Sweeps beyond one machine: submitit and Ray launchers run a small sweep (debug=smoke, 2 runs)
that scripts/report.py reads; the Slurm launcher config composes for a typical cluster."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from omegaconf import OmegaConf

ROOT = Path(__file__).resolve().parents[2]
TRAIN, REPORT = ROOT / "scripts" / "train.py", ROOT / "scripts" / "report.py"


def sweep_and_report(sweep_dir: Path, *overrides: str) -> str:
    """Run a 2-job sweep (greedy, random on System-I) with a launcher, then the report."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}  # the launched jobs import this checkout
    result = subprocess.run(
        [sys.executable, str(TRAIN), "-m", "debug=smoke", "learner=greedy,random",
         "system=system1", f"hydra.sweep.dir={sweep_dir}", *overrides],
        cwd=sweep_dir.parent, capture_output=True, text=True, timeout=600, env=env,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-3000:]
    assert sorted(p.parent.name for p in sweep_dir.glob("*/metrics.json")) == ["0", "1"]
    metrics = [json.loads(p.read_text()) for p in sweep_dir.glob("*/metrics.json")]
    learners = {m["learner"]["name"] for m in metrics}
    assert learners == {"greedy", "random"}
    done = subprocess.run(
        [sys.executable, str(REPORT), str(sweep_dir)],
        cwd=sweep_dir.parent, capture_output=True, text=True, timeout=300, env=env,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    assert "2 runs, 0 missing" in done.stdout
    report = (sweep_dir / "report" / "report.md").read_text()
    assert "IQM" in report
    return result.stdout + result.stderr


def test_submitit_local_sweep(tmp_path):
    pytest.importorskip("submitit")
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher")
    output = sweep_and_report(tmp_path / "sweep", "hydra/launcher=submitit_local")
    assert "Submitit 'local' sweep output dir" in output
    assert list((tmp_path / "sweep" / ".submitit").iterdir())  # the jobs went through submitit


@pytest.mark.slow  # starting and stopping Ray takes most of a minute on 2 cores
def test_ray_local_sweep(tmp_path):
    ray = pytest.importorskip("ray")
    pytest.importorskip("hydra_plugins.hydra_ray_launcher")
    output = sweep_and_report(
        tmp_path / "sweep",
        "hydra/launcher=ray_cluster",
        "hydra.launcher.ray.init.address=local",  # an instance of its own, beside any running one
        "+hydra.launcher.ray.init.num_cpus=2",
        "+hydra.launcher.ray.init.include_dashboard=false",
    )
    assert "Ray Launcher is launching 2 jobs" in output
    assert not ray.is_initialized()  # this process never joined it


@pytest.mark.parametrize(
    ("launcher", "target", "expected"),
    [
        ("slurm", "SlurmLauncher", {"mem_gb": 8, "cpus_per_task": 2, "timeout_min": 120}),
        ("ray_cluster", "RayLauncher", {"ray": {"init": {"address": "auto"},
                                                "remote": {"num_cpus": 1, "max_calls": 1}}}),
    ],
)  # fmt: skip
def test_launcher_configs_compose(launcher, target, expected):
    module = {"slurm": "hydra_plugins.hydra_submitit_launcher",
              "ray_cluster": "hydra_plugins.hydra_ray_launcher"}[launcher]  # fmt: skip
    pytest.importorskip(module)
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base=None):
        cfg = compose(
            "config",
            overrides=[f"hydra/launcher={launcher}", "hydra.sweep.dir=/x"],
            return_hydra_config=True,
        )
    GlobalHydra.instance().clear()
    plain = OmegaConf.to_container(cfg.hydra.launcher, resolve=False)
    assert plain["_target_"].endswith(target)
    assert contains(plain, expected)


def contains(tree: dict, expected: dict) -> bool:
    """Every key of ``expected`` (nested) has the same value in ``tree``."""
    return all(
        contains(tree.get(k) or {}, v) if isinstance(v, dict) else tree.get(k) == v
        for k, v in expected.items()
    )

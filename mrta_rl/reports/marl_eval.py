"""The runs as the JSON file that marl-eval reads, and that BenchMARL and Mava write.

``{env: {task: {algorithm: {"seed_<seed>": {"step_0": {"step_count": ..., "return": [...]},
"absolute_metrics": {"return": [...]}}}}}}``: the env is the auction (:data:`ENV_NAME`), a task
is a system, an algorithm is a learner configuration (``subg_cql``, ``subg_reserve reserve=1``)
and each run seed holds its evaluation: the team return of every evaluation episode
(``team_return.per_episode`` of metrics.json, or its mean for a run without it), after
``step_count`` training env ticks. A run is evaluated once, at the end of its training, so that
evaluation is both its one step and its absolute metric.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from mrta_rl.reports.collect import RunRecord

ENV_NAME = "auction"
METRIC = "return"  # marl-eval's name of the episode return
FILE = "marl_eval.json"


def marl_eval_data(runs: Sequence[RunRecord]) -> dict[str, Any]:
    """The marl-eval structure of the runs (module docstring)."""
    data: dict[str, Any] = {}
    for run in runs:
        returns = run.metrics["eval"]["team_return"]
        episodes = returns.get("per_episode") or [returns["mean"]]
        ticks = int((run.metrics.get("train") or {}).get("env_ticks", 0))
        tasks = data.setdefault(ENV_NAME, {}).setdefault(run.system, {})
        tasks.setdefault(run.learner, {})[f"seed_{run.seed}"] = {
            "step_0": {"step_count": ticks, METRIC: list(episodes)},
            "absolute_metrics": {METRIC: list(episodes)},
        }
    return data


def write_marl_eval(runs: Sequence[RunRecord], out_dir: Path) -> Path:
    """Write :data:`FILE` in ``out_dir``; returns its path."""
    path = out_dir / FILE
    path.write_text(json.dumps(marl_eval_data(runs), indent=2))
    return path

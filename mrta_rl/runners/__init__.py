"""Runners: wire config, env and learner together; train, evaluate and summarize a run."""

from __future__ import annotations

from mrta_rl.runners.evaluate import (
    evaluate_checkpoint,
    evaluate_policy,
    evaluate_run,
    format_summary,
)
from mrta_rl.runners.train import TRAINING_LOOPS, RunSetup, build_run, train

__all__ = [
    "TRAINING_LOOPS",
    "RunSetup",
    "build_run",
    "evaluate_checkpoint",
    "evaluate_policy",
    "evaluate_run",
    "format_summary",
    "train",
]

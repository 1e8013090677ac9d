"""Runners: wire config, env and learner together; train, evaluate and summarize a run."""

from __future__ import annotations

from mrta_rl.config_guard import guard_config_files
from mrta_rl.runners.evaluate import evaluate_policy, evaluate_run, format_summary
from mrta_rl.runners.run_config import register_resolvers
from mrta_rl.runners.run_setup import RunSetup
from mrta_rl.runners.train import build_run, evaluate_checkpoint, train
from mrta_rl.runners.validation import validate_config

register_resolvers()  # before Hydra composes conf/config.yaml (run dirs, see checkpoint.py)
guard_config_files()  # before Hydra reads a config file: size, encoding, depth, aliases

__all__ = [
    "RunSetup",
    "build_run",
    "evaluate_checkpoint",
    "evaluate_policy",
    "evaluate_run",
    "format_summary",
    "train",
    "validate_config",
]

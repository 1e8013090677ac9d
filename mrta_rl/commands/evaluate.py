"""``mrta-evaluate``: re-evaluate a finished training run, write eval_metrics.json in its run dir.

Usage: ``mrta-evaluate checkpoint=outputs/<date>/<time>_<learner>_<id> [episodes=50]
[batch_size=50] [eval.split=validation]`` (or ``python scripts/evaluate.py ...``).
The run dir is read as data (``mrta_rl/runners/checkpoint.py``): a tampered config or damaged
tables are refused with a message naming the key or file.
"""

from __future__ import annotations

import hydra
from omegaconf import DictConfig

from mrta_rl.conf_paths import conf_dir
from mrta_rl.runners import cli, evaluate_checkpoint, format_summary
from mrta_rl.runners.validation import check_evaluate_config


@hydra.main(config_path=str(conf_dir()), config_name="evaluate", version_base=None)
@cli.job
def _task(cfg: DictConfig) -> None:
    args = check_evaluate_config(cfg)
    metrics = evaluate_checkpoint(
        hydra.utils.to_absolute_path(args["checkpoint"]),
        args["episodes"],
        args["batch_size"],
        args["split"],
    )
    print(format_summary(metrics))


def main() -> None:
    """Run the command with the overrides of the command line."""
    cli.run(_task)

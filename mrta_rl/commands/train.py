"""``mrta-train``: train one learner on one system, evaluate it against the greedy auction.

Usage: ``mrta-train learner=greedy system=system1 eval.episodes=20 seed=3`` (or
``python scripts/train.py ...``; see conf/config.yaml; ``debug=smoke`` for a seconds-long run;
``system=/path/to/team.yaml`` for a team of your own). Results go to the Hydra run dir
(``outputs/<date>/<time>_<learner>_<id>`` under the working directory): metrics.json,
curve.csv, learner/ (state of trained learners), .hydra/ (the config) and, while training,
checkpoint/. Continue an interrupted run with ``mrta-train resume=<run dir>``.
"""

from __future__ import annotations

import hydra
from omegaconf import DictConfig

from mrta_rl.commands import use_team_files
from mrta_rl.conf_paths import conf_dir
from mrta_rl.runners import cli, format_summary, train


@hydra.main(config_path=str(conf_dir()), config_name="config", version_base=None)
@cli.job
def _task(cfg: DictConfig) -> None:
    print(format_summary(train(cfg)))


def _start() -> None:
    use_team_files()
    _task()


def main() -> None:
    """Run the command with the overrides of the command line."""
    cli.run(_start)

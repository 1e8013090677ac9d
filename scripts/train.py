"""Train one learner on one system, evaluate it against the greedy auction, print a summary.

Usage: ``python scripts/train.py learner=greedy system=system1 eval.episodes=20 seed=3``
(see conf/config.yaml; ``debug=smoke`` for a seconds-long run). Results go to the Hydra run dir
(``outputs/<date>/<time>_<learner>_<id>``): metrics.json, curve.csv, learner/ (state of trained
learners), .hydra/ (the config) and, while training, checkpoint/. Continue an interrupted run
with ``python scripts/train.py resume=<run dir>``.
"""

from __future__ import annotations

import hydra
from omegaconf import DictConfig

from mrta_rl.runners import cli, format_summary, train


@hydra.main(config_path="../conf", config_name="config", version_base=None)
@cli.job
def main(cfg: DictConfig) -> None:
    print(format_summary(train(cfg)))


if __name__ == "__main__":
    cli.run(main)

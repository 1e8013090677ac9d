"""Re-evaluate a finished training run and write eval_metrics.json in its run dir.

Usage: ``python scripts/evaluate.py checkpoint=outputs/<date>/<time> [episodes=50]``.
"""

from __future__ import annotations

import hydra
from omegaconf import DictConfig

from mrta_rl.runners import evaluate_checkpoint, format_summary


@hydra.main(config_path="../conf", config_name="evaluate", version_base=None)
def main(cfg: DictConfig) -> None:
    metrics = evaluate_checkpoint(hydra.utils.to_absolute_path(cfg.checkpoint), cfg.episodes)
    print(format_summary(metrics))


if __name__ == "__main__":
    main()

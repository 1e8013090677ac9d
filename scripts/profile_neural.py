"""Where the wall time of a neural training run goes: collection, training, evaluation (issue 13).

Usage: ``python scripts/profile_neural.py learner=qmix system=system2`` (any ``scripts/train.py``
overrides; e.g. ``env.horizon=100`` scales every part of the default run by 1/10). Trains and
evaluates exactly as ``scripts/train.py`` (same run dir outputs), with wall-clock timers around
the parts (``mrta_rl/runners/neural_profile.py``), and prints seconds and shares per part.
"""

from __future__ import annotations

from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from mrta_rl.bench.neural_profile import format_profile, profile_run
from mrta_rl.runners import cli


@hydra.main(config_path="../conf", config_name="config", version_base=None)
@cli.job
def main(cfg: DictConfig) -> None:
    _, rows = profile_run(cfg, Path(HydraConfig.get().runtime.output_dir))
    print(format_profile(rows))


if __name__ == "__main__":
    cli.run(main)

"""``mrta-partition``: print the subG-CQL partition (paper §4) of a system.

Usage: ``mrta-partition system=system1 [format=json] [partition.max_group_size=4]`` (or
``python scripts/partition.py ...``; ``system=/path/to/team.yaml`` for a team of your own).
"""

from __future__ import annotations

import json

import hydra
from omegaconf import DictConfig, OmegaConf

from mrta_rl.commands import use_team_files
from mrta_rl.conf_files import conf_dir
from mrta_rl.config import ConfigError
from mrta_rl.partition import format_partition, subg_partition
from mrta_rl.runners import cli
from mrta_rl.systems import build_system


@hydra.main(config_path=str(conf_dir()), config_name="partition", version_base=None)
@cli.job
def _task(cfg: DictConfig) -> None:
    system = build_system(OmegaConf.to_container(cfg.system, resolve=True))
    partition = subg_partition(system, cfg.partition.max_group_size)
    if cfg.format == "json":
        print(json.dumps(partition.to_json()))
    elif cfg.format == "table":
        print(format_partition(partition))
    else:
        raise ConfigError(f"format: must be 'table' or 'json', got {cfg.format!r}")


def _start() -> None:
    use_team_files()
    _task()


def main() -> None:
    """Run the command with the overrides of the command line."""
    cli.run(_start)

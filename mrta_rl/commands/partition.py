"""``mrta-partition``: print the subG-CQL partition (paper §4) of a system.

Usage: ``mrta-partition system=system1 [format=json] [partition.max_group_size=4]`` (or
``python scripts/partition.py ...``; ``system=/path/to/team.yaml`` for a team of your own).
The arguments and the team are checked as training checks them (``runners/validation.py``:
the settings, the team-size limits), before the partition is computed.
"""

from __future__ import annotations

import json
from typing import Any

import hydra
from omegaconf import DictConfig

from mrta_rl.commands import use_team_files
from mrta_rl.conf_paths import conf_dir
from mrta_rl.partition import format_partition, subg_partition
from mrta_rl.runners import cli
from mrta_rl.runners.validation import check_partition_config, checked_team, memory_limit
from mrta_rl.systems import RobotSystem


@hydra.main(config_path=str(conf_dir()), config_name="partition", version_base=None)
@cli.job
def _task(cfg: DictConfig) -> None:
    args = check_partition_config(cfg)
    system = _team(args["system"])
    partition = subg_partition(system, args["max_group_size"])
    if args["format"] == "json":
        print(json.dumps(partition.to_json()))
    else:
        print(format_partition(partition))


def _team(system_cfg: Any) -> RobotSystem:
    """The team, refused before it is built if training would refuse its size (no env copies)."""
    return checked_team(system_cfg, memory_limit({}), env_overrides={})[2]


def _start() -> None:
    use_team_files(check=_team)  # a team file: before Hydra composes it
    _task()


def main() -> None:
    """Run the command with the overrides of the command line."""
    cli.run(_start)

"""Print the Table-9 analogue: learning space dimension of every tabular learner per system.

Usage: ``python scripts/learning_space.py`` (System-I and System-II of ``conf/system/``).
"""

from __future__ import annotations

from pathlib import Path

from omegaconf import OmegaConf

from mrta_rl.learners.registry import learning_space_table
from mrta_rl.metrics.learning_space import format_learning_space_table
from mrta_rl.runners import cli
from mrta_rl.systems import build_system

SYSTEMS = ("system1", "system2")
CONF = Path(__file__).resolve().parents[1] / "conf" / "system"


def main() -> None:
    tables = {}
    for name in SYSTEMS:
        system = build_system(OmegaConf.to_container(OmegaConf.load(CONF / f"{name}.yaml")))
        tables[name] = learning_space_table(system)
    print(format_learning_space_table(tables))


if __name__ == "__main__":
    cli.run(main)

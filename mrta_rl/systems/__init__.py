"""Robot systems (paper Tables 1-2): robots, their task sets and willingness."""

from __future__ import annotations

from mrta_rl.systems.build import build_system, system_shape
from mrta_rl.systems.robot_system import (
    MAX_PAIRS,
    DurationRange,
    RobotSystem,
    SystemConfigError,
    natural_key,
    random_system,
)

__all__ = [
    "MAX_PAIRS",
    "DurationRange",
    "RobotSystem",
    "SystemConfigError",
    "build_system",
    "natural_key",
    "random_system",
    "system_shape",
]

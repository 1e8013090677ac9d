"""Robot systems (paper Tables 1-2): robots, their task sets and willingness."""

from __future__ import annotations

from mrta_rl.systems.robot_system import (
    DurationRange,
    RobotSystem,
    SystemConfigError,
    build_system,
    natural_key,
    random_system,
)

__all__ = [
    "DurationRange",
    "RobotSystem",
    "SystemConfigError",
    "build_system",
    "natural_key",
    "random_system",
]

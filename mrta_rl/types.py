"""Shared type aliases: paper identifiers (R1, T1, L/H, G1), group maps, and their sort order."""

from __future__ import annotations

import re
from typing import Literal

RobotId = str  # "R1", "R2", ... (paper: R_i)
TaskType = str  # "T1", "T2", ... (paper: T_j)
GroupName = str  # "G1", "G2", ... (paper: sub-group L_g)
Priority = Literal["L", "H"]
GroupMap = dict[GroupName, list[RobotId]]  # TorchRL group_map: group -> robots

PRIORITIES: tuple[Priority, Priority] = ("L", "H")  # index 0 = low, 1 = high


def natural_key(name: str) -> tuple[tuple[int, int, str], ...]:
    """Sort key of a name with its digit runs compared as numbers (``T2`` < ``T10``)."""
    return tuple(
        (0, int(part), "") if part.isdigit() else (1, 0, part)
        for part in re.split(r"(\d+)", name)
        if part
    )

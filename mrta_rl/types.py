"""Shared type aliases: paper identifiers (R1, T1, L/H, G1) and group maps."""

from __future__ import annotations

from typing import Literal

RobotId = str  # "R1", "R2", ... (paper: R_i)
TaskType = str  # "T1", "T2", ... (paper: T_j)
GroupName = str  # "G1", "G2", ... (paper: sub-group L_g)
Priority = Literal["L", "H"]
GroupMap = dict[GroupName, list[RobotId]]  # TorchRL group_map: group -> robots

PRIORITIES: tuple[Priority, Priority] = ("L", "H")  # index 0 = low, 1 = high

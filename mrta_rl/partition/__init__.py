"""subG-CQL partition of a robot system into independent sub-groups (paper §4)."""

from __future__ import annotations

from mrta_rl.partition.subg import Partition, format_partition, partition_matrices, subg_partition

__all__ = ["Partition", "format_partition", "partition_matrices", "subg_partition"]

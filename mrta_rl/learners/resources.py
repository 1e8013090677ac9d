"""What a learner's memory estimate is asked and what it answers, before the learner is built.

:class:`MemoryQuery` is what a learner class's ``estimate_memory`` is given (``learners/base.py``)
and :class:`ResourceEstimate` what it returns; :func:`~mrta_rl.learners.memory.estimate_resources`
asks every class through them. They live here, apart from both, so that the learner base and the
estimates' helpers (``learners/memory.py``) import this module and not each other.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, NamedTuple

from mrta_rl.envs import AuctionEnv
from mrta_rl.partition import Partition


class MemoryQuery(NamedTuple):
    """What a learner's memory estimate depends on, asked before the learner is built."""

    env: AuctionEnv  # a probe env of the run's team and parameters
    partition: Partition | None  # the subG partition, for learners that need one
    settings: dict[str, Any]  # the learner's hyperparameters from the run config
    decisions: int  # copy-ticks of training: the most states a table can meet
    copies: int  # training copies (collector batch of the neural learners); 0: it only plays


@dataclass(frozen=True)
class ResourceEstimate:
    """What a learner needs on a system (``learners/memory.py``'s module docstring).

    Attributes:
        learner: Class name.
        up_front: Bytes the learner takes for sure.
        worst: Upper bound of the bytes, tables grown to every state they could meet.
        parts: Bytes by part (``"G1 table"``, ``"replay buffer"``, ``"networks"``...), worst case.
        per_copy: Bytes each env copy of a tick takes up front, by part (``"G1 row (44,001
            joint actions)"``); :func:`~mrta_rl.learners.memory.estimate_resources` counts them
            for the most copies that play one tick, training's or evaluation's.
        up_front_parts: ``up_front`` by part where it is not ``parts`` (set with ``per_copy``
            by :func:`~mrta_rl.learners.memory.estimate_resources`); empty: ``parts``.
        reason: Why the learner cannot run at all (e.g. joint actions beyond int64), else None.
        advice: What to change, for the messages.
    """

    learner: str
    up_front: int = 0
    worst: int = 0
    parts: dict[str, int] = field(default_factory=dict)
    per_copy: dict[str, int] = field(default_factory=dict)
    up_front_parts: dict[str, int] = field(default_factory=dict)
    reason: str | None = None
    advice: str = ""

    def refusal(self, limit_bytes: int) -> str | None:
        """Why the run must not start under a memory limit, or None if it may.

        Args:
            limit_bytes: The memory allowed.

        Returns:
            The reason (what is too big), without advice, or None.
        """
        if self.reason is not None:
            return self.reason
        if self.up_front > limit_bytes:
            parts = self.up_front_parts or self.parts
            biggest = sorted(parts.items(), key=lambda kv: -kv[1])[:3]
            detail = ", ".join(f"{name} {format_bytes(b)}" for name, b in biggest)
            return (
                f"needs about {format_bytes(self.up_front)} up front ({detail}), more than the "
                f"limit of {format_bytes(limit_bytes)}"
            )
        return None


def format_bytes(n: float) -> str:
    """``1.5 GB``, ``12 MB``: decimal units, three significant digits."""
    for unit, size in (("TB", 1e12), ("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= size:
            return f"{n / size:.3g} {unit}"
    return f"{int(n)} B"

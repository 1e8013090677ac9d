"""A logger of one's own: the curve rows also as JSON lines, beside curve.csv and the tracker.

A run's logger is a :class:`~mrta_rl.metrics.run_logger.RunLogger` (the runner's checkpoints and
reports read its curve.csv), so a new one extends it: it takes the same settings and adds what it
does with each row.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from typing import Any

from mrta_rl.metrics.run_logger import RunLogger

JSONL_FILE = "curve.jsonl"


class JsonLinesLogger(RunLogger):
    """curve.csv and the tracker as :class:`RunLogger`, and ``curve.jsonl``, one row a line."""

    def __init__(self, **settings: Any) -> None:
        super().__init__(**settings)
        self._lines = (self.path.parent / JSONL_FILE).open("w")

    def log(self, row: Mapping[str, float | int]) -> None:
        """Write the row to curve.csv and the tracker, then as one JSON line."""
        super().log(row)
        self._lines.write(json.dumps(dict(row)) + "\n")
        self._lines.flush()

    def close(self) -> None:
        """Close curve.csv and curve.jsonl."""
        super().close()
        self._lines.close()

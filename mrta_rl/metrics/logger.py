"""Training-curve logging: CSV in the run dir (TensorBoard or W&B can be added as other loggers).

A logger is built from ``conf/logger/<name>.yaml`` (``_partial_: true``) by the runner, which
supplies the run dir, and receives one row per training episode.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from types import TracebackType

CURVE_COLUMNS = ("env_ticks", "episode", "team_return_mean")  # the columns every runner writes


class CSVLogger:
    """Append rows of scalars to ``<run_dir>/<filename>``, flushed after every row.

    Used as a context manager, the file is closed even if training fails; the rows written so far
    stay readable.
    """

    def __init__(
        self, *, run_dir: Path, filename: str = "curve.csv", columns: Sequence[str] = CURVE_COLUMNS
    ) -> None:
        """Open the file and write the header.

        Args:
            run_dir: The run's output directory (created if missing).
            filename: File name inside ``run_dir``.
            columns: Column names, in order; every row must give exactly these keys.
        """
        self.path = Path(run_dir) / filename
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.columns = tuple(columns)
        self._file = self.path.open("w", newline="")
        self._writer = csv.writer(self._file)
        self._writer.writerow(self.columns)
        self._file.flush()

    def log(self, row: Mapping[str, float | int]) -> None:
        """Write one row.

        Args:
            row: Column name -> value; NaN is written as an empty field.

        Raises:
            ValueError: if the keys differ from the columns.
        """
        if set(row) != set(self.columns):
            raise ValueError(f"row keys {sorted(row)} differ from the columns {list(self.columns)}")
        values = [row[c] for c in self.columns]
        self._writer.writerow(["" if isinstance(v, float) and math.isnan(v) else v for v in values])
        self._file.flush()

    def close(self) -> None:
        """Close the file (idempotent)."""
        if not self._file.closed:
            self._file.close()

    def __enter__(self) -> CSVLogger:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self.close()

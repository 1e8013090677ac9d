"""Run logging: the training curve as curve.csv, and every scalar to a TorchRL logger.

A logger is built from ``conf/logger/<name>.yaml`` (``_partial_: true``) by the runner, which
supplies the run dir, and receives one row per training episode. Two outputs:

* **curve.csv** in the run dir (columns :data:`CURVE_COLUMNS`), the file the reports and a
  resumed run read. It stays this module's own writer: TorchRL's ``CSVLogger`` writes one file
  per scalar (``step,value``), which cannot hold an episode's row.
* **A tracker**: one of TorchRL's loggers (``torchrl.record.loggers``), chosen by ``backend``:
  ``csv`` (TorchRL's scalar files under ``<run dir>/torchrl``), ``tensorboard``, ``wandb``
  (offline: ``WANDB_MODE=offline``, a run under ``<run dir>/wandb``, which ``wandb sync``
  uploads later) or ``mlflow`` (a file store in the run dir, tracking uri
  ``file:<run dir>/mlruns``).
  None needs a network. It gets the curve (``train/team_return``), what the training loop adds
  through :attr:`RunLogger.torchrl_logger` (the neural runner: losses, epsilon, frames per
  second; the tabular runner: epsilon) and, from :func:`finish_run`, the run's final metrics
  (evaluation, training speed, resources) under their ``metrics.json`` paths
  (``eval/team_return/mean``).

The training loop closes its logger when it ends, which closes curve.csv; the tracker of the run
dir stays open in this process until :func:`finish_run` logs the final metrics and shuts it
down, so the evaluation lands in the same tracker run as the curve.
"""

from __future__ import annotations

import csv
import hashlib
import logging
import math
import numbers
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from types import TracebackType
from typing import Any, Literal

CURVE_COLUMNS = ("env_ticks", "episode", "team_return_mean")  # the columns every runner writes
Backend = Literal["csv", "tensorboard", "wandb", "mlflow"]
EXPERIMENT = "train"  # TorchRL's exp_name: the tracker run's name
# a tracker keeps a file or a series per scalar: a block with more keys than this (the ITR of
# each robot of a 1,000-robot team) stays in metrics.json alone
MAX_BLOCK_SCALARS = 256
logger = logging.getLogger(__name__)
_TRACKERS: dict[Path, Any] = {}  # run dir -> its open TorchRL logger (module docstring)


class RunLogger:
    """curve.csv in the run dir, flushed after every row, and the run's TorchRL logger.

    Used as a context manager, curve.csv is closed even if training fails; the rows written so
    far stay readable.

    Attributes:
        torchrl_logger: The run's TorchRL logger: training loops log their scalars there.
    """

    def __init__(
        self,
        *,
        run_dir: Path,
        filename: str = "curve.csv",
        backend: Backend = "csv",
        log_dir: str = "torchrl",
        project: str = "mrta_rl",
        columns: Sequence[str] = CURVE_COLUMNS,
    ) -> None:
        """Open curve.csv, write the header, and open (or join) the run dir's tracker.

        Args:
            run_dir: The run's output directory (created if missing).
            filename: Curve file name inside ``run_dir``.
            backend: The TorchRL logger (module docstring).
            log_dir: The tracker's folder inside ``run_dir``.
            project: The W&B project or MLflow experiment the run belongs to.
            columns: Column names, in order; every row must give exactly these keys.
        """
        self.path = Path(run_dir) / filename
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.columns = tuple(columns)
        self.torchrl_logger = open_tracker(Path(run_dir), backend, log_dir, project)
        self._file = self.path.open("w", newline="")
        self._writer = csv.writer(self._file)
        self._writer.writerow(self.columns)
        self._file.flush()

    def log(self, row: Mapping[str, float | int]) -> None:
        """Write one row; its team return also goes to the tracker (step = env ticks).

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
        if "team_return_mean" in row and "env_ticks" in row:
            step = int(row["env_ticks"])
            self.torchrl_logger.log_scalar(
                "train/team_return", float(row["team_return_mean"]), step=step
            )
            if "episode" in row:
                self.torchrl_logger.log_scalar("train/episode", float(row["episode"]), step=step)

    def close(self) -> None:
        """Close curve.csv (idempotent); the tracker stays open for :func:`finish_run`."""
        if not self._file.closed:
            self._file.close()

    def __enter__(self) -> RunLogger:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self.close()


def open_tracker(run_dir: Path, backend: Backend, log_dir: str, project: str) -> Any:
    """The TorchRL logger of ``run_dir``: the one open in this process, else a new one.

    Opening the tracker of another run dir shuts down the one still open.

    Args:
        run_dir: The run's output directory.
        backend: ``csv``, ``tensorboard``, ``wandb`` or ``mlflow``.
        log_dir: The tracker's folder inside ``run_dir``.
        project: The W&B project or MLflow experiment.

    Returns:
        A ``torchrl.record.loggers.Logger``.

    Raises:
        ValueError: for an unknown backend.
    """
    key = Path(run_dir).resolve()
    if key in _TRACKERS:
        return _TRACKERS[key]
    # W&B and MLflow have one active run per process: a run dir left unfinished (a loop that
    # failed, a benchmark's run, a test) is shut down before the next one starts
    for other in list(_TRACKERS):
        _shutdown(_TRACKERS.pop(other))
    folder = key / log_dir
    if backend == "csv":
        from torchrl.record.loggers import CSVLogger as TorchRLCSVLogger

        tracker = TorchRLCSVLogger(exp_name=EXPERIMENT, log_dir=str(folder))
    elif backend == "tensorboard":
        from torchrl.record.loggers import TensorboardLogger

        tracker = TensorboardLogger(exp_name=EXPERIMENT, log_dir=str(folder))
    elif backend == "wandb":
        from torchrl.record.loggers import WandbLogger

        os.environ["WANDB_MODE"] = "offline"  # no network: `wandb sync` uploads the files later
        tracker = WandbLogger(
            exp_name=run_name(key),
            # one id per run dir: a resumed run continues its W&B run ("resume": "allow")
            id=hashlib.sha1(str(key).encode()).hexdigest()[:16],
            offline=True,
            save_dir=str(folder),
            project=project,
            log_env_packages=False,
            mode="offline",
            settings={"console": "off", "silent": True},  # the run dir's log has the output
        )
    elif backend == "mlflow":
        from torchrl.record.loggers import MLFlowLogger

        # MLflow 3 keeps the file store (no database, no server) behind this switch
        os.environ["MLFLOW_ALLOW_FILE_STORE"] = "true"
        import mlflow

        tracker = MLFlowLogger(exp_name=project, tracking_uri=folder.as_uri())
        mlflow.set_tag("mlflow.runName", run_name(key))  # TorchRL starts the run unnamed
    else:
        raise ValueError(
            f"logger.backend: must be csv, tensorboard, wandb or mlflow, got {backend}"
        )
    _TRACKERS[key] = tracker
    return tracker


def run_name(run_dir: Path) -> str:
    """The tracker run's name: the run dir's, with its sweep's for a sweep job (``<sweep>/3``)."""
    return "/".join(run_dir.parts[-2:]) if run_dir.name.isdigit() else run_dir.name


def final_scalars(metrics: Mapping[str, Any]) -> dict[str, float]:
    """The numbers of ``metrics.json`` under their slash paths (lists and labels left out).

    Args:
        metrics: The run's metrics (``runners/train.py``).

    Returns:
        ``{"eval/team_return/mean": ..., "train/fps": ...}``: every finite number, plus the
        training's copy-ticks per second (``train/fps``) when it trained. A block of more than
        :data:`MAX_BLOCK_SCALARS` keys (the ITR of each robot of a large team) is left out.
    """
    out: dict[str, float] = {}

    def walk(value: Any, path: str) -> None:
        if isinstance(value, Mapping):
            if len(value) > MAX_BLOCK_SCALARS:
                logger.info(
                    "tracker: %s holds %s values, left out (they are in metrics.json)",
                    path,
                    f"{len(value):,}",
                )
                return
            for key, item in value.items():
                walk(item, f"{path}/{key}" if path else str(key))
        elif isinstance(value, numbers.Real) and not isinstance(value, bool):
            if math.isfinite(value):
                out[path] = float(value)

    walk({k: v for k, v in metrics.items() if k != "seed"}, "")
    train = metrics.get("train", {})
    if train.get("wall_s") and train.get("env_ticks"):
        out["train/fps"] = train["env_ticks"] / train["wall_s"]
    return out


def finish_run(run_dir: Path, metrics: Mapping[str, Any]) -> None:
    """Log the run's final metrics to its tracker and shut the tracker down.

    Args:
        run_dir: The run's output directory.
        metrics: The content of ``metrics.json``.
    """
    tracker = _TRACKERS.pop(Path(run_dir).resolve(), None)
    if tracker is None:  # the training loop opens it; a loop that failed leaves nothing to finish
        return
    step = int(metrics.get("train", {}).get("env_ticks", 0))
    for name, value in final_scalars(metrics).items():
        tracker.log_scalar(name, value, step=step)
    _shutdown(tracker)


def _shutdown(tracker: Any) -> None:
    """Flush and close a TorchRL logger, and end its MLflow run (TorchRL's shutdown does not)."""
    tracker.shutdown()
    if type(tracker).__name__ == "MLFlowLogger":
        import mlflow

        mlflow.end_run()

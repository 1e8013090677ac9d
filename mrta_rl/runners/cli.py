"""How the scripts end: one clear message for a user error, exit codes, no half-made run dir.

Every script in ``scripts/`` is a thin entry point::

    @hydra.main(config_path="../conf", config_name="config", version_base=None)
    @cli.job
    def main(cfg): ...

    if __name__ == "__main__":
        cli.run(main)

* A **user error** -- a :class:`~mrta_rl.config.UserError` (bad setting, malformed system file,
  bad checkpoint path), a Hydra composition error (unknown key or config group option, bad
  override syntax), a YAML syntax error in a config or system file, or an operating-system
  fault (disk full, file too large, permission denied, a file where a folder goes) -- prints
  ``error: <message>`` on stderr, one line naming the culprit (``mrta_rl/errors.py``), and exits
  with :data:`EXIT_USER_ERROR`.
* **Ctrl-C** prints ``interrupted`` and exits with :data:`EXIT_INTERRUPTED` (130, the shell's
  convention), without a traceback. A training loop that saves on Ctrl-C does so before the
  ``KeyboardInterrupt`` reaches this layer.
* A single run told its dir (``hydra.run.dir=<dir>``, ``resume=<dir>``) claims it before Hydra
  writes anything (``runners/run_dir.py``): a dir in use by another process, a finished run or a
  dir that cannot be resumed is refused as a user error, and nothing is written or created.
* Either way :func:`job` removes the run directory Hydra made for the failed job when it holds
  nothing but Hydra's own files (``.hydra/`` and the job log), then empty parent folders up to
  the working directory. A directory holding anything else (a checkpoint, an earlier run's
  results) is never touched.
* Anything else is a bug and keeps its full traceback; ``HYDRA_FULL_ERROR=1`` also gives the
  traceback of user errors.
"""

from __future__ import annotations

import functools
import json
import logging
import os
import shutil
import sys
from collections.abc import Callable
from contextlib import suppress
from pathlib import Path
from typing import Any

from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode

from mrta_rl.errors import EXIT_INTERRUPTED, EXIT_USER_ERROR, os_fault, user_message
from mrta_rl.run_layout import REFUSED_JOBS_FILE
from mrta_rl.runners.run_dir import claim_from_args

__all__ = ["EXIT_INTERRUPTED", "EXIT_USER_ERROR", "job", "remove_unused_run_dir", "run"]

HYDRA_FILES = frozenset({"config.yaml", "hydra.yaml", "overrides.yaml"})  # of <run dir>/.hydra
SWEEP_FILES = frozenset({"multirun.yaml"})  # what Hydra writes in a sweep dir before the jobs


FAILED_JOBS: list[str] = []  # "job <n> (<overrides>): <message>" of this sweep's failed jobs
# in a sweep dir: one JSON line {"overrides": [...], "reason": ...} per job refused by a user
# error, whose run dir is removed (reports/collect.py shows the job as refused, with the reason)


_HANDLE_ERROR = logging.FileHandler.handleError  # logging's own: a traceback on stderr, go on


def _log_faults_stop(handler: logging.Handler, record: logging.LogRecord) -> None:
    """A log file the machine refuses to write (disk full...) stops the command, naming it.

    ``logging`` prints a traceback for every record it cannot write and goes on; the job log is
    one of the run's files, so its refused write ends the command as any other does: in one
    line (:func:`run`), with the newest checkpoint kept.
    """
    err = sys.exc_info()[1]
    fault = os_fault(err) if err is not None else None
    if fault is not None and isinstance(handler, logging.FileHandler):
        raise OSError(fault.errno, fault.strerror, handler.baseFilename) from err
    _HANDLE_ERROR(handler, record)


def _quiet_faults_at_exit(unraisable: Any) -> None:
    """After a refused write has been named, files that cannot flush as they close say nothing.

    Loggers close their files when the interpreter exits; after a full disk those closes fail
    again, and Python would print a traceback for each.
    """
    if os_fault(unraisable.exc_value) is None:
        sys.__unraisablehook__(unraisable)


def _exit(err: BaseException) -> None:
    """Print the one message of a user error or Ctrl-C and exit, unless tracebacks are wanted."""
    if _FULL_ERROR:
        return  # the caller re-raises: the traceback is printed
    if os_fault(err) is not None:
        sys.unraisablehook = _quiet_faults_at_exit
    if isinstance(err, KeyboardInterrupt):
        print("interrupted", file=sys.stderr)
        sys.exit(EXIT_INTERRUPTED)
    if len(FAILED_JOBS) > 1:  # Hydra raises the first failure only: name them all
        lines = "".join(f"\n  {failure}" for failure in FAILED_JOBS)
        print(f"error: {len(FAILED_JOBS)} jobs of the sweep failed:{lines}", file=sys.stderr)
        sys.exit(EXIT_USER_ERROR)
    print(f"error: {user_message(err)}", file=sys.stderr)
    sys.exit(EXIT_USER_ERROR)


_FULL_ERROR = os.environ.get("HYDRA_FULL_ERROR") == "1"  # as the user started the script


def run(main: Callable[[], Any]) -> None:
    """Run a script's entry point; turn user errors and Ctrl-C into a message and an exit code.

    Errors of the job itself are handled by :func:`job`; this catches those of Hydra's start
    (composition, override syntax, YAML) and a Ctrl-C outside the job.

    Args:
        main: The script's ``main`` (a ``@hydra.main`` function or a plain one).
    """
    # Hydra then re-raises instead of printing its own stack trace; the handlers below decide
    os.environ["HYDRA_FULL_ERROR"] = "1"
    logging.FileHandler.handleError = _log_faults_stop  # type: ignore[method-assign]
    claimed = None
    try:
        with claim_from_args(sys.argv[1:]) as claimed:  # before Hydra writes into the run dir
            main()
    except (Exception, KeyboardInterrupt) as err:
        if isinstance(err, KeyboardInterrupt) or user_message(err) is not None:
            # Hydra's files of a job that never ran (Hydra's own write refused); Hydra names
            # the job after the module of its task function
            remove_unused_run_dir(claimed, main.__module__.rpartition(".")[2])
            _exit(err)
        raise


def job(task: Callable[[Any], Any]) -> Callable[[Any], Any]:
    """Decorate a Hydra task function: on a user error or Ctrl-C, remove its unused run dir.

    Args:
        task: The task function, called with the composed config.

    Returns:
        The wrapped task function. In a single run it exits the process on a user error or
        Ctrl-C (re-raises under ``HYDRA_FULL_ERROR=1``). In a sweep it re-raises: Hydra runs the
        other jobs, then names the failed job and :func:`run` prints the message; Ctrl-C stops
        the sweep.
    """

    @functools.wraps(task)
    def wrapper(cfg: Any) -> Any:
        try:
            return task(cfg)
        except (Exception, KeyboardInterrupt) as err:
            message = None if isinstance(err, KeyboardInterrupt) else user_message(err)
            if message is None and not isinstance(err, KeyboardInterrupt):
                raise  # a bug: its traceback
            sweep = HydraConfig.get().mode == RunMode.MULTIRUN
            if sweep and message is not None:
                hydra_job = HydraConfig.get().job
                overrides = " ".join(hydra_job.override_dirname.split(",")) or "-"
                FAILED_JOBS.append(f"job {hydra_job.num} ({overrides}): {message}")
                if os_fault(err) is None:  # refused by its input; a fault of the machine is not
                    _record_refusal(message)  # first: the sweep dir then keeps it
            remove_unused_run_dir()
            if not sweep:
                _exit(err)
            raise

    return wrapper


def _record_refusal(reason: str) -> None:
    """Append the current sweep job's refusal to :data:`REFUSED_JOBS_FILE` in the sweep dir."""
    hydra_cfg = HydraConfig.get()
    record = {"overrides": list(hydra_cfg.overrides.task), "reason": reason}
    sweep_dir = Path(hydra_cfg.sweep.dir)
    sweep_dir.mkdir(parents=True, exist_ok=True)
    with (sweep_dir / REFUSED_JOBS_FILE).open("a") as handle:
        handle.write(json.dumps(record) + "\n")


def remove_unused_run_dir(run_dir: Path | None = None, job_name: str = "") -> Path | None:
    """Remove the current Hydra job's run dir if it holds only Hydra's own files.

    Args:
        run_dir: The run dir when no Hydra job is current: Hydra lets go of a job's config when
            its own writes into the run dir fail, before the job starts. Ignored in a job.
        job_name: The job's name, with ``run_dir`` (its log file is ``<job_name>.log``).

    Returns:
        The removed directory, or None when nothing was removed.
    """
    if HydraConfig.initialized():
        hydra_cfg = HydraConfig.get()
        run_dir, top = Path(hydra_cfg.runtime.output_dir), Path(hydra_cfg.runtime.cwd)
        job_name = hydra_cfg.job.name
    elif run_dir is None:
        return None
    else:
        top = Path.cwd()
    run_dir, top, log_file = run_dir.resolve(), top.resolve(), f"{job_name}.log"
    if run_dir == top or top.is_relative_to(run_dir) or not _only_hydra_files(run_dir, log_file):
        return None
    for handler in list(logging.root.handlers):  # Hydra's job log is open in the run dir
        if (
            isinstance(handler, logging.FileHandler)
            and Path(handler.baseFilename).parent == run_dir
        ):
            with suppress(OSError):  # its last lines cannot be written: it closes anyway
                handler.close()
            logging.root.removeHandler(handler)
    shutil.rmtree(run_dir, ignore_errors=True)  # a folder it cannot remove stays
    parent = run_dir.parent
    while parent != top and parent.is_relative_to(top):
        if any(p.name not in SWEEP_FILES for p in parent.iterdir()):
            break
        shutil.rmtree(parent, ignore_errors=True)
        parent = parent.parent
    return run_dir


def _only_hydra_files(run_dir: Path, log_file: str) -> bool:
    """True if ``run_dir`` has Hydra's ``.hydra/`` snapshot and nothing but it and the job log."""
    snapshot = run_dir / ".hydra"
    if not snapshot.is_dir() or any(p.name not in HYDRA_FILES for p in snapshot.iterdir()):
        return False
    return all(p.name in (".hydra", log_file) for p in run_dir.iterdir())

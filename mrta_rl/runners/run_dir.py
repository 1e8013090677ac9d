"""The run-dir lock and checks: one process per run dir, claimed before Hydra writes into it.

A run dir is used by one process at a time. The lock is ``flock`` on the directory itself, so
nothing is added to the dir, and the lock dies with its process: a SIGKILLed run leaves no stale
lock. A second process on a locked dir is refused at once, naming the holder's pid.

Hydra writes a run's ``.hydra/`` snapshot and job log before the task function runs, so
``cli.run`` claims the dir a script is told (``hydra.run.dir=``, ``resume=``) first
(:func:`claim_from_args`): it locks the dir and checks that the run may use it
(:func:`check_run_dir`), so a refused run changes nothing and creates nothing. :func:`train`
claims its run dir too (the lock is reentrant), which covers default and sweep dirs: Hydra makes
those unique, and the lock then keeps a ``resume=`` of a live run out.
"""

from __future__ import annotations

import errno
import fcntl
import functools
import os
import re
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any, NoReturn, TypeVar

from mrta_rl.run_layout import CHECKPOINT_DIR, CONFIG_FILE, METRICS_FILE, RunDirError
from mrta_rl.runners.checkpoint import require_checkpoint

_HELD: dict[str, int] = {}  # realpath of a run dir -> descriptor holding its lock (this process)
_LOCKS_TABLE = Path("/proc/locks")  # Linux: who holds which flock
_FLOCK_LINE = re.compile(r"FLOCK\s+\S+\s+WRITE\s+(\d+)\s+([0-9a-f]+):([0-9a-f]+):(\d+)\s")
NO_JOB_FLAGS = ("help", "hydra_help", "info", "cfg", "shell_completion", "multirun")
F = TypeVar("F", bound=Callable[..., Any])


class RunDirInUse(RunDirError):
    """The run dir is locked by another live process."""


def _holder(run_dir: Path) -> int | None:
    """Pid of the process holding the flock on ``run_dir``, if the system says."""
    try:
        stat = run_dir.stat()
        table = _LOCKS_TABLE.read_text()
    except OSError:
        return None
    for match in _FLOCK_LINE.finditer(table):
        pid, major, minor, inode = match.groups()
        same_dev = (int(major, 16), int(minor, 16)) == (
            os.major(stat.st_dev),
            os.minor(stat.st_dev),
        )
        if int(inode) == stat.st_ino and (same_dev or os.major(stat.st_dev) == 0):
            return int(pid)
    return None


def lock_run_dir(run_dir: Path | str) -> bool:
    """Take this process's exclusive lock on an existing run dir; a no-op if already held.

    Args:
        run_dir: The run dir (it must exist).

    Returns:
        True if the lock was taken now, False if this process already held it.

    Raises:
        RunDirInUse: if another process holds it (the message names its pid).
        RunDirError: if the dir cannot be opened.
    """
    key = os.path.realpath(run_dir)
    if key in _HELD:
        return False
    try:
        fd = os.open(key, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
    except OSError as err:
        raise RunDirError(f"{run_dir}: cannot open the run dir ({err.strerror})") from err
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as err:
        os.close(fd)
        if err.errno not in (errno.EWOULDBLOCK, errno.EAGAIN):
            raise RunDirError(f"{run_dir}: cannot lock the run dir ({err.strerror})") from err
        pid = _holder(Path(key))
        who = f"another process (pid {pid})" if pid else "another process"
        raise RunDirInUse(
            f"{run_dir} is in use by {who}; wait for it to end, or choose another hydra.run.dir"
        ) from None
    _HELD[key] = fd
    return True


def release_run_dir(run_dir: Path | str) -> None:
    """Release this process's lock on ``run_dir`` (nothing if it holds none)."""
    fd = _HELD.pop(os.path.realpath(run_dir), None)
    if fd is not None:
        os.close(fd)  # closing the last descriptor releases the flock


def releases_run_dirs(function: F) -> F:
    """Decorate a function: the run-dir locks it takes are released when it returns or raises.

    Locks held before the call (taken by :func:`claim_from_args`) stay held.
    """

    @functools.wraps(function)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        before = set(_HELD)
        try:
            return function(*args, **kwargs)
        finally:
            for key in set(_HELD) - before:
                release_run_dir(key)

    return wrapper  # type: ignore[return-value]


def check_run_dir(run_dir: Path, *, resume: bool) -> None:
    """Refuse a run dir a run may not use: finished, interrupted (fresh run), not resumable.

    Args:
        run_dir: The run dir.
        resume: The run continues the dir's checkpoint (``resume=``), else it starts afresh.

    Raises:
        RunDirError: naming the dir and what to do instead.
    """
    if (run_dir / METRICS_FILE).exists():
        raise RunDirError(
            f"{run_dir} already holds the results of a finished run ({METRICS_FILE}); "
            "choose another hydra.run.dir (the default is unique per run)"
        )
    if not resume:
        if (run_dir / CHECKPOINT_DIR).exists():
            raise RunDirError(
                f"{run_dir} holds the checkpoint of an interrupted run: continue it with "
                f"resume={run_dir}, or choose another hydra.run.dir"
            )
        return
    if not (run_dir / CONFIG_FILE).is_file():
        raise RunDirError(
            f"resume={run_dir}: not a run dir of scripts/train.py (no {run_dir / CONFIG_FILE})"
        )
    require_checkpoint(run_dir)


def claim_run_dir(run_dir: Path, *, resume: bool) -> list[Path]:
    """Lock the run dir (made if a fresh run's is missing), then check it (:func:`check_run_dir`).

    Args:
        run_dir: The run dir.
        resume: See :func:`check_run_dir`; a resumed run's dir must exist.

    Returns:
        The folders made, deepest first.

    Raises:
        RunDirError: if the dir is refused (nothing is made then) or locked by another process.
    """
    if resume and not run_dir.is_dir():
        raise RunDirError(f"resume={run_dir}: not a run dir of scripts/train.py (no such folder)")
    made = [p for p in (run_dir, *run_dir.parents) if not p.exists()]
    run_dir.mkdir(parents=True, exist_ok=True)
    taken = lock_run_dir(run_dir)
    try:
        check_run_dir(run_dir, resume=resume)
    except RunDirError:
        if taken:
            release_run_dir(run_dir)
        _remove_empty(made)
        raise
    return made


def _remove_empty(folders: Sequence[Path]) -> None:
    """Remove the folders (deepest first) that are still empty."""
    for folder in folders:
        try:
            folder.rmdir()
        except FileNotFoundError:  # removed with the job's unused run dir (cli.job)
            continue
        except OSError:  # not empty: it is in use
            return


def run_dir_of(args: Sequence[str]) -> tuple[Path, bool] | None:
    """The run dir a script's command line names, and whether it resumes, if it names one.

    Args:
        args: The command line after the script (``sys.argv[1:]``).

    Returns:
        ``(dir, resume)`` for a single run given ``resume=<dir>`` (it then runs in that dir) or
        ``hydra.run.dir=<dir>``; None when no job runs in one named dir (sweeps, ``--help``,
        ``--cfg``...) or the value is left to Hydra (an interpolation, a syntax error).
    """
    from hydra._internal.utils import get_args_parser  # the parser hydra.main uses
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    parser = get_args_parser()
    parser.error = _no_usage  # type: ignore[method-assign]  # Hydra's own parse reports it
    try:
        parsed, _ = parser.parse_known_args(list(args))  # other flags: an argparse script's
    except ValueError:
        return None
    if any(getattr(parsed, flag, None) for flag in NO_JOB_FLAGS):
        return None
    try:
        overrides = OverridesParser.create().parse_overrides(parsed.overrides)
    except HydraException:  # Hydra reports the syntax error
        return None
    values = {}
    for override in overrides:
        if override.key_or_group in ("resume", "hydra.run.dir") and not override.is_delete():
            values[override.key_or_group] = override.value()
    for key in ("resume", "hydra.run.dir"):
        value = values.get(key)
        if isinstance(value, bool) or not isinstance(value, str | int | float):
            continue  # null, absent or not a path: Hydra's config decides
        if "${" in str(value):
            return None
        return Path(str(value)), key == "resume"
    return None


def _no_usage(message: str) -> NoReturn:
    raise ValueError(message)


@contextmanager
def claim_from_args(args: Sequence[str]) -> Iterator[Path | None]:
    """Claim the run dir the command line names before Hydra writes anything (:func:`run_dir_of`).

    Args:
        args: The command line after the script (``sys.argv[1:]``).

    Yields:
        The claimed run dir, or None if the command line names none. If the block fails, the
        folders made for the claim are removed when still empty.

    Raises:
        RunDirError: if the dir is refused or in use; nothing has been written then.
    """
    named = run_dir_of(args)
    if named is None:
        yield None
        return
    run_dir, resume = named
    made = claim_run_dir(run_dir, resume=resume)
    try:
        yield run_dir
    except BaseException:
        _remove_empty(made)
        raise

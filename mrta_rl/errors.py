"""User errors in one line: what counts as one, its message, the exit codes, checked outputs.

Every command ends a user error with ``error: <one line>`` on stderr and :data:`EXIT_USER_ERROR`
(``runners/cli.py``; ``commands/report.py``, which loads no runner); anything else is a bug and
keeps its traceback. :func:`user_message` gives the line, or None for a bug:

* a :class:`~mrta_rl.config.UserError`: its message names the culprit;
* a YAML syntax error in a config or system file;
* a Hydra error: an unknown key or config option, or an override it cannot parse, said in one
  line naming the key or the option (the known ones cut after a few, with a count); an override
  its parser fails on with an error of Python's own (a number past Python's digit limit, lists
  nested past the recursion limit) is named too;
* an operating-system fault (:data:`OS_FAULTS`): disk full, file too large, permission denied,
  a read-only file system, a file or folder in the way. The line names the path and the cause:
  the error's own file name, else the file the failing code was writing through a file object
  (such a write fails without a name; the error of ``torch.save`` into a file object carries
  the fault as its context), else the current run dir.

The line is at most :data:`MAX_LINE` characters: a long value or path it quotes is cut in its
middle (:func:`short_line`).

Where a command writes is checked before any work (:func:`check_output_file`,
:func:`check_output_folder`, :func:`check_writable`): a command that could not write its results
refuses to start, and writes nothing.
"""

from __future__ import annotations

import errno
import io
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from types import FrameType

import yaml
from hydra.errors import HydraException, MissingConfigException, OverrideParseException
from omegaconf.errors import ConfigAttributeError, ConfigKeyError, OmegaConfBaseException

from mrta_rl.config import UserError, short_list

EXIT_USER_ERROR = 2  # bad input or a refused write (as argparse); 1 stays Python's for a crash
EXIT_INTERRUPTED = 130  # 128 + SIGINT
# errno of the faults that are the machine's, not the program's: named in one line
OS_FAULTS = frozenset(
    {
        errno.ENOSPC,  # disk full
        errno.EDQUOT,  # disk quota exceeded
        errno.EFBIG,  # file too large (ulimit -f)
        errno.EACCES,  # permission denied
        errno.EPERM,  # operation not permitted (an immutable file or folder)
        errno.EROFS,  # read-only file system
        errno.EEXIST,  # a file where a folder is made
        errno.ENOTDIR,  # a file where a folder is expected
        errno.EISDIR,  # a folder where a file is written
    }
)
SEARCH_PATH = ("Config search path:", "Search path:")  # where Hydra's messages list its sources
# Hydra's functions that read and apply one override (module, function) -> the local holding it
HYDRA_OVERRIDE_FRAMES = {
    ("hydra.core.override_parser.overrides_parser", "parse_rule"): "s",
    ("hydra._internal.config_loader_impl", "_apply_overrides_to_config"): "override",
}
MAX_LINE = 300  # characters of a message line (a long value or path is cut in its middle)


def user_message(err: BaseException) -> str | None:
    """The one line a command prints for a user error (module docstring), None for a bug.

    Args:
        err: The exception that ended the command.

    Returns:
        The message, without the ``error: `` prefix; None if ``err`` is not a user error.
    """
    if isinstance(err, UserError):
        message = str(err)
    elif isinstance(err, yaml.YAMLError):
        message = f"YAML syntax error: {err}"
    elif isinstance(err, HydraException):
        message = hydra_message(err)
    elif (fault := os_fault(err)) is not None:
        message = _fault_message(fault, err)
    elif (override := _unparsed_override(err)) is not None:
        reason = "nested too deeply" if isinstance(err, RecursionError) else str(err)
        # the override cut short, so that the reason stays whole (not Python's advice after ;)
        message = f"{short_line(override, MAX_LINE // 2)}: {reason.split(';')[0]}"
    else:
        return None
    return short_line(message)


def short_line(message: str, width: int = MAX_LINE) -> str:
    """``message`` on one line of at most ``width`` characters, cut in its middle.

    A message quotes what it names; a value or a path given on the command line can be any
    length, and its line then keeps its start (the key) and its end, with the count of what
    was cut between.
    """
    message = " ".join(message.splitlines())
    if len(message) <= width:
        return message
    tail = width // 4
    head = width - tail - 32  # what the count between takes, up to 10**10 characters
    return f"{message[:head]} [...{len(message) - head - tail:,} characters...] {message[-tail:]}"


def _unparsed_override(err: BaseException) -> str | None:
    """The override Hydra was reading or applying when it failed with an error of Python's own.

    Hydra raises its own errors (:func:`hydra_message`) for what it cannot read or apply, but
    not for a number past Python's digit limit (``ValueError``) or lists nested past the
    recursion limit (``RecursionError``, in its parser or in OmegaConf).
    """
    if not isinstance(err, (ValueError, RecursionError)):
        return None
    for frame in _frames(err):
        local = HYDRA_OVERRIDE_FRAMES.get((frame.f_globals.get("__name__"), frame.f_code.co_name))
        if local is not None:
            override = frame.f_locals.get(local)
            override = getattr(override, "input_line", override)  # applied: an Override
            return override if isinstance(override, str) else None
    return None


# ---------------------------------------------------------------------------------- OS faults
def os_fault(err: BaseException) -> OSError | None:
    """The operating-system fault (:data:`OS_FAULTS`) behind ``err``, if any.

    ``err`` itself, or an error it was raised from or during (``torch.save`` raises a
    ``RuntimeError`` during the ``OSError`` of its file object).
    """
    seen: set[int] = set()
    while err is not None and id(err) not in seen:
        seen.add(id(err))
        if isinstance(err, OSError) and err.errno in OS_FAULTS:
            return err
        err = err.__cause__ or (None if err.__suppress_context__ else err.__context__)
    return None


def _frames(err: BaseException) -> Iterator[FrameType]:
    """The frames of ``err``'s traceback, innermost first."""
    frames = []
    tb = err.__traceback__
    while tb is not None:
        frames.append(tb.tb_frame)
        tb = tb.tb_next
    return reversed(frames)


def _written_file(fault: OSError, err: BaseException) -> str | None:
    """The file the failing code had open: a file object among the locals, innermost first."""
    for frame in [*_frames(fault), *_frames(err)]:
        for value in frame.f_locals.values():
            if isinstance(value, io.IOBase) and isinstance(getattr(value, "name", None), str):
                return value.name
    return None


def _run_dir() -> str | None:
    """The current Hydra job's run dir, if a job is running."""
    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized():
        return None
    return str(HydraConfig.get().runtime.output_dir)


def _fault_message(fault: OSError, err: BaseException) -> str:
    cause = f"{fault.strerror or os.strerror(fault.errno)} ({errno.errorcode[fault.errno]})"
    if fault.filename is not None:
        path = os.fsdecode(fault.filename)
        if fault.filename2 is not None:
            path += f" -> {os.fsdecode(fault.filename2)}"
        return f"{path}: {cause}"
    written = _written_file(fault, err)
    if written is not None:
        return f"{written}: {cause}"
    run_dir = _run_dir()
    return f"writing in {run_dir}: {cause}" if run_dir else cause


def _cause(err: OSError) -> str:
    """``File name too long (ENAMETOOLONG)``: the system's reason and its errno name."""
    return f"{err.strerror} ({errno.errorcode.get(err.errno, err.errno)})"


def check_writable(folder: Path | str, what: str) -> None:
    """Refuse a folder this process cannot create files in, before any work.

    The probe is an unnamed temporary file (``O_TMPFILE`` where the file system has it), so
    nothing appears in the folder; it meets what a write would (permissions, an immutable
    folder, a read-only file system).

    Args:
        folder: An existing folder.
        what: The argument or file the message names (``--out``, ``eval_metrics.json``).

    Raises:
        UserError: naming ``what``, the folder and the cause.
    """
    try:
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as err:
        raise UserError(f"{what}: cannot write in {folder}: {_cause(err)}") from None


def _exists(path: Path) -> bool:
    """Whether ``path`` names an entry, itself (a link is not followed).

    Raises:
        OSError: for anything but a missing entry: a name too long, no permission to look.
    """
    try:
        os.lstat(path)
    except (FileNotFoundError, NotADirectoryError):
        return False
    return True


def _broken_link(path: Path) -> bool:
    """Whether ``path`` is a link to nothing (a missing target, or a loop of links)."""
    return path.is_symlink() and not path.exists()


def check_output_file(path: Path | str, what: str) -> None:
    """Refuse an output file that could not be written, before any work.

    Its folder must exist and take new files. A file already there (or the file a link names)
    must open for writing; a link to a file not yet there needs that file's folder. An empty
    path, a folder, a link to nothing (a missing folder, a loop of links) or a name the system
    refuses (too long) is refused.

    Args:
        path: The file a command will write (replacing it if it exists).
        what: The argument the message names (``--out``).

    Raises:
        UserError: naming ``what``, the path and why.
    """
    if not os.fspath(path):
        raise UserError(f"{what}: an empty path; name a file")
    path = Path(path)
    target = Path(os.path.realpath(path))  # where a write through the path lands
    folders = [path.parent]  # its folder, where an atomic write makes its temporary file
    try:
        if not _exists(target):
            folders.append(target.parent)  # where a write through the path makes the file
        else:
            if target.is_dir():
                raise UserError(f"{what}: {path} is a folder; name a file")
            if _broken_link(target):
                raise UserError(f"{what}: {path} is a link to nothing (a loop of links)")
            # O_NONBLOCK: a FIFO without a reader is refused, not waited for; nothing is written
            os.close(os.open(target, os.O_WRONLY | os.O_APPEND | os.O_NONBLOCK | os.O_CLOEXEC))
        for folder in dict.fromkeys(folders):
            if not folder.is_dir():
                missing = "is not a folder" if _exists(folder) else "does not exist"
                raise UserError(f"{what}: {path}: the folder {folder} {missing}")
    except OSError as err:
        raise UserError(f"{what}: {path}: {_cause(err)}") from None
    for folder in dict.fromkeys(folders):
        check_writable(folder, what)


def check_output_folder(path: Path | str, what: str) -> None:
    """Refuse an output folder that could not be made or written, before any work.

    The path, or the nearest of its ancestors that exists, must be a folder (or a link to one)
    that takes new files (the command makes the missing folders). An empty path, a file or a
    link to nothing in the way, or a name the system refuses (too long) is refused.

    Args:
        path: The folder a command will write into.
        what: The argument the message names (``--out``).

    Raises:
        UserError: naming ``what``, the path and why.
    """
    if not os.fspath(path):
        raise UserError(f"{what}: an empty path; name a folder")
    path = Path(path)
    try:
        # lexically (``..`` is not resolved), as the folders are made
        existing = next((p for p in (path, *path.parents) if _exists(p)), Path.cwd())
        if not existing.is_dir():
            kind = "a link to nothing" if _broken_link(existing) else "a file"
            raise UserError(f"{what}: {path}: {existing} is {kind}, not a folder")
    except OSError as err:
        raise UserError(f"{what}: {path}: {_cause(err)}") from None
    check_writable(existing, what)


# ---------------------------------------------------------------------------------- Hydra
def hydra_message(err: HydraException) -> str:
    """One line for a Hydra error, naming the key or the option (module docstring).

    Args:
        err: A Hydra error of composition or of an override.

    Returns:
        The message: ``train.workers: unknown key (known: ...)``, ``learner=nope: no such
        option (available: ...)``, ``<override>: <parse error>``; else Hydra's own message with
        its lines joined and its search path left out.
    """
    if isinstance(err, OverrideParseException):
        return f"{err.override}: {err.message.splitlines()[0]}"
    if isinstance(err, MissingConfigException) and err.options and err.missing_cfg_file:
        group, _, option = err.missing_cfg_file.rpartition("/")
        return f"{group}={option}: no such option (available: {short_list(err.options)})"
    cause = err.__cause__
    if isinstance(cause, (ConfigAttributeError, ConfigKeyError)) and cause.full_key:
        parent = cause.parent_node
        keys = [str(k) for k in parent.keys() if not str(k).startswith("_") and k != "hydra"]
        known = f"known: {short_list(keys)}" if keys else "it has no keys"
        return f"{cause.full_key}: unknown key ({known})"
    return _one_line(str(err), cause)


def _one_line(message: str, cause: BaseException | None) -> str:
    """Hydra's message on one line: its list items joined, its search path left out."""
    words, items = [], []
    for line in message.splitlines():
        if line.startswith(SEARCH_PATH):
            break
        if line.startswith("\t"):
            items.append(line.strip())
        elif line.strip():
            words.append(line.strip())
    text = " ".join(words)
    if items:
        text += f" {short_list(items)}"
    if isinstance(cause, OmegaConfBaseException):  # its first line: what is wrong
        text += f": {str(cause).splitlines()[0]}" if str(cause) else ""
    return text

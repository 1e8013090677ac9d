"""Every file a run reads is read here: regular files only, bounded bytes, checked parsing.

A run reads files that anyone may have written, replaced or damaged: its own run dir
(``.hydra/*.yaml``, ``learner/``, ``checkpoint/``, ``metrics.json``, ``curve.csv``), the run dirs
it names (``init=``, ``learner.base=``, ``resume=``, ``scripts/evaluate.py``, the report) and the
team files given by path. Each read goes through one of these functions, and every refusal is a
:class:`RunDirError` of one short line naming the file and the cause:

* :func:`open_regular` opens the file without blocking (``O_NONBLOCK``) and refuses anything but a
  regular file (a FIFO, a device, a socket, a folder, or a symlink to one) before a byte is read:
  a FIFO never hangs a run and ``/dev/zero`` is never read;
* the bytes read are bounded by what is read, not by the size the file system reports
  (:func:`read_bytes` reads at most ``limit + 1`` bytes; the binary readers refuse any read past
  ``limit``);
* :func:`read_json` (no NaN or infinity constants), :func:`read_yaml` and :func:`check_yaml_text`
  (no aliases, bounded nesting, a syntax error as one line with its line and column) and
  :func:`read_csv_numbers` (a cell that is not a number names its line and column) parse text;
* :func:`read_arrays` reads an ``.npz`` file against an :class:`ArraySpec` per array: each
  member's npy header is parsed first and its names, dtype and shape are checked, and the bytes it
  declares bounded, before anything is allocated; values are checked after (finite, ranges,
  names); nothing is ever unpickled;
* :func:`read_tensors` reads a ``.pt`` file with ``torch.load(weights_only=True)`` through the
  same bounded reader.
"""

from __future__ import annotations

import csv
import io
import json
import lzma
import math
import os
import stat
import zipfile
import zlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any

import numpy as np
import yaml

from mrta_rl.config import UserError, short_list

if TYPE_CHECKING:
    import torch
    from omegaconf import DictConfig, ListConfig

MAX_TEXT_BYTES = 256 * 2**20  # JSON and CSV of a run dir: a training.json holds a row per episode
MAX_YAML_BYTES = 2**20  # 1 MiB, about 40,000 robots in table form (random teams have no limit)
MAX_DEPTH = 64  # YAML nesting of mappings and lists; a system file needs 4
ZIP_MAGIC = b"PK\x03\x04"  # an npz file and a torch file (torch.save) are zip archives
NPY_OVERHEAD = 2**16  # bytes of an npz member beyond its data: zip entry and npy header
PT_OVERHEAD = 2**20  # bytes of a torch file beyond its tensors' data, plus PT_PER_TENSOR each
PT_PER_TENSOR = 2**10
MAX_NAME_LENGTH = 256  # characters of an item of a text array without declared names
# what the zip reader raises on a damaged archive: besides its own errors, a member's compressed
# data that does not decompress (zlib, lzma; bz2 raises OSError), and a member it cannot read at
# all (NotImplementedError: a compression method or zip version it lacks; RuntimeError: encrypted)
ZIP_FAULTS = (
    zipfile.BadZipFile,
    zipfile.LargeZipFile,
    zlib.error,
    lzma.LZMAError,
    EOFError,
    OSError,
    ValueError,
    RuntimeError,
)


class RunDirError(UserError):
    """A file a run reads (of a run dir, or a team file) that cannot be used.

    The message names the file and what is wrong, in one line.
    """


class YamlSyntaxError(RunDirError):
    """A YAML file that does not parse; the message names the file, line and column."""


# ---------------------------------------------------------------------------------- opening
def _kind(mode: int) -> str | None:
    """What a non-regular file is, for messages (None: a regular file)."""
    if stat.S_ISREG(mode):
        return None
    kinds = {
        stat.S_ISDIR: "a folder",
        stat.S_ISFIFO: "a FIFO (named pipe)",
        stat.S_ISCHR: "a character device",
        stat.S_ISBLK: "a block device",
        stat.S_ISSOCK: "a socket",
    }
    return next((name for test, name in kinds.items() if test(mode)), "not a regular file")


def open_regular(path: Path | str) -> int:
    """A read-only descriptor of ``path``, refused unless it is a regular file.

    The file (or the file a symlink names) is opened with ``O_NONBLOCK``, so that opening a FIFO
    never waits for a writer, and its kind is checked on the open descriptor (``fstat``) before
    anything is read.

    Args:
        path: The file.

    Returns:
        The descriptor (the caller closes it).

    Raises:
        RunDirError: naming the file: missing, not a regular file (saying what it is), or not
            readable (the system's reason).
    """
    flags = os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC | getattr(os, "O_NOCTTY", 0)
    try:
        kind = _kind(os.stat(path).st_mode)  # a socket cannot be opened: named from its stat
        if kind is not None:
            raise RunDirError(f"{path}: {kind}, not a regular file")
        fd = os.open(path, flags)
    except FileNotFoundError:
        raise RunDirError(f"{path}: missing") from None
    except OSError as err:
        raise RunDirError(f"{path}: cannot be read ({err.strerror})") from None
    try:
        kind = _kind(os.fstat(fd).st_mode)  # the file opened, whatever the path names now
        if kind is not None:
            raise RunDirError(f"{path}: {kind}, not a regular file")
    except BaseException:
        os.close(fd)
        raise
    return fd


def _too_big(path: Path | str, limit: int, what: str) -> RunDirError:
    return RunDirError(f"{path}: more than the limit of {limit:,} bytes for {what}")


def read_bytes(path: Path | str, limit: int, what: str = "such a file") -> bytes:
    """The bytes of a regular file of at most ``limit`` bytes.

    At most ``limit + 1`` bytes are read: a file that holds more is refused, whatever size the
    file system reports (a file that grows while it is read included).

    Args:
        path: The file.
        limit: The most bytes it may hold.
        what: The kind of file, for the message (``"a training.json"``).

    Returns:
        Its bytes.

    Raises:
        RunDirError: naming the file, if it is not a regular file, unreadable or too big.
    """
    fd = open_regular(path)
    try:
        if os.fstat(fd).st_size > limit:  # a regular file's size: refused before reading it
            raise _too_big(path, limit, what)
        chunks, size = [], 0
        while size <= limit:
            chunk = os.read(fd, min(limit + 1 - size, 2**24))
            if not chunk:
                break
            chunks.append(chunk)
            size += len(chunk)
    except OSError as err:
        raise RunDirError(f"{path}: cannot be read ({err.strerror})") from None
    finally:
        os.close(fd)
    if size > limit:
        raise _too_big(path, limit, what)
    return b"".join(chunks)


def read_text(path: Path | str, limit: int, what: str = "such a file") -> str:
    """The UTF-8 text of a regular file of at most ``limit`` bytes (:func:`read_bytes`).

    Raises:
        RunDirError: naming the file, as :func:`read_bytes`, or if it is not UTF-8 text.
    """
    data = read_bytes(path, limit, what)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as err:
        raise RunDirError(f"{path}: not UTF-8 text (byte {err.start})") from None


class _BoundedFile(io.RawIOBase):
    """A regular file's descriptor as a seekable binary file that refuses to read past a limit.

    The zip readers (numpy's archives, torch's files) seek and read where the archive's own
    records point; any byte read at an offset of ``limit`` or more refuses the file as too big.
    """

    def __init__(self, fd: int, limit: int, path: Path | str, what: str) -> None:
        super().__init__()
        self._file = io.FileIO(fd, "rb", closefd=True)
        self.limit, self.path, self.what = limit, path, what

    def readable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        return self._file.seek(offset, whence)

    def tell(self) -> int:
        return self._file.tell()

    def readinto(self, buffer: Any) -> int:
        count = self._file.readinto(buffer) or 0
        if count and self._file.tell() > self.limit:
            raise _too_big(self.path, self.limit, self.what)
        return count

    def close(self) -> None:
        self._file.close()
        super().close()


def open_bounded(path: Path | str, limit: int, what: str) -> IO[bytes]:
    """A regular file opened for the zip readers, refusing any read past ``limit`` bytes.

    Args:
        path: The file.
        limit: The most bytes it may hold.
        what: The kind of file, for messages.

    Returns:
        A buffered binary file (the caller closes it).

    Raises:
        RunDirError: naming the file, if it is not a regular file or is too big.
    """
    fd = open_regular(path)
    try:
        if os.fstat(fd).st_size > limit:
            raise _too_big(path, limit, what)
    except BaseException:
        os.close(fd)
        raise
    return io.BufferedReader(_BoundedFile(fd, limit, path, what))


# ---------------------------------------------------------------------------------- text formats
def _no_constant(name: str) -> Any:
    raise ValueError(f"{name} is not a finite number")


def parse_json(text: str, path: Path | str) -> Any:
    """JSON text read from ``path``, NaN and infinities refused.

    Raises:
        RunDirError: naming the file, if the text is not JSON.
    """
    try:
        return json.loads(text, parse_constant=_no_constant)
    except (ValueError, RecursionError) as err:  # JSONDecodeError is a ValueError
        raise RunDirError(f"{path}: not valid JSON ({str(err)[:120]})") from None


def read_json(path: Path | str, limit: int = MAX_TEXT_BYTES) -> Any:
    """A JSON file's content (:func:`read_text`, then :func:`parse_json`).

    Raises:
        RunDirError: naming the file, if it is missing, not a regular file, too big, not UTF-8
            or not JSON.
    """
    return parse_json(read_text(path, limit, "a JSON file of a run"), path)


class _BoundedLoader(yaml.SafeLoader):
    """YAML's safe loader, refusing aliases and nesting deeper than :data:`MAX_DEPTH`."""

    depth = 0
    source = ""

    def compose_node(self, parent: Any, index: Any) -> Any:
        if self.check_event(yaml.AliasEvent):
            mark = self.peek_event().start_mark
            raise RunDirError(
                f"{self.source}: line {mark.line + 1}: YAML aliases (*name) are refused "
                "(write the values out)"
            )
        self.depth += 1
        try:
            if self.depth > MAX_DEPTH:
                mark = self.peek_event().start_mark
                raise RunDirError(
                    f"{self.source}: line {mark.line + 1}: nested deeper than {MAX_DEPTH} levels"
                )
            return super().compose_node(parent, index)
        finally:
            self.depth -= 1


def _syntax_error(path: Path | str, err: yaml.YAMLError) -> YamlSyntaxError:
    """One line for PyYAML's several-line message: file, line and column, problem, construct.

    The construct is the one the problem was found in (``while parsing a flow sequence at line
    3, column 7``).
    """

    def at(mark: Any) -> str:
        return f"line {mark.line + 1}, column {mark.column + 1}"

    problem_mark = getattr(err, "problem_mark", None)
    context, context_mark = getattr(err, "context", None), getattr(err, "context_mark", None)
    where = f"{at(problem_mark)}: " if problem_mark is not None else ""
    problem = getattr(err, "problem", None) or context or type(err).__name__
    within = f" ({context} at {at(context_mark)})" if context and context_mark else ""
    return YamlSyntaxError(f"{path}: {where}YAML syntax error: {problem}{within}")


def check_yaml_text(text: str, path: Path | str) -> Any:
    """Parse YAML text read from ``path`` safely: no aliases, nesting bounded, no NUL bytes.

    The text is composed without expanding an alias (a linear pass), so a hostile file
    ("billion laughs", 5,000 nested lists) is refused before any of it is built.

    Args:
        text: The text.
        path: Its file, for messages.

    Returns:
        The content as plain data (``yaml.safe_load``'s).

    Raises:
        RunDirError: naming the file and the line; :class:`YamlSyntaxError` if it does not parse.
    """
    if "\x00" in text:
        raise RunDirError(f"{path}: not a text file (it holds NUL bytes); a config is YAML")
    loader = _BoundedLoader(text)
    loader.source = str(path)
    try:
        return loader.get_single_data()
    except yaml.YAMLError as err:
        raise _syntax_error(path, err) from None
    except RecursionError:
        raise RunDirError(f"{path}: nested too deeply") from None
    finally:
        loader.dispose()


def read_yaml_text(path: Path | str, limit: int = MAX_YAML_BYTES) -> str:
    """A YAML file's text, checked by :func:`check_yaml_text` (for a parser of its own).

    OmegaConf reads a config's text with its own YAML resolvers (``1e-3`` is a float there);
    it parses the text returned here, which has passed every check of :func:`read_yaml`.

    Raises:
        RunDirError: as :func:`read_yaml`.
    """
    text = read_text(path, limit, "a config file (a larger team: system=random with n_robots)")
    check_yaml_text(text, path)
    return text


def read_config(path: Path | str, limit: int = MAX_YAML_BYTES) -> DictConfig | ListConfig:
    """A YAML config as OmegaConf reads it (its resolvers), after :func:`read_yaml`'s checks.

    Args:
        path: The file (a run dir's ``.hydra/*.yaml``, a sweep's ``multirun.yaml``).
        limit: The most bytes it may hold.

    Returns:
        What ``OmegaConf.load`` would return.

    Raises:
        RunDirError: as :func:`read_yaml`, or if OmegaConf refuses the content.
    """
    from omegaconf import OmegaConf

    text = read_yaml_text(path, limit)
    try:
        return OmegaConf.create(text)
    except Exception as err:  # OmegaConf raises several types
        raise RunDirError(f"{path}: not a readable YAML config ({str(err)[:120]})") from None


def read_yaml(path: Path | str, limit: int = MAX_YAML_BYTES) -> Any:
    """A YAML file's content as plain data, read safely (:func:`check_yaml_text`).

    Args:
        path: The file.
        limit: The most bytes it may hold.

    Returns:
        The content (``yaml.safe_load``'s).

    Raises:
        RunDirError: naming the file, if it is not a regular file, too big, not UTF-8 text, uses
            aliases or nests too deeply; :class:`YamlSyntaxError` naming the line if it does not
            parse.
    """
    text = read_text(path, limit, "a config file (a larger team: system=random with n_robots)")
    return check_yaml_text(text, path)


def read_csv_numbers(
    path: Path | str,
    columns: Sequence[str],
    *,
    key: str | None = None,
    limit: int = MAX_TEXT_BYTES,
) -> list[tuple[float, ...]]:
    """The numbers of some columns of a CSV file with a header row, one tuple per row.

    Args:
        path: The file.
        columns: The columns to read, in the order of the tuples.
        key: A column whose empty cell marks a row that is not data (skipped).
        limit: The most bytes it may hold.

    Returns:
        One tuple per data row.

    Raises:
        RunDirError: naming the file, if it is unreadable, lacks a column, or a cell is not a
            number (naming its line and column).
    """
    text = read_text(path, limit, "a CSV file of a run")
    reader = csv.DictReader(io.StringIO(text, newline=""))
    rows = []
    try:
        missing = [c for c in columns if c not in (reader.fieldnames or [])]
        if missing and reader.fieldnames:
            raise RunDirError(f"{path}: no column {short_list(missing)}")
        for row in reader:
            if key is not None and row.get(key) in (None, ""):
                continue
            values = []
            for column in columns:
                cell = row.get(column) or ""
                try:
                    value = float(cell)
                except ValueError:
                    value = math.nan
                if not math.isfinite(value):
                    shown = f"{cell[:40]!r}" if cell else "(empty)"
                    raise RunDirError(
                        f"{path}: line {reader.line_num}: {column} {shown} is not a number"
                    )
                values.append(value)
            rows.append(tuple(values))
    except csv.Error as err:
        raise RunDirError(f"{path}: line {reader.line_num}: not CSV ({err})") from None
    return rows


# ---------------------------------------------------------------------------------- arrays
def machine_memory() -> int:
    """Bytes of memory of this machine: no array larger than this can be read."""
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):  # not POSIX
        return 2**40


# numpy dtype kinds, as messages name them
KINDS = {"f": "real float", "i": "integer", "u": "unsigned integer", "b": "bool", "U": "text"}


@dataclass(frozen=True)
class ArraySpec:
    """What one saved array must be: a learner declares one per array of its state file.

    Attributes:
        shape: The shape; ``None`` on an axis: any length (a table's rows, which grow).
        kinds: numpy dtype kinds allowed (``"f"`` real floats, ``"i"`` signed integers, ``"U"``
            text...): never complex numbers or Python objects.
        dtype: The exact dtype (``np.dtype(...).str``), if one is required.
        finite: Floats hold no infinity (NaN is never allowed).
        low: Every value is at least this.
        magnitude: Every value's absolute value is at most this.
        names: The exact content of a text array (the names of the weights).
        meaning: What the array is, for messages (``"the weights"``).
    """

    shape: tuple[int | None, ...]
    kinds: str = "f"
    dtype: str | None = None
    finite: bool = True
    low: float | None = None
    magnitude: float | None = None
    names: tuple[str, ...] | None = None
    meaning: str | None = None

    @classmethod
    def like(cls, array: np.ndarray, *, grows: bool = False, **more: Any) -> ArraySpec:
        """The spec of arrays like ``array``: its dtype and shape (rows free if ``grows``)."""
        shape = (None, *array.shape[1:]) if grows else array.shape
        return cls(shape, kinds=array.dtype.kind, dtype=array.dtype.str, **more)

    def max_itemsize(self) -> int:
        """The largest bytes per item an array of this spec can have."""
        if self.dtype is not None:
            return np.dtype(self.dtype).itemsize
        if self.names is not None:
            return 4 * max((len(n) for n in self.names), default=1)  # UTF-32
        if "U" in self.kinds:
            return 4 * MAX_NAME_LENGTH
        return 16  # a float128

    def max_bytes(self) -> int | None:
        """The most bytes an array of this spec takes (None: its rows are free)."""
        if any(n is None for n in self.shape):
            return None
        return math.prod(self.shape) * self.max_itemsize()  # type: ignore[arg-type]

    def describe(self) -> str:
        """``"real float of shape (358,)"``, as messages show it."""
        shape = tuple("rows" if n is None else n for n in self.shape)
        if self.dtype is not None:
            kind = np.dtype(self.dtype).name
        else:
            kind = " or ".join(KINDS.get(k, k) for k in self.kinds)
        return f"{kind} of shape {shape}"


def _check_header(
    name: str,
    shape: tuple[int, ...],
    dtype: np.dtype,
    spec: ArraySpec,
    source: str,
    error: type[UserError],
) -> None:
    """Dtype, shape and size declared by an npy header, before its data is read.

    The bytes declared are bounded by the spec's (its shape is fixed), else by the machine's
    memory (a table's rows).
    """
    name = f"{name} ({spec.meaning})" if spec.meaning else name
    if dtype.hasobject:
        raise error(f"{source}: {name} holds Python objects (pickled data), never loaded")
    if dtype.kind not in spec.kinds or (spec.dtype is not None and dtype != np.dtype(spec.dtype)):
        raise error(f"{source}: {name} has dtype {dtype}, expected {spec.describe()}")
    fits = len(shape) == len(spec.shape) and all(
        want is None or got == want for got, want in zip(shape, spec.shape, strict=False)
    )
    if not fits:
        raise error(f"{source}: {name} has shape {shape}, expected {spec.describe()}")
    size = math.prod(shape) * dtype.itemsize
    bound = spec.max_bytes() or machine_memory()
    if size > bound:
        raise error(
            f"{source}: {name} declares {size:,} bytes (shape {shape}), more than the "
            f"{bound:,} it may take"
        )


def _check_values(
    name: str, array: np.ndarray, spec: ArraySpec, source: str, error: type[UserError]
) -> None:
    """The values of an array against its spec: finite floats, bounds, names."""
    name = f"{name} ({spec.meaning})" if spec.meaning else name
    if array.dtype.kind == "f":
        bad = np.isnan(array) | (np.isinf(array) if spec.finite else False)
        if bad.any():
            raise error(f"{source}: {name} holds NaN or infinite values")
    if not array.size:
        return
    if spec.low is not None and array.min() < spec.low:
        raise error(f"{source}: {name} holds {array.min().item()!r}, must be >= {spec.low:g}")
    # compared as Python floats: a narrow float (float16) never holds the bound, nor warns
    if spec.magnitude is not None and float(np.abs(array).max()) > spec.magnitude:
        largest = array.flat[np.abs(array).argmax()].item()
        raise error(f"{source}: {name} holds {largest!r}, must be within +-{spec.magnitude:g}")
    if spec.names is not None and tuple(array.tolist()) != spec.names:
        raise error(
            f"{source}: {name} names {short_list(array.tolist())}, expected "
            f"{short_list(spec.names)}"
        )


def check_arrays(
    arrays: Mapping[str, np.ndarray],
    schema: Mapping[str, ArraySpec],
    source: Path | str,
    error: type[UserError] = RunDirError,
) -> None:
    """Arrays, read or about to be saved, against a learner's schema: names, dtypes, shapes, values.

    Args:
        arrays: The arrays by name.
        schema: What they must be (:class:`ArraySpec` by name).
        source: Their file, or what made them (``"net-ES after ES step 7"``), for messages.
        error: The error to raise.

    Raises:
        RunDirError: (or ``error``) naming the source, the array and the first fault.
    """
    _check_names(arrays, schema, str(source), error)
    for name, spec in schema.items():
        array = np.asarray(arrays[name])
        _check_header(name, array.shape, array.dtype, spec, str(source), error)
        _check_values(name, array, spec, str(source), error)


def _check_names(
    found: Any, schema: Mapping[str, Any], source: str, error: type[UserError] = RunDirError
) -> None:
    missing = [name for name in schema if name not in found]
    unknown = [name for name in found if name not in schema]
    if missing or unknown:
        parts = [f"lacks {short_list(missing)}"] if missing else []
        parts += [f"holds unknown {short_list(unknown)}"] if unknown else []
        raise error(
            f"{source}: {' and '.join(parts)} (this run's learner has {short_list(schema)}: "
            "saved for another system, partition or learner?)"
        )


def _read_member(
    archive: zipfile.ZipFile, info: zipfile.ZipInfo, spec: ArraySpec, path: str
) -> np.ndarray:
    """One npy member of an archive: header checked, then exactly its declared bytes read."""
    name = info.filename.removesuffix(".npy")
    with archive.open(info) as member:
        version = np.lib.format.read_magic(member)
        if version == (1, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_1_0(member)
        elif version == (2, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_2_0(member)
        else:
            raise RunDirError(f"{path}: {name}: npy format {version} is not read")
        _check_header(name, shape, dtype, spec, path, RunDirError)
        array = np.empty(shape[::-1] if fortran else shape, dtype)
        view = memoryview(array.reshape(-1).view(np.uint8)) if array.size else memoryview(b"")
        done = 0
        while done < len(view):
            count = member.readinto(view[done:])
            if not count:
                raise RunDirError(f"{path}: {name}: truncated")
            done += count
        if member.read(1):
            raise RunDirError(f"{path}: {name}: more data than its header declares")
    return array.T if fortran else array


def read_arrays(
    path: Path | str,
    schema: Mapping[str, ArraySpec],
    *,
    limit: int | None = None,
    what: str = "such a file",
) -> dict[str, np.ndarray]:
    """The arrays of an npz file (``np.savez``), checked against a schema; nothing unpickled.

    Each member's npy header is checked (name, dtype, shape, declared bytes) before its data is
    read; the data read is exactly what the header declares; the values are then checked
    (:func:`check_arrays`).

    Args:
        path: The file.
        schema: The arrays it must hold, by name.
        limit: The most bytes the file may hold; default: what the schema's arrays take (if
            every shape is fixed), else the machine's memory.
        what: The kind of file, for messages (``"a net_es.npz of this learner"``).

    Returns:
        ``{name: array}``.

    Raises:
        RunDirError: naming the file (and the array) at the first fault.
    """
    sizes = [spec.max_bytes() for spec in schema.values()]
    if limit is None:
        fixed = None if None in sizes else sum(sizes) + NPY_OVERHEAD * (len(sizes) + 1)
        limit = min(fixed or machine_memory(), machine_memory())
    with open_bounded(path, limit, what) as handle:
        if handle.read(len(ZIP_MAGIC)) != ZIP_MAGIC:
            raise RunDirError(f"{path}: not an npz archive (no zip header): not {what}")
        handle.seek(0)
        arrays: dict[str, np.ndarray] = {}
        try:
            with zipfile.ZipFile(handle) as archive:
                infos = archive.infolist()
                names = [info.filename.removesuffix(".npy") for info in infos]
                if len(set(names)) != len(names) or any(
                    not info.filename.endswith(".npy") for info in infos
                ):
                    raise RunDirError(f"{path}: not an npz archive of numpy arrays: not {what}")
                _check_names(names, schema, str(path))
                for info, name in zip(infos, names, strict=True):
                    arrays[name] = _read_member(archive, info, schema[name], str(path))
        except RunDirError:
            raise
        except ZIP_FAULTS as err:
            raise RunDirError(
                f"{path}: truncated or damaged ({type(err).__name__}: {str(err)[:80]})"
            ) from None
    for name, spec in schema.items():
        _check_values(name, arrays[name], spec, str(path), RunDirError)
    return arrays


# ---------------------------------------------------------------------------------- tensors
def tensor_bytes(tree: Any) -> tuple[int, int]:
    """``(bytes, count)`` of the tensors in nested dicts, lists and tuples."""
    import torch

    if isinstance(tree, torch.Tensor):
        return tree.numel() * tree.element_size(), 1
    items = (
        tree.values() if isinstance(tree, dict) else tree if isinstance(tree, list | tuple) else ()
    )
    total = count = 0
    for item in items:
        size, n = tensor_bytes(item)
        total, count = total + size, count + n
    return total, count


def tensor_file_limit(*trees: Any, copies: int = 1) -> int:
    """The most bytes a torch file of ``copies`` times these tensors may take (with margin)."""
    size, count = tensor_bytes(list(trees))
    return 2 * copies * size + PT_OVERHEAD + PT_PER_TENSOR * copies * count


def read_tensors(
    path: Path | str, device: torch.device, limit: int, what: str = "a torch file of this package"
) -> Any:
    """``torch.load(weights_only=True)`` of a regular file of at most ``limit`` bytes.

    Args:
        path: The file.
        device: Where the tensors go.
        limit: The most bytes it may hold (:func:`tensor_file_limit`).
        what: The kind of file, for messages.

    Returns:
        The loaded content (tensors, dicts, lists and plain values only).

    Raises:
        RunDirError: naming the file, if it is missing, not a regular file, too big, truncated
            or not a tensor file (the message never suggests loading it unsafely).
    """
    import torch

    with open_bounded(path, limit, what) as handle:
        if handle.read(len(ZIP_MAGIC)) != ZIP_MAGIC:
            raise RunDirError(f"{path}: not a zip archive: not {what}")
        handle.seek(0)
        try:
            return torch.load(handle, map_location=device, weights_only=True)
        except RunDirError:
            raise
        except Exception as err:  # torch raises many types; its message suggests unsafe loading
            raise RunDirError(
                f"{path}: truncated, damaged or not {what} ({type(err).__name__})"
            ) from None

"""Run directories as data: their config and learner state read safely; training checkpoints.

A run dir may come from anyone (a shared drive, a download), so reading one never executes what
it says. :func:`read_run_config` accepts a ``.hydra/config.yaml`` only if its learner is a
:class:`~mrta_rl.learners.Learner` class of this package with plain scalar or list
hyperparameters, its logger a curve logger of this package, and everything else plain data (no
``_target_``, no interpolation); anything else is refused with a message naming the key.
:func:`load_learner` restores saved tables or weights through the learner's own ``load``, which
checks them against the learner built for the run; any failure names the file and what is wrong.

Training checkpoints (:class:`TrainingCheckpoint`) hold everything a run needs to continue
exactly where it stopped: the learner state (``save``), what ``save`` lacks
(:meth:`Learner.checkpoint_state`: generators, counters; neural: optimizer, target networks,
replay buffer), the training loop's counters and the curve so far. They are taken at episode
boundaries, where every training copy starts a new episode, so the env is fully given by its
seeds and the number of episodes played. Each checkpoint is a version folder
``checkpoint/<episode>/``, written in full under a temporary name, synced to disk and renamed;
then the pointer file ``checkpoint/latest`` is replaced (one atomic rename) to name it, and only
then are older versions removed. A crash at any instant leaves the pointer naming a complete
checkpoint: the newest one written completely (:func:`latest_checkpoint`).

Import direction: ``train`` -> ``evaluate``, ``train`` -> ``checkpoint``; this module imports no
other runner module.
"""

from __future__ import annotations

import importlib
import json
import logging
import os
import secrets
import shutil
import signal
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import DictConfig, OmegaConf

from mrta_rl.config import UserError
from mrta_rl.learners import Learner
from mrta_rl.metrics.logger import CSVLogger
from mrta_rl.systems.files import check_yaml_file

logger = logging.getLogger(__name__)

CONFIG_FILE = Path(".hydra") / "config.yaml"
HYDRA_FILE = Path(".hydra") / "hydra.yaml"
LEARNER_DIR = "learner"  # final learner state (Learner.save)
CHECKPOINT_DIR = "checkpoint"  # training checkpoints: version folders and the pointer file
POINTER_FILE = "latest"  # in CHECKPOINT_DIR: the name of the current version folder
METRICS_FILE = "metrics.json"
EVAL_METRICS_FILE = "eval_metrics.json"  # a re-evaluation (scripts/evaluate.py) beside metrics.json
REFUSED_FILE = "refused.json"  # instead of metrics.json: the run was refused up front, and why
TEAM_FILE = "team.json"  # in a learner state folder: the team it was trained on (save_learner)
STATE_FILE = "training.json"  # loop counters, curve so far, learner checkpoint_state
PACKAGE = "mrta_rl."
SCALARS = (str, int, float, bool, type(None))


class RunDirError(UserError):
    """A run dir that cannot be used; the message names the file and what is wrong."""


def write_json(path: Path, payload: dict[str, Any], *, exclusive: bool = False) -> None:
    """Write JSON atomically (temporary file then rename), so a file is never half-written.

    Args:
        path: The file.
        payload: JSON-serialisable content (no NaN).
        exclusive: Never replace an existing file (the rename is a hard link that fails if
            ``path`` exists): the results of a run are never overwritten by another run.

    Raises:
        RunDirError: if ``exclusive`` and ``path`` exists.
    """
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(payload, indent=2, allow_nan=False) + "\n")
    if not exclusive:
        os.replace(tmp, path)
        return
    try:
        os.link(tmp, path)
    except FileExistsError:
        raise RunDirError(
            f"{path} was written by another run meanwhile; this run's results are kept in {tmp}"
        ) from None
    tmp.unlink()


# ---------------------------------------------------------------------------------- run dirs
RUN_ID = f"{os.getpid() % 0x10000:04x}{secrets.token_hex(2)}"  # this process's run dir suffix


def register_resolvers() -> None:
    """OmegaConf resolvers of the run dir pattern in ``conf/config.yaml`` (``hydra.run.dir``).

    * ``${run_id:}``: a short id unique to this process (pid and random bits): runs started in
      the same second get different dirs.
    * ``${resume_or:<resume>,<default>}``: the ``resume`` dir if given, else ``default``.
    * ``${unless_resume:<resume>,<value>}``: ``value``, or null when resuming (so a resumed run
      does not overwrite its ``.hydra/`` snapshot with the resume command's config).
    """
    resolvers = {
        "run_id": lambda: RUN_ID,
        "resume_or": lambda resume, default: str(resume) if resume else default,
        "unless_resume": lambda resume, value: None if resume else value,
    }
    for name, function in resolvers.items():
        if not OmegaConf.has_resolver(name):
            OmegaConf.register_new_resolver(name, function)


# ---------------------------------------------------------------------------------- config
def package_class(target: Any, base: type, what: str, where: str) -> type:
    """The class ``target`` names, if it is a subclass of ``base`` defined in this package.

    Only modules of ``mrta_rl`` are imported, so a tampered name runs no foreign code.

    Args:
        target: The ``_target_`` value.
        base: The required base class.
        what: What the class is for (in messages: ``learner``, ``logger``).
        where: ``<file>: <key>`` for messages.

    Returns:
        The class.

    Raises:
        RunDirError: if the name is not a ``mrta_rl`` class derived from ``base``.
    """
    if not isinstance(target, str) or not target.startswith(PACKAGE) or "." not in target:
        raise RunDirError(f"{where}: {target!r} is not a {what} class of {PACKAGE.rstrip('.')}")
    module_name, _, name = target.rpartition(".")
    try:
        cls = getattr(importlib.import_module(module_name), name)
    except (ImportError, AttributeError) as err:
        raise RunDirError(f"{where}: unknown {what} class {target!r} ({err})") from err
    if not (isinstance(cls, type) and issubclass(cls, base)):
        raise RunDirError(f"{where}: {target!r} is not a {what} ({base.__name__} subclass)")
    return cls


def _check_data(value: Any, key: str, source: Path) -> None:
    """Plain data only: mappings without special keys, lists, scalars without interpolation."""
    if isinstance(value, dict):
        for k, v in value.items():
            if str(k).startswith("_"):
                raise RunDirError(
                    f"{source}: {key}.{k}: special key refused (a run dir is data, never code)"
                )
            _check_data(v, f"{key}.{k}" if key else str(k), source)
    elif isinstance(value, list):
        for i, item in enumerate(value):
            _check_data(item, f"{key}[{i}]", source)
    elif isinstance(value, str) and "${" in value:
        raise RunDirError(f"{source}: {key}: interpolation {value!r} refused (plain values only)")
    elif not isinstance(value, SCALARS):
        raise RunDirError(f"{source}: {key}: unexpected value {value!r}")


def _check_component(block: Any, key: str, base: type, source: Path, *, flat: bool) -> None:
    """A ``_target_`` block: a package class, ``_partial_: true``, plain (scalar/list) settings."""
    if not isinstance(block, dict):
        raise RunDirError(f"{source}: {key}: expected a mapping with _target_, got {block!r}")
    package_class(block.get("_target_"), base, key, f"{source}: {key}._target_")
    if block.get("_partial_") is not True:
        raise RunDirError(f"{source}: {key}._partial_: must be true")
    for name, value in block.items():
        if name in ("_target_", "_partial_"):
            continue
        if flat and isinstance(value, dict):
            raise RunDirError(
                f"{source}: {key}.{name}: a mapping is refused; hyperparameters are plain scalars "
                f"or lists (got {value!r})"
            )
        _check_data({name: value}, key, source)


def check_run_config(config: dict[str, Any], source: Path) -> None:
    """Refuse anything in a run's config that is not plain data (module docstring).

    Args:
        config: The config as a plain container (``resolve=False``).
        source: Its file, for messages.

    Raises:
        RunDirError: naming the first offending key.
    """
    if not isinstance(config, dict):
        raise RunDirError(f"{source}: not a mapping of settings")
    for key in ("learner", "logger"):  # the rest is checked by validate_config
        if key not in config:
            raise RunDirError(f"{source}: {key}: missing")
    for key, value in config.items():
        if key == "learner":
            _check_component(value, "learner", Learner, source, flat=True)
        elif key == "logger":
            _check_component(value, "logger", CSVLogger, source, flat=True)
        else:
            _check_data({key: value}, "", source)


def read_run_config(run_dir: Path | str) -> DictConfig:
    """The run's ``.hydra/config.yaml``, checked to hold only plain data (module docstring).

    Args:
        run_dir: A run dir of ``scripts/train.py``.

    Returns:
        The config, safe to build the run from.

    Raises:
        RunDirError: if the file is missing, unreadable or holds anything but plain data (its
            settings are checked when the run is built: ``train.build_saved_run``).
    """
    run_dir = Path(run_dir)
    path = run_dir / CONFIG_FILE
    if not path.is_file():
        raise RunDirError(f"{run_dir} is not a run dir of scripts/train.py: no {path}")
    check_yaml_file(path)  # size, encoding, depth, aliases: before OmegaConf expands anything
    try:
        cfg = OmegaConf.load(path)
    except Exception as err:  # YAML and OmegaConf raise several types
        raise RunDirError(f"{path}: not a readable YAML config ({err})") from err
    check_run_config(OmegaConf.to_container(cfg, resolve=False), path)
    fill_settings_before(cfg)
    return cfg  # type: ignore[return-value]


def fill_settings_before(config: DictConfig | dict[str, Any]) -> None:
    """Give a run made before a learner setting existed the value it ran with (in place).

    Such a run's config has no key for the setting, and building its learner from the config
    would take today's declared default; where that default has moved since, the class's
    ``settings_before`` names what the run used (semi-CQL's ``state: system``). Every reader of
    a run's config goes through here: evaluation and resume (:func:`read_run_config`) and the
    reports (``reports.collect``).
    """
    from mrta_rl.runners.validation import learner_class  # imports the learner (and its deps)

    learner = config.get("learner")
    try:
        cls = learner_class(learner)
    except UserError:  # not a learner config: the run's own checks name it when it is built
        return
    for key, value in getattr(cls, "settings_before", {}).items():
        if key not in learner:
            learner[key] = value


def run_choices(run_dir: Path) -> dict[str, str]:
    """Config-group choices recorded in ``.hydra/hydra.yaml`` (``learner`` -> ``greedy``)."""
    path = Path(run_dir) / HYDRA_FILE
    if not path.is_file():
        return {}
    check_yaml_file(path)  # a hostile file is refused; a merely damaged one loses the names
    try:
        choices = OmegaConf.select(OmegaConf.load(path), "hydra.runtime.choices", default={})
        return {str(k): str(v) for k, v in dict(choices).items() if isinstance(v, str | int)}
    except Exception as err:  # a damaged hydra.yaml only loses the names
        logger.warning("%s: config-group choices unreadable (%s)", path, err)
        return {}


# ---------------------------------------------------------------------------------- learner state
def team_record(learner: Learner) -> dict[str, Any]:
    """The team a learner state belongs to: robots, task types and willingness, in order.

    Tables and weights are indexed by robot and task type, so a state of another team of the
    same shape would load and then act for robots that cannot do what it chooses.
    """
    system = learner.env.system
    return {
        "robots": list(system.robots),
        "task_types": list(system.task_types),
        "willingness": np.asarray(system.willingness).tolist(),
    }


def save_learner(learner: Learner, directory: Path) -> None:
    """``learner.save`` into ``directory``, with the team it was trained on (:data:`TEAM_FILE`)."""
    learner.save(directory)
    write_json(directory / TEAM_FILE, team_record(learner))


def _check_team(learner: Learner, directory: Path) -> None:
    """Refuse a learner state saved for another team, naming the first robot that differs."""
    path = directory / TEAM_FILE
    try:
        saved = json.loads(path.read_text())
    except FileNotFoundError:
        raise RunDirError(f"{path}: missing (the team the learner state was trained on)") from None
    except (OSError, ValueError) as err:
        raise RunDirError(f"{path}: not readable JSON ({err})") from None
    expected = team_record(learner)
    if not isinstance(saved, dict) or set(saved) != set(expected):
        raise RunDirError(f"{path}: expected the keys {sorted(expected)}")
    for key in ("robots", "task_types"):
        if saved[key] != expected[key]:
            raise RunDirError(
                f"{path}: {key}: the learner state was trained on another team ({saved[key]!r}), "
                f"not the run's system ({expected[key]!r})"
            )
    for robot, row, want in zip(
        expected["robots"], saved["willingness"], expected["willingness"], strict=True
    ):
        if row != want:
            raise RunDirError(
                f"{path}: willingness.{robot}: the learner state was trained on another team "
                f"({row!r}), not the run's system ({want!r})"
            )


def load_learner(learner: Learner, directory: Path) -> None:
    """Restore a saved learner state into the learner built for the run, or refuse it.

    The state must have been saved for the run's team (:func:`save_learner`), and the learner's
    ``load`` checks the files against itself (keys, shapes, dtypes, consistency); any problem
    names the file.

    Args:
        learner: The learner built for the run.
        directory: Folder written by :func:`save_learner`.

    Raises:
        RunDirError: if the folder is missing or its content does not fit the learner.
    """
    if not directory.is_dir():
        raise RunDirError(f"no saved learner state: {directory} is missing")
    _check_team(learner, directory)
    try:
        learner.load(directory)
    except (OSError, ValueError, KeyError, RuntimeError, EOFError) as err:
        message = str(err)
        if str(directory) not in message:
            message = f"{directory}: {message}"
        raise RunDirError(f"saved learner state refused: {message}") from err


# ---------------------------------------------------------------------------------- checkpoints
def latest_checkpoint(run_dir: Path | str) -> Path | None:
    """The run's current training checkpoint: the version folder the pointer file names.

    Args:
        run_dir: A run dir of ``scripts/train.py``.

    Returns:
        The checkpoint folder (holding ``training.json``, ``learner/`` and the loop's files),
        or None if the run has no checkpoint.

    Raises:
        RunDirError: if the pointer file is damaged or names no complete checkpoint.
    """
    root = Path(run_dir) / CHECKPOINT_DIR
    pointer = root / POINTER_FILE
    if not pointer.is_file():  # a checkpoint written before versions existed has no pointer
        return root if (root / STATE_FILE).is_file() else None
    name = pointer.read_text().strip()
    if not name.isdigit():
        raise RunDirError(f"{pointer}: not a checkpoint version (got {name[:40]!r})")
    version = root / name
    if not (version / STATE_FILE).is_file():
        raise RunDirError(f"{pointer}: names {version}, which holds no {STATE_FILE}")
    return version


def require_checkpoint(run_dir: Path | str) -> Path:
    """The run's current training checkpoint (:func:`latest_checkpoint`), or refuse to resume.

    Raises:
        RunDirError: if the run has no checkpoint or its pointer is damaged.
    """
    version = latest_checkpoint(run_dir)
    if version is None:
        raise RunDirError(f"cannot resume: {run_dir} holds no training checkpoint")
    return version


def _sync(path: Path) -> None:
    """Flush a file, or a folder's entries (the renames in it), to disk."""
    fd = os.open(path, os.O_RDONLY | (os.O_DIRECTORY if path.is_dir() else 0))
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _sync_tree(folder: Path) -> None:
    """Flush every file and folder under ``folder`` to disk (before it is renamed into place)."""
    for path in [*sorted(folder.rglob("*"), reverse=True), folder]:
        _sync(path)


class TrainingInterrupted(Exception):  # noqa: N818 - an event, not an error of the program
    """Training stopped by a signal (Ctrl-C, or SIGTERM from a scheduler) after saving a checkpoint.

    Attributes:
        checkpoint: The checkpoint folder, or None if none could be written.
        signum: The signal that stopped the run; the process exits with ``128 + signum``.
    """

    def __init__(self, checkpoint: Path | None, signum: int = signal.SIGINT) -> None:
        super().__init__(f"training interrupted; checkpoint: {checkpoint}")
        self.checkpoint = checkpoint
        self.signum = int(signum)


class TrainingCheckpoint:
    """Periodic, atomic checkpoints of a training loop at episode boundaries, and resuming.

    A training loop creates one, asks :meth:`restore` for the loop state to continue from (None
    for a fresh run), and calls :meth:`episode_end` after every episode with its loop state; the
    call saves every ``train.checkpoint_every`` episodes, and at once after a first Ctrl-C or
    SIGTERM (see :meth:`catch_interrupt`), then raises :class:`TrainingInterrupted`.

    Args:
        learner: The run's learner.
        run_dir: The run dir; the checkpoints are in ``<run_dir>/checkpoint`` (module docstring).
        every: Episodes between checkpoints (0: only on Ctrl-C or SIGTERM).
        resume: Continue from the run dir's checkpoint.
        episodes: The run's ``train.episodes``: a checkpoint follows at most that many.
    """

    def __init__(
        self, learner: Learner, run_dir: Path, every: int, resume: bool, episodes: int
    ) -> None:
        self.learner = learner
        self.episodes = int(episodes)
        self.run_dir = Path(run_dir)
        self.root = self.run_dir / CHECKPOINT_DIR
        self.path: Path | None = None  # the current checkpoint: restored or last saved
        self.every = int(every)
        self.resume = resume
        self.stop_requested = False
        self.stop_signal: int = signal.SIGINT  # the signal that asked to stop (exit code)
        self.saved_episode = 0  # episode of the last checkpoint

    def restore(self) -> dict[str, Any] | None:
        """The loop state of the checkpoint, with the learner restored; None for a fresh run.

        Returns:
            The ``loop`` dict given to :meth:`save`, or None when not resuming.

        Raises:
            RunDirError: if resuming and the checkpoint is missing or does not fit the run.
        """
        if not self.resume:
            return None
        version = require_checkpoint(self.run_dir)
        self.path = version  # the loop reads its own files from here
        state_path = version / STATE_FILE
        from mrta_rl.runners.run_files import read_training_state  # it imports this module

        loop, learner_state = read_training_state(state_path, self.learner.kind, self.episodes)
        load_learner(self.learner, version / LEARNER_DIR)
        try:
            self.learner.restore_state(learner_state, version)
        except Exception as err:  # the learner's own checks, or a state it cannot even read
            raise RunDirError(f"{state_path}: learner: state refused ({err!r})") from err
        logger.info("resuming from %s after episode %d", version, loop["episode"])
        self.saved_episode = loop["episode"]
        return loop

    def save(self, loop: dict[str, Any], files: Callable[[Path], None] | None = None) -> Path:
        """Write a new checkpoint version, then point to it (atomic at every instant).

        The version folder is written in full under a temporary name, synced and renamed; the
        pointer file is replaced in one rename; older versions are removed last (module
        docstring). Temporary names carry the pid.

        Args:
            loop: The training loop's state (JSON: counters, curve rows, ``episode``).
            files: Writes the loop's own files (replay buffer...) into the folder it is given.

        Returns:
            The checkpoint folder (``<run dir>/checkpoint/<episode>``).
        """
        name = str(int(loop["episode"]))
        tmp = self.root / f".{name}.{os.getpid()}.tmp"
        version = self.root / name
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir(parents=True)
        save_learner(self.learner, tmp / LEARNER_DIR)
        state = {"loop": loop, "learner": self.learner.checkpoint_state(tmp)}
        if files is not None:
            files(tmp)
        write_json(tmp / STATE_FILE, state)
        _sync_tree(tmp)
        if version.exists():  # left by a crash before its pointer moved: never pointed to
            shutil.rmtree(version)
        os.rename(tmp, version)
        _sync(self.root)
        pointer_tmp = self.root / f".{POINTER_FILE}.{os.getpid()}.tmp"
        with open(pointer_tmp, "w") as file:
            file.write(name + "\n")
            file.flush()
            os.fsync(file.fileno())
        os.replace(pointer_tmp, self.root / POINTER_FILE)  # the checkpoint is complete here
        _sync(self.root)
        self.path = version
        self.saved_episode = loop["episode"]
        for entry in self.root.iterdir():  # older versions and leftovers of crashed saves
            if entry.name in (name, POINTER_FILE):
                continue
            if entry.is_dir():
                shutil.rmtree(entry, ignore_errors=True)
            else:
                entry.unlink(missing_ok=True)
        # logged once the checkpoint is complete: tests and job scripts wait for this line
        logger.info("checkpoint after episode %d in %s", loop["episode"], version)
        return version

    def episode_end(
        self, loop: dict[str, Any], last: bool, files: Callable[[Path], None] | None = None
    ) -> None:
        """Save when due (every ``every`` episodes), or after a stop signal (then raise).

        Call it only where the loop can continue from: every training copy between episodes.

        Args:
            loop: The loop state after the episode (``episode`` = episodes done).
            last: True after the last episode (nothing to save then: the run finishes).
            files: See :meth:`save`.

        Raises:
            TrainingInterrupted: after saving, if Ctrl-C was pressed or SIGTERM received.
        """
        if last:
            return
        if self.stop_requested:
            raise TrainingInterrupted(self.save(loop, files), self.stop_signal)
        if self.every > 0 and loop["episode"] - self.saved_episode >= self.every:
            self.save(loop, files)

    def finish(self) -> None:
        """Remove the checkpoint once the run has written its results (it is complete)."""
        shutil.rmtree(self.root, ignore_errors=True)

    @contextmanager
    def catch_interrupt(self) -> Iterator[None]:
        """First Ctrl-C or SIGTERM: finish the episode, save, stop; a second one: stop at once.

        SIGTERM is what schedulers (Slurm) send before killing a job, so a preempted run saves
        its checkpoint and resumes like one stopped with Ctrl-C.

        Yields:
            Nothing; the SIGINT and SIGTERM handlers are in place inside the block.
        """
        stop_signals = (signal.SIGINT, signal.SIGTERM)
        try:
            previous = {signum: signal.getsignal(signum) for signum in stop_signals}
            for signum in stop_signals:
                signal.signal(signum, self._on_interrupt)
        except ValueError:  # not the main thread: keep the default behaviour
            yield
            return
        try:
            yield
        except KeyboardInterrupt:
            last = latest_checkpoint(self.run_dir)
            raise TrainingInterrupted(last, self.stop_signal) from None
        finally:
            for signum, handler in previous.items():
                signal.signal(signum, handler)

    def _on_interrupt(self, signum: int, frame: Any) -> None:
        if self.stop_requested:
            raise KeyboardInterrupt
        self.stop_requested = True
        self.stop_signal = signum
        name = signal.Signals(signum).name
        logger.warning(
            "%s: saving a checkpoint at the end of this episode (%s again to stop now, keeping "
            "the last checkpoint)",
            "interrupted" if signum == signal.SIGINT else f"terminated ({name})",
            "Ctrl-C" if signum == signal.SIGINT else name,
        )

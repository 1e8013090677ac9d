"""Training checkpoints: versioned folders, a pointer file, and resuming from them.

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

"""

from __future__ import annotations

import importlib
import logging
import os
import shutil
import signal
import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import Any

from mrta_rl.checked_files import read_text
from mrta_rl.learners import Learner
from mrta_rl.metrics.usage import RunResources
from mrta_rl.run_layout import (
    CHECKPOINT_DIR,
    LEARNER_DIR,
    POINTER_FILE,
    STATE_FILE,
    RunDirError,
    read_training_state,
    write_json,
)
from mrta_rl.runners.learner_state import load_learner, save_learner

logger = logging.getLogger(__name__)
POINTER_BYTES = 64  # the pointer file holds a version folder's name: an episode number


# ---------------------------------------------------------------------------------- time spent
class LoopTime:
    """The seconds of a training loop over its run's whole life.

    The share of the processes before a resume (the checkpoint's ``loop.spent``) plus this
    process's, so that a resumed run reports the wall time and the frames per second of the
    run, not of its last process. Parts: ``collect_s`` (collection), ``train_s`` (updates).

    Args:
        spent: The restored loop state's ``spent`` block (None or absent keys: nothing).
    """

    PARTS = ("collect_s", "train_s")

    def __init__(self, spent: Mapping[str, float] | None = None) -> None:
        spent = spent or {}
        self._before = {key: float(spent.get(key, 0.0)) for key in ("wall_s", *self.PARTS)}
        self._parts = dict.fromkeys(self.PARTS, 0.0)
        self._start = time.perf_counter()

    def add(self, part: str, seconds: float) -> None:
        """Count ``seconds`` of this process in a part (``collect_s`` or ``train_s``)."""
        self._parts[part] += seconds

    def total(self, part: str) -> float:
        """Seconds of a part over the whole life."""
        return self._before[part] + self._parts[part]

    def wall(self) -> float:
        """Wall seconds of the loop over the whole life, up to now."""
        return self._before["wall_s"] + time.perf_counter() - self._start

    def spent(self) -> dict[str, float]:
        """The ``loop.spent`` block of a checkpoint taken now (``run_layout.SPENT``)."""
        return {"wall_s": self.wall(), **{part: self.total(part) for part in self.PARTS}}


# ---------------------------------------------------------------------------------- checkpoints
def loop_counters(training_loop: str) -> tuple[str, ...]:
    """The counters a training loop keeps in its checkpoints (``COUNTERS`` of its module).

    Args:
        training_loop: A learner's ``training_loop`` (``"module:function"``).
    """
    module = importlib.import_module(training_loop.partition(":")[0])
    return tuple(getattr(module, "COUNTERS", ()))


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
    if not pointer.exists():  # no save has completed: a version folder alone is not named yet
        return None
    name = read_text(pointer, POINTER_BYTES, "a checkpoint pointer").strip()
    if not name.isdigit():
        raise RunDirError(f"{pointer}: not a checkpoint version (got {name[:40]!r})")
    version = root / name
    if not (version / STATE_FILE).exists():
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
        resources: The run's wall time, CPU time and peak memory: a checkpoint records them
            (``loop.spent``), and resuming adds the checkpoint's to them.
    """

    def __init__(
        self,
        learner: Learner,
        run_dir: Path,
        every: int,
        resume: bool,
        episodes: int,
        resources: RunResources | None = None,
    ) -> None:
        self.learner = learner
        self.resources = resources
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
        loop, learner_state = read_training_state(
            state_path, loop_counters(self.learner.training_loop), self.episodes
        )
        load_learner(self.learner, version / LEARNER_DIR)
        try:
            self.learner.restore_state(learner_state, version)
        except RunDirError:  # a file of the checkpoint refused: the message names it
            raise
        except Exception as err:  # the learner's own checks, or a state it cannot even read
            raise RunDirError(f"{state_path}: learner: state refused ({err!r})") from err
        logger.info("resuming from %s after episode %d", version, loop["episode"])
        self.saved_episode = loop["episode"]
        if self.resources is not None:
            self.resources.add_before(loop.get("spent", {}))
        return loop

    def save(self, loop: dict[str, Any], files: Callable[[Path], None] | None = None) -> Path:
        """Write a new checkpoint version, then point to it (atomic at every instant).

        The version folder is written in full under a temporary name, synced and renamed; the
        pointer file is replaced in one rename; older versions are removed last (module
        docstring). Temporary names carry the pid.

        Args:
            loop: The training loop's state (JSON: counters, curve rows, ``episode``, the
                loop's ``spent`` seconds); the run's own (wall, CPU, memory) are added here.
            files: Writes the loop's own files (replay buffer...) into the folder it is given.

        Returns:
            The checkpoint folder (``<run dir>/checkpoint/<episode>``).
        """
        name = str(int(loop["episode"]))
        tmp = self.root / f".{name}.{os.getpid()}.tmp"
        version = self.root / name
        pointer_tmp = self.root / f".{POINTER_FILE}.{os.getpid()}.tmp"
        try:
            shutil.rmtree(tmp, ignore_errors=True)
            tmp.mkdir(parents=True)
            save_learner(self.learner, tmp / LEARNER_DIR)
            if self.resources is not None:
                loop = {**loop, "spent": {**loop.get("spent", {}), **self.resources.spent()}}
            state = {"loop": loop, "learner": self.learner.checkpoint_state(tmp)}
            if files is not None:
                files(tmp)
            write_json(tmp / STATE_FILE, state)
            _sync_tree(tmp)
            if version.exists():  # left by a crash before its pointer moved: never pointed to
                shutil.rmtree(version)
            os.rename(tmp, version)
            _sync(self.root)
            with open(pointer_tmp, "w") as file:
                file.write(name + "\n")
                file.flush()
                os.fsync(file.fileno())
            os.replace(pointer_tmp, self.root / POINTER_FILE)  # the checkpoint is complete here
        except BaseException:
            # a write refused (disk full, file too large...) or Ctrl-C: the pointer still names
            # the last complete checkpoint; what this save wrote goes (a renamed version folder
            # that no pointer names is removed by the next save)
            shutil.rmtree(tmp, ignore_errors=True)
            with suppress(OSError):
                pointer_tmp.unlink(missing_ok=True)
            raise
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

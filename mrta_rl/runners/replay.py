"""The neural loop's replay buffer in training checkpoints: written compactly, checked on resume.

A checkpoint's ``replay.pt`` (``torch.save``, read back with ``weights_only=True``) holds

* ``transitions``: the filled rows of the buffer's storage, in storage order, as nested dicts of
  tensors ``[rows, ...]`` (rows = ``min(frames, capacity)``; the storage's unfilled capacity is
  not written);
* ``torch_rng``: torch's generator (exploration draws and replay sampling), the state at the
  episode boundary of the checkpoint.

The writer's position follows from the frames collected (the loop's ``frames`` counter in
``training.json``): every frame is one transition, so ``frames`` were written and the next one
goes to ``frames % capacity``. On resume, the file is checked against what the learner stores
(:func:`replay_layout`, the same path from the env's specs through the learner's policy and
:meth:`~mrta_rl.learners.neural.NeuralLearner.transitions` as collected data), before anything is
built or written: a file of the wrong structure, shapes, dtypes or with NaN is refused with a
:class:`~mrta_rl.runners.checkpoint.RunDirError` naming the file and the key.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch
from tensordict import TensorDict
from torchrl.data import TensorDictReplayBuffer
from torchrl.envs.utils import ExplorationType, set_exploration_type

from mrta_rl.checked_files import PT_OVERHEAD, PT_PER_TENSOR, read_tensors
from mrta_rl.learners.neural.common import write_tensors
from mrta_rl.run_layout import RunDirError

if TYPE_CHECKING:
    from mrta_rl.envs.torchrl_env import AuctionTorchRLEnv
    from mrta_rl.learners.neural import NeuralLearner

REPLAY_FILE = "replay.pt"  # training checkpoints: replay buffer rows and torch's generator
REPLAY_KEYS = ("torch_rng", "transitions")
INDEX_KEY = "index"  # written by TensorDictReplayBuffer.extend itself: not saved

Layout = dict[tuple[str, ...], tuple[tuple[int, ...], torch.dtype]]


def replay_layout(env: AuctionTorchRLEnv, learner: NeuralLearner) -> Layout:
    """What one replayed transition of the learner holds: key -> (shape, dtype).

    Built as collected data is: the env's zero TensorDict (its specs), the greedy policy's
    actions, then the learner's :meth:`transitions`; torch's generator is left untouched.

    Args:
        env: The TorchRL view the run collects from.
        learner: The run's neural learner.

    Returns:
        Every leaf key (a tuple) with the shape of one transition and its dtype.
    """
    fake = env.fake_tensordict().to(learner.device)  # [B]
    with (
        torch.no_grad(),
        torch.random.fork_rng(devices=[]),
        set_exploration_type(ExplorationType.DETERMINISTIC),
    ):
        fake = learner.explore_policy(fake)
    rows = learner.transitions(fake.unsqueeze(-1))  # as a [B, T = 1] collector batch
    return {
        key if isinstance(key, tuple) else (key,): (tuple(value.shape[1:]), value.dtype)
        for key, value in rows.items(include_nested=True, leaves_only=True)
    }


def save_replay(buffer: TensorDictReplayBuffer, path: Path) -> None:
    """Write the buffer's filled rows and torch's generator to ``path`` (module docstring).

    Args:
        buffer: The run's replay buffer.
        path: The checkpoint's ``replay.pt``.
    """
    filled = len(buffer)
    rows = buffer[:filled].exclude(INDEX_KEY) if filled else TensorDict()
    if 0 < filled < buffer.storage.max_size:
        # a slice is a view, and torch.save writes a view's whole storage (every row): cloned.
        # A full buffer's rows are its whole storage, written as they are: a copy of a full
        # buffer would double the run's peak memory for the time of the save.
        rows = rows.clone()
    payload = {"transitions": rows.to_dict(), "torch_rng": torch.get_rng_state()}
    write_tensors(payload, path)


def _describe(value: Any) -> str:
    if isinstance(value, torch.Tensor):
        return f"a {value.dtype} tensor of shape {tuple(value.shape)}"
    return f"a {type(value).__name__}"


def _leaves(tree: Any, path: Path, prefix: tuple[str, ...] = ()) -> dict[tuple[str, ...], Any]:
    """Nested dicts -> ``{key tuple: leaf}``; a non-dict level is a leaf."""
    if not isinstance(tree, dict):
        return {prefix: tree}
    leaves: dict[tuple[str, ...], Any] = {}
    for name, value in tree.items():
        if not isinstance(name, str):
            raise RunDirError(f"{path}: transitions: key {name!r} is not a name")
        leaves.update(_leaves(value, path, (*prefix, name)))
    return leaves


def read_replay(
    path: Path, layout: Layout, frames: int, capacity: int
) -> tuple[TensorDict, torch.Tensor]:
    """Read and check a checkpoint's ``replay.pt`` against the run (module docstring).

    Args:
        path: The checkpoint's ``replay.pt``.
        layout: :func:`replay_layout` of the run.
        frames: Frames collected before the checkpoint (``training.json``'s ``loop.frames``).
        capacity: The buffer's capacity (``learner.buffer_size``).

    Returns:
        ``(rows, torch_rng)``: the stored rows ``[min(frames, capacity)]`` and torch's
        generator state, for :func:`restore_replay`.

    Raises:
        RunDirError: naming the file and the key, if the file is missing, truncated, not a
            tensor file, or its content does not fit the run.
    """
    stored = min(frames, capacity)
    row_bytes = sum(math.prod(shape) * dtype.itemsize for shape, dtype in layout.values())
    # the rows and torch's generator, twice over (with the file's own records)
    limit = 2 * stored * row_bytes + PT_OVERHEAD + PT_PER_TENSOR * (len(layout) + 1)
    try:
        payload = read_tensors(path, torch.device("cpu"), limit, "a replay buffer of this run")
    except RunDirError as err:
        raise RunDirError(f"cannot resume: {err}") from None
    if not isinstance(payload, dict) or set(payload) != set(REPLAY_KEYS):
        held = sorted(map(str, payload)) if isinstance(payload, dict) else _describe(payload)
        raise RunDirError(
            f"{path}: holds {held}, expected the keys {list(REPLAY_KEYS)} (a replay buffer and "
            "torch's generator written by this package)"
        )
    rng, want = payload["torch_rng"], torch.get_rng_state()
    if not isinstance(rng, torch.Tensor) or rng.dtype != want.dtype or rng.shape != want.shape:
        raise RunDirError(
            f"{path}: torch_rng: expected a {want.dtype} tensor of shape {tuple(want.shape)} "
            f"(torch's generator), got {_describe(rng)}"
        )
    if not isinstance(payload["transitions"], dict):
        raise RunDirError(
            f"{path}: transitions: expected a mapping of tensors, got "
            f"{_describe(payload['transitions'])}"
        )
    leaves = _leaves(payload["transitions"], path)
    unexpected = sorted(set(leaves) - set(layout))
    if unexpected:
        raise RunDirError(
            f"{path}: transitions.{'.'.join(unexpected[0])}: not a key of this run's replayed "
            "transitions (saved for another learner, system or partition?)"
        )
    rows = TensorDict(batch_size=[stored])
    for key, (shape, dtype) in layout.items():
        name = f"transitions.{'.'.join(key)}"
        if key not in leaves:
            raise RunDirError(f"{path}: {name}: missing")
        value = leaves[key]
        if not isinstance(value, torch.Tensor) or value.dtype != dtype:
            raise RunDirError(f"{path}: {name}: expected a {dtype} tensor, got {_describe(value)}")
        if tuple(value.shape) != (stored, *shape):
            raise RunDirError(
                f"{path}: {name}: shape {tuple(value.shape)}, expected {(stored, *shape)} "
                f"({stored} transitions of {frames} frames collected, capacity {capacity})"
            )
        if value.is_floating_point() and not bool(torch.isfinite(value).all()):
            raise RunDirError(f"{path}: {name}: holds NaN or infinite values")
        rows.set(key, value)
    return rows, rng


def restore_replay(buffer: TensorDictReplayBuffer, rows: TensorDict, frames: int) -> None:
    """Put checked rows back in an empty buffer, its writer where ``frames`` writes left it.

    Args:
        buffer: The run's new (empty) replay buffer.
        rows: Rows from :func:`read_replay`, in storage order.
        frames: Frames collected before the checkpoint (every frame one transition).
    """
    if not len(rows):
        return
    buffer.extend(rows.to(buffer.storage.device))  # storage rows 0 .. len - 1, in order
    state = buffer.state_dict()
    state["_writer"].update({"_cursor": frames % buffer.storage.max_size, "_write_count": frames})
    buffer.load_state_dict(state)

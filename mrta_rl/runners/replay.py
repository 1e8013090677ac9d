"""The torch loop's buffers: TorchRL replay buffers, one per team, and their checkpoint file.

The loop keeps what :meth:`~mrta_rl.learners.neural.torch_learner.TorchLearner.process_batch` gives
it in TorchRL's ``TensorDictReplayBuffer`` over ``LazyTensorStorage`` (:class:`LoopBuffer`). The
learner's regime picks the sampler, as in BenchMARL: an on-policy learner's buffer holds one batch
and is sampled without replacement (``epochs`` passes of whole minibatches), then emptied; an
off-policy learner's holds ``buffer_size`` transitions, sampled at random.

On one team there is one buffer. On a family of teams (``system.family``) every episode plays
another team, whose transitions have other shapes (robots, slots, types): each team's go into a
buffer of their own, the oldest teams' buffers are dropped when the transitions pass
``buffer_size``, and a minibatch comes from one team's buffer, drawn with probability in
proportion to the transitions it holds (so every stored transition is equally likely).

A checkpoint's ``replay.pt`` (``torch.save``, read back with ``weights_only=True``) holds

* ``transitions``: per stored team (its family index, or ``"team"`` on one team) the filled rows
  of its storage, in storage order, as nested dicts of tensors ``[rows, ...]``;
* ``torch_rng``: torch's generator (exploration draws and sampling), the state at the episode
  boundary of the checkpoint.

A writer's position follows from the frames it was given (every frame is one transition). On
resume, each team's rows are checked against what the learner stores for that team
(:func:`replay_layout`), before anything is built or written: a file of the wrong structure,
shapes, dtypes or with NaN is refused with a :class:`~mrta_rl.run_layout.RunDirError` naming the
file and the key.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.data.replay_buffers.samplers import SamplerWithoutReplacement
from torchrl.envs.utils import ExplorationType, set_exploration_type

from mrta_rl.checked_files import PT_OVERHEAD, PT_PER_TENSOR, read_tensors
from mrta_rl.learners.neural.tensor_files import write_tensors
from mrta_rl.run_layout import RunDirError

if TYPE_CHECKING:
    from mrta_rl.envs.torchrl_env import AuctionTorchRLEnv
    from mrta_rl.learners.neural.torch_learner import LoopSettings, TorchLearner

REPLAY_FILE = "replay.pt"  # training checkpoints: replay buffer rows and torch's generator
REPLAY_KEYS = ("torch_rng", "transitions")
INDEX_KEY = "index"  # written by TensorDictReplayBuffer.extend itself: not saved
ONE_TEAM = "team"  # the key of the one team's rows in replay.pt

Layout = dict[tuple[str, ...], tuple[tuple[int, ...], torch.dtype]]


class EpochSampler(SamplerWithoutReplacement):
    """TorchRL's sampler without replacement, drawing each epoch's order when it starts.

    TorchRL's draws the next permutation as soon as the last whole minibatch of an epoch is
    taken, also after the last epoch of a batch; drawn when the next epoch starts instead, the
    orders are those of one ``torch.randperm`` per epoch, and no draw is spent on an epoch that
    never comes.
    """

    def __init__(self) -> None:
        super().__init__(drop_last=True)

    def _single_sample(self, len_storage: int, batch_size: int) -> torch.Tensor:
        index = self._sample_list[:batch_size]
        self._sample_list = self._sample_list[batch_size:]
        self._remaining_batches = self._sample_list.numel() // batch_size
        self.ran_out = self._remaining_batches == 0
        if self.ran_out:
            self._sample_list = None  # the next sample starts a new epoch
        return index


class LoopBuffer:
    """The torch loop's buffers (module docstring): one per team, sampled per the regime.

    Args:
        settings: The learner's :class:`~mrta_rl.learners.neural.torch_learner.LoopSettings`.
        on_policy: The learner's regime.
        device: Where the rows are stored (the learner's device).
        episode_frames: Frames of one episode (copies x horizon): the most a family's team
            stores.
    """

    def __init__(
        self, settings: LoopSettings, on_policy: bool, device: torch.device, episode_frames: int
    ) -> None:
        self.settings, self.on_policy, self.device = settings, on_policy, device
        self.episode_frames = episode_frames
        self.buffers: dict[str, TensorDictReplayBuffer] = {}  # team key -> its buffer, oldest first
        self.written: dict[str, int] = {}  # team key -> transitions written

    def capacity(self, team: str) -> int:
        """Transitions ``team``'s buffer holds: all the loop keeps, or one episode of a family."""
        if self.on_policy or team == ONE_TEAM:
            return self.settings.buffer_size
        return min(self.settings.buffer_size, self.episode_frames)

    def expected(self, frames: int, episodes: int, family: bool) -> dict[str, tuple[int, int]]:
        """What the buffers hold after ``frames`` collected in ``episodes`` episodes.

        Per team key: ``(rows, transitions written)``; an on-policy buffer holds nothing between
        batches. On a family, episode ``e`` wrote its frames into team ``str(e)``, and the newest
        teams are kept whose transitions fit ``buffer_size`` (at least the newest).

        Args:
            frames: Frames collected so far.
            episodes: Episodes played so far.
            family: Whether the run trains on a family of teams.
        """
        if self.on_policy or not frames:
            return {}
        if not family:
            return {ONE_TEAM: (min(frames, self.capacity(ONE_TEAM)), frames)}
        kept: dict[str, tuple[int, int]] = {}
        total = 0
        for episode in range(episodes, 0, -1):
            rows = min(self.episode_frames, self.capacity(str(episode)))
            if kept and total + rows > self.settings.buffer_size:
                break
            kept[str(episode)] = (rows, self.episode_frames)
            total += rows
        return dict(reversed(kept.items()))

    def _new(self, capacity: int) -> TensorDictReplayBuffer:
        return TensorDictReplayBuffer(
            storage=LazyTensorStorage(capacity, device=self.device),
            batch_size=self.settings.minibatch_size,
            sampler=EpochSampler() if self.on_policy else None,
        )

    def __len__(self) -> int:
        return sum(len(buffer) for buffer in self.buffers.values())

    def extend(self, rows: TensorDictBase, team: str = ONE_TEAM) -> None:
        """Store a processed batch of ``team``'s transitions (the oldest teams leave when full)."""
        if team not in self.buffers:
            self.buffers[team], self.written[team] = self._new(self.capacity(team)), 0
        self.buffers[team].extend(rows)
        self.written[team] += len(rows)
        while len(self) > self.settings.buffer_size and len(self.buffers) > 1:
            oldest = next(iter(self.buffers))
            del self.buffers[oldest], self.written[oldest]

    def sample(self) -> TensorDictBase:
        """A minibatch of one team's transitions (module docstring)."""
        if len(self.buffers) == 1:
            return next(iter(self.buffers.values())).sample()
        sizes = torch.tensor([len(buffer) for buffer in self.buffers.values()])
        pick = int(
            torch.searchsorted(sizes.cumsum(0), torch.randint(int(sizes.sum()), ()), right=True)
        )
        return list(self.buffers.values())[pick].sample()

    def clear(self) -> None:
        """Drop every row (an on-policy batch, once consumed)."""
        self.buffers.clear()
        self.written.clear()

    # ------------------------------------------------------------------ checkpoints
    def save(self, path: Path) -> None:
        """Write every buffer's filled rows and torch's generator to ``path`` (module docstring)."""
        transitions = {}
        for team, buffer in self.buffers.items():
            filled = len(buffer)
            rows = buffer[:filled].exclude(INDEX_KEY) if filled else TensorDict()
            if 0 < filled < buffer.storage.max_size:
                # a slice is a view, and torch.save writes a view's whole storage (every row):
                # cloned. A full buffer's rows are its whole storage, written as they are: a copy
                # of a full buffer would double the run's peak memory for the time of the save.
                rows = rows.clone()
            transitions[team] = {"rows": rows.to_dict(), "written": self.written[team]}
        write_tensors({"transitions": transitions, "torch_rng": torch.get_rng_state()}, path)

    def restore(self, stored: dict[str, tuple[TensorDict, int]]) -> None:
        """Put checked rows (:func:`read_replay`) back in empty buffers, writers where they were."""
        for team, (rows, written) in stored.items():
            buffer = self.buffers[team] = self._new(self.capacity(team))
            self.written[team] = written
            if not len(rows):
                continue
            buffer.extend(rows.to(buffer.storage.device))  # storage rows 0 .. len - 1, in order
            state = buffer.state_dict()
            cursor = written % buffer.storage.max_size
            state["_writer"].update({"_cursor": cursor, "_write_count": written})
            buffer.load_state_dict(state)


def replay_layout(env: AuctionTorchRLEnv, learner: TorchLearner) -> Layout:
    """What one stored transition of the learner holds on a team: key -> (shape, dtype).

    Built as collected data is: the env's zero TensorDict (its specs), the collection policy's
    actions, then the learner's :meth:`process_batch`; torch's generator is left untouched.

    Args:
        env: The TorchRL view of the team.
        learner: The run's torch learner, bound to that team.

    Returns:
        Every leaf key (a tuple) with the shape of one transition and its dtype.
    """
    fake = env.fake_tensordict().to(learner.device)  # [B]
    with (
        torch.no_grad(),
        torch.random.fork_rng(devices=[]),
        set_exploration_type(ExplorationType.DETERMINISTIC),
    ):
        fake = learner.collection_policy(fake)
        rows = learner.process_batch(fake.unsqueeze(-1))  # as a [B, T = 1] collector batch
    return {
        key if isinstance(key, tuple) else (key,): (tuple(value.shape[1:]), value.dtype)
        for key, value in rows.items(include_nested=True, leaves_only=True)
    }


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


def _check_rows(tree: Any, layout: Layout, rows: int, path: Path, where: str) -> TensorDict:
    """One team's stored rows against its layout: keys, dtypes, shapes, finite values."""
    leaves = _leaves(tree, path)
    unexpected = sorted(set(leaves) - set(layout))
    if unexpected and leaves != {(): {}}:
        raise RunDirError(
            f"{path}: {where}.{'.'.join(unexpected[0])}: not a key of this run's stored "
            "transitions (saved for another learner, system or partition?)"
        )
    out = TensorDict(batch_size=[rows])
    if rows == 0:
        return out
    for key, (shape, dtype) in layout.items():
        name = f"{where}.{'.'.join(key)}"
        if key not in leaves:
            raise RunDirError(f"{path}: {name}: missing")
        value = leaves[key]
        if not isinstance(value, torch.Tensor) or value.dtype != dtype:
            raise RunDirError(f"{path}: {name}: expected a {dtype} tensor, got {_describe(value)}")
        if tuple(value.shape) != (rows, *shape):
            raise RunDirError(
                f"{path}: {name}: shape {tuple(value.shape)}, expected {(rows, *shape)}"
            )
        if value.is_floating_point() and not bool(torch.isfinite(value).all()):
            raise RunDirError(f"{path}: {name}: holds NaN or infinite values")
        out.set(key, value)
    return out


def read_replay(
    path: Path,
    expected: dict[str, tuple[int, int]],
    layout_of: Callable[[str], Layout],
    capacity: int,
) -> tuple[dict[str, tuple[TensorDict, int]], torch.Tensor]:
    """Read and check a checkpoint's ``replay.pt`` against the run (module docstring).

    Args:
        path: The checkpoint's ``replay.pt``.
        expected: Per stored team the rows and the transitions written that the loop's counters
            imply (``{}``: nothing stored, e.g. on-policy).
        layout_of: A team key -> :func:`replay_layout` of that team.
        capacity: The most transitions stored (``buffer_size``), bounding the file.

    Returns:
        ``({team: (rows, written)}, torch_rng)`` for :meth:`LoopBuffer.restore` and torch.

    Raises:
        RunDirError: naming the file and the key, if the file is missing, truncated, not a
            tensor file, or its content does not fit the run.
    """
    layouts = {team: layout_of(team) for team in expected}
    row_bytes = max(
        (
            sum(_bytes(shape, dtype) for shape, dtype in layout.values())
            for layout in layouts.values()
        ),
        default=0,
    )
    leaves = max((len(layout) for layout in layouts.values()), default=0)
    limit = capacity * row_bytes + PT_OVERHEAD + (leaves * len(layouts) + 8) * PT_PER_TENSOR
    payload = read_tensors(path, torch.device("cpu"), limit, "a replay buffer of this package")
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
    stored = payload["transitions"]
    if not isinstance(stored, dict) or set(stored) != set(expected):
        held = sorted(map(str, stored)) if isinstance(stored, dict) else _describe(stored)
        raise RunDirError(
            f"{path}: transitions: holds the teams {held}, this run stored {sorted(expected)}"
        )
    out = {}
    for team, (rows, written) in expected.items():
        entry = stored[team]
        where = f"transitions.{team}"
        if not isinstance(entry, dict):
            raise RunDirError(f"{path}: {where}: expected the keys rows, written")
        for name in {"rows", "written"} ^ set(entry):
            fault = "unknown key" if name in entry else "missing"
            raise RunDirError(f"{path}: {where}.{name}: {fault} (expected the keys rows, written)")
        if not isinstance(entry["written"], int) or entry["written"] != written:
            raise RunDirError(f"{path}: {where}.written: {entry['written']}, expected {written}")
        checked = _check_rows(entry["rows"], layouts[team], rows, path, f"{where}.rows")
        out[team] = (checked, written)
    return out, rng


def _bytes(shape: tuple[int, ...], dtype: torch.dtype) -> int:
    count = 1
    for size in shape:
        count *= size
    return count * (torch.finfo(dtype).bits if dtype.is_floating_point else _int_bits(dtype)) // 8


def _int_bits(dtype: torch.dtype) -> int:
    return 8 if dtype == torch.bool else torch.iinfo(dtype).bits

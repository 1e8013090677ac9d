"""The base of the tabular learners: eq. (3) hyperparameters, schedules, uniforms, save / load.

Paper §2 eq. (3) is the update of every tabular learner; §5.2 eqs. (10)-(16) count the tables.
Design (docs/learners.md): decision points, conflict-free joint actions, ties to a prior, and the
``B`` copies of a tick applied one after another in copy order with synchronous targets. The
per-tick work (encoding, action choice, eq. 3) runs in compiled per-copy loops
(``group_kernels``, ``robot_kernels``) over flat numpy tables.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Annotated, Any, ClassVar

import numpy as np

from mrta_rl.checked_files import ArraySpec, read_arrays
from mrta_rl.config import Choices, Range
from mrta_rl.envs import AuctionEnv, StepResult
from mrta_rl.learners.base import NUMPY_LOOP, Learner, LearnerKind, read_description
from mrta_rl.learners.tabular.schedules import LinearSchedule
from mrta_rl.partition import Partition
from mrta_rl.run_layout import INT, STR, RunDirError

logger = logging.getLogger(__name__)

NO_UNIFORMS = np.zeros(0)  # the block of a call that draws nothing (greedy, epsilon 0)
TARGETS = ("max", "prior")  # what eq. (3) bootstraps from (docs/learners.md, "Targets")

Q_FILE = "q_tables.npz"  # arrays of every table, np.savez without object arrays
META_FILE = "learner.json"  # hyperparameters and schedule position
META = {"class": STR, "episodes_done": INT}  # learner.json as save writes it


class Uniforms:
    """Uniforms in [0, 1) for the compiled loops, the same stream as ``rng.random()`` calls.

    The generator draws blocks of many uniforms ahead (one numpy call per :data:`AHEAD` calls
    of :meth:`block`); a loop reads the next ones from :meth:`block` and reports how many it
    consumed with :meth:`used`. :meth:`settle` moves the generator back over those drawn and not
    consumed (``bit_generator.advance(-unused)``), so that the generator is exactly where
    ``k`` successive ``rng.random()`` calls would have left it: the learner settles at the end
    of every training episode and before a checkpoint reads the generator.

    Args:
        rng: The learner's generator.

    Raises:
        ValueError: if its bit generator cannot move back (default_rng's PCG64 can).
    """

    AHEAD = 64  # calls of block() served by one draw

    def __init__(self, rng: np.random.Generator) -> None:
        if not hasattr(rng.bit_generator, "advance"):
            raise ValueError(
                f"tabular learners need a generator whose bit generator has advance() "
                f"(np.random.default_rng's PCG64), got {type(rng.bit_generator).__name__}"
            )
        self.rng = rng
        self._drawn = NO_UNIFORMS  # uniforms drawn ahead
        self._next = 0  # the first not consumed

    def block(self, size: int) -> np.ndarray:
        """At least ``size`` next uniforms; call :meth:`used` with how many were read."""
        if self._next + size > len(self._drawn):
            self.settle()
            self._drawn = self.rng.random(size * self.AHEAD)
        return self._drawn[self._next :]

    def used(self, count: int) -> None:
        """Consume the first ``count`` uniforms of the last :meth:`block`."""
        self._next += count

    def settle(self) -> None:
        """Give back the uniforms drawn ahead and not consumed."""
        unused = len(self._drawn) - self._next
        if unused:
            self.rng.bit_generator.advance(-unused)
        self._drawn, self._next = NO_UNIFORMS, 0


class TabularLearner(Learner, abstract=True):
    """Q-learning (paper eq. 3) with epsilon-greedy over valid actions; shared plumbing.

    Subclasses implement :meth:`encode`, :meth:`act`, :meth:`update`, their fusion
    :meth:`train_tick`, the table arrays for save / load and :meth:`learning_space`.

    Args:
        env: The env (sizes, active tasks).
        rng: Exploration randomness.
        partition: The subG partition (subG-CQL only).
        alpha: Learning rate of eq. (3) (base value, see ``alpha_power``).
        alpha_power: ``alpha_n = max(alpha_min, alpha / n^alpha_power)`` with ``n`` the entry's
            visits; 0 keeps ``alpha`` constant.
        alpha_min: Floor of the decaying learning rate.
        gamma: Discount per tick.
        epsilon_start: Exploration rate in the first episode.
        epsilon_end: Exploration rate after the decay.
        epsilon_decay_episodes: Episodes of the linear decay (0: always ``epsilon_end``).
        decisions_only: Update only at decision points (semi-Markov, docs/learners.md).
        target: What eq. (3) bootstraps from (:data:`TARGETS`): ``max``, the greatest
            competing ``Q(s', .)`` (the paper's); ``prior``, the prior's ``Q(s', prior(s'))``,
            so the table evaluates the prior and acting greedily on it is one step of policy
            improvement over the prior.
    """

    kind: ClassVar[LearnerKind] = "tabular"
    training_loop: ClassVar[str] = NUMPY_LOOP

    def __init__(
        self,
        *,
        env: AuctionEnv,
        rng: np.random.Generator,
        partition: Partition | None = None,
        alpha: Annotated[float, Range(0, 1, low_open=True)],
        alpha_power: Annotated[float, Range(0)],
        alpha_min: Annotated[float, Range(0, 1)],
        gamma: Annotated[float, Range(0, 1)],
        epsilon_start: Annotated[float, Range(0, 1)],
        epsilon_end: Annotated[float, Range(0, 1)],
        epsilon_decay_episodes: Annotated[int, Range(0)],
        decisions_only: bool,
        target: Annotated[str, Choices(*TARGETS)],
    ) -> None:
        # types and ranges: the annotations, checked before __init__ (mrta_rl.config); the
        # values: self.hp (the kernels' settings tuple reads them there)
        super().__init__(env=env, rng=rng, partition=partition)
        self.epsilon_schedule = LinearSchedule(epsilon_start, epsilon_end, epsilon_decay_episodes)
        self.prior_target = target == "prior"
        self.episodes_done = 0
        self.n_slots = env.n_slots
        self.uniforms = Uniforms(rng)
        # willingness d_i,type by slot type; the extra last row answers an empty slot (type -1)
        # C order whatever the system's layout: the kernels then compile for one array type only
        self._weight_by_type = np.ascontiguousarray(
            np.vstack([env.system.willingness.T, np.zeros(env.n_robots)])
        )

    @property
    def epsilon(self) -> float:
        """Current exploration rate (linear schedule over episodes)."""
        return self.epsilon_schedule(self.episodes_done)

    def end_episode(self) -> None:
        """Advance the epsilon schedule by one episode."""
        self.uniforms.settle()
        self.episodes_done += 1

    def checkpoint_state(self, directory: Path) -> dict[str, Any]:
        """The generator's state (``Learner.checkpoint_state``), uniforms drawn ahead given back."""
        self.uniforms.settle()
        return super().checkpoint_state(directory)

    def train_tick(self, env: AuctionEnv, result: StepResult | None) -> np.ndarray | None:
        """One training tick in one compiled call (``runners/tabular.py``'s loop).

        Exactly ``view = encode(env)``; ``update(last view, last actions, result, view,
        env.action_mask)`` unless ``result`` is None (the start of an episode); then
        ``act(view, env.action_mask, explore=True)`` unless the episode has ended: the same
        tables and the same draws as those calls, without their Python overhead per tick.

        Args:
            env: The env after its reset or ``step``.
            result: What that ``step`` returned (None after a reset).

        Returns:
            ``[B, m]`` the actions to play, or None when the episode has ended.

        Raises:
            ValueError: if ``result`` is given and no actions were returned since the episode
                started (start every episode with ``train_tick(env, None)``).
        """
        raise NotImplementedError

    @staticmethod
    def _no_last_decision() -> ValueError:
        """The error of a ``train_tick`` with a step result and no actions to learn about."""
        return ValueError(
            "train_tick(env, result): no actions of this episode to learn about; start every "
            "episode with train_tick(env, None) and step the actions it returns"
        )

    # -- persistence
    def _table_arrays(self) -> dict[str, np.ndarray]:
        raise NotImplementedError

    def _load_table_arrays(self, arrays: dict[str, np.ndarray]) -> None:
        raise NotImplementedError

    def save(self, directory: Path) -> None:
        """Write the tables (``q_tables.npz``) and the schedule position (``learner.json``).

        Args:
            directory: Target folder, created if missing.
        """
        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(directory / Q_FILE, **self._table_arrays())
        meta = {"class": type(self).__name__, "episodes_done": self.episodes_done}
        (directory / META_FILE).write_text(json.dumps(meta, indent=2) + "\n")

    def state_schema(self) -> dict[str, ArraySpec]:
        """The arrays of ``q_tables.npz``, as the learner built for the run holds them.

        Call it on the fresh learner (before any training): each array's name and dtype, its
        whole shape, or its trailing dimensions for a table with no rows yet (it grows with the
        states met); no NaN, and infinity only where the fresh learner holds one (a threshold).
        """
        return {
            name: ArraySpec.like(
                want,
                grows=want.ndim > 0 and want.shape[0] == 0,
                finite=not (want.dtype.kind == "f" and np.isinf(want).any()),
            )
            for name, want in self._table_arrays().items()
        }

    def load(self, directory: Path) -> None:
        """Restore what :meth:`save` wrote (never unpickling), checked against this learner.

        Args:
            directory: Folder written by :meth:`save`.

        Raises:
            ValueError: naming the file, if it is unreadable, written by another learner class,
                or its arrays do not fit this learner (other system or partition, wrong
                dtype or shape, NaN, inconsistent tables).
        """
        directory = Path(directory)
        meta_path = directory / META_FILE
        meta = read_description(meta_path, META)
        if meta["class"] != type(self).__name__:
            raise ValueError(f"{directory} holds a {meta['class']}, not a {type(self).__name__}")
        if meta["episodes_done"] < 0:
            raise RunDirError(
                f"{meta_path}: episodes_done: must be >= 0, got {meta['episodes_done']}"
            )
        path = directory / Q_FILE
        arrays = read_arrays(path, self.state_schema(), what="a table file written by save")
        try:
            self._load_table_arrays(arrays)
        except (ValueError, KeyError, IndexError) as err:
            raise ValueError(f"{path}: {err}") from err
        self.episodes_done = meta["episodes_done"]

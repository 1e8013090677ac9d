"""The torch learners' collection on Ray workers (``train.workers``).

The training copies are cut into contiguous chunks of equal size, one per worker. Each worker
holds an env of its copies, started from the training env's state (so copy ``b`` plays the task
stream it plays in one process), a learner of the run's class and settings built on that env, and
the learner's own TorchRL collector. Before each batch the training process sends the collection
policy's state (weights and buffers: epsilon among them); every worker collects its copies' ticks
of the batch, and the pieces are put together in copy order: the ``[B, T]`` batch one collector
gives, which the loop turns into buffer rows and gradient steps as ever.

Exploration draws come from each worker's torch generator, seeded before every batch from the run
seed, the worker and the batch's number. A run is therefore deterministic under its seed and its
number of workers, and a resumed run ends as the uninterrupted one; it is not the run of one
process, where one generator draws for every copy.

A worker lost during a batch cannot be replayed (its collector holds episodes in progress): the
run stops with one line naming it, and ``resume=<run dir>`` continues from the last checkpoint.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from typing import Any

import numpy as np
import torch
from tensordict import TensorDictBase

from mrta_rl.cluster.workers import (
    Actor,
    RayWorkers,
    WorkerFailure,
    serialized_size,
)
from mrta_rl.envs import AuctionEnv
from mrta_rl.learners.base import Learner
from mrta_rl.metrics.usage import process_peak_mib
from mrta_rl.partition import Partition


def batch_seed(seed: int, worker: int, batch: int) -> int:
    """The torch seed of one worker's share of one batch: a hash of the three, below 2**63."""
    mixed = np.random.SeedSequence([seed, worker, batch]).generate_state(2, np.uint32)
    return int(mixed[0]) << 31 | int(mixed[1]) >> 1


class CollectWorker(Actor):
    """The Ray actor: collects its copies' ticks with the learner's collector.

    Args:
        learner_class: The run's learner class.
        settings: Its checked settings.
        team: ``(system, params, active_tasks, partition)`` of the training env.
        start: The training env's state of this worker's copies.
        seed: The run seed.
        index: The worker's place.
    """

    def __init__(
        self,
        learner_class: type[Learner],
        settings: dict[str, Any],
        team: tuple,
        start: dict[str, np.ndarray],
        seed: int,
        index: int,
    ) -> None:
        system, params, active, partition = team
        torch.set_num_threads(1)  # one core per worker, as the torch loop's one thread
        copies = len(next(iter(start.values())))
        self.env = AuctionEnv(system, params, copies, active)
        self.env.set_state(start)
        rng = np.random.default_rng(0)  # its networks are overwritten before every batch
        self.learner = learner_class(env=self.env, rng=rng, partition=partition, **settings)
        self.seed, self.index = seed, index
        self.batches: Iterator[TensorDictBase] | None = None

    def collect(
        self, state: dict[str, torch.Tensor], batch: int, frames_per_batch: int, frames: int
    ) -> tuple[TensorDictBase, float, float]:
        """One batch of this worker's copies with the collection policy's ``state``.

        Args:
            state: The collection policy's state dict.
            batch: The batch's number in the run (seeds the exploration draws).
            frames_per_batch: This worker's frames of a batch.
            frames: This worker's frames still to collect in the run (its collector's total).

        Returns:
            ``([copies, T] batch, seconds, the process's peak memory in MiB)``.
        """
        began = time.perf_counter()
        self.learner.collection_policy.load_state_dict(state)
        if self.batches is None:
            view = self.learner.training_view(self.env)
            self.batches = iter(self.learner.collector(view, frames_per_batch, frames))
        # seeded after the collector is built (its policy runs once then), so that a batch's
        # draws do not depend on whether this process collected the batches before it
        torch.manual_seed(batch_seed(self.seed, self.index, batch))
        data = next(self.batches)
        return data, time.perf_counter() - began, process_peak_mib()


class CollectionWorkers(RayWorkers):
    """Ray workers that collect a torch learner's batches (module docstring).

    Args:
        learner: The run's torch learner.
        env: The training env, in the state the run's collector would start from.
        partition: The run's partition (learners that need one).
        seed: The run seed.
        first_batch: Batches collected before (a resumed run).
        **kwargs: ``workers``, ``address``, ``log_every_s`` of :class:`RayWorkers`.
    """

    actor_class = CollectWorker
    unit = "frames"

    def __init__(
        self,
        learner: Learner,
        env: AuctionEnv,
        partition: Partition | None,
        seed: int,
        first_batch: int,
        **kwargs: Any,
    ) -> None:
        super().__init__(learner, **kwargs)
        self.copies = env.batch_size // self.count
        self.start = env.get_state()
        self.team = (env.system, env.params, env.active_tasks, partition)
        self.seed, self.batch = seed, first_batch

    def actor_arguments(self, index: int) -> tuple:
        """Class, settings, team, the start state of the worker's copies, seed and place."""
        rows = slice(index * self.copies, (index + 1) * self.copies)
        start = {name: array[rows] for name, array in self.start.items()}
        self.traffic.team += serialized_size((self.team, start))
        return type(self.learner), dict(self.learner.hp), self.team, start, self.seed, index

    def batches(self, frames_per_batch: int, frames: int) -> Iterator[TensorDictBase]:
        """The run's batches, ``[B, T]`` in copy order, with the current weights each time.

        Args:
            frames_per_batch: Frames of a batch, all copies.
            frames: Frames still to collect.

        Raises:
            WorkerFailure: naming the worker lost (resume from the last checkpoint).
        """
        import ray  # noqa: PLC0415 - the cluster extra

        per_worker, total = frames_per_batch // self.count, frames // self.count
        while frames > 0:
            began = time.perf_counter()
            state = {k: v.cpu() for k, v in self.learner.collection_policy.state_dict().items()}
            state_ref = ray.put(state)
            refs = [
                w.actor.collect.remote(state_ref, self.batch, per_worker, total)
                for w in self.workers
            ]
            pieces = []
            for worker, ref in zip(self.workers, refs, strict=True):
                try:
                    data, seconds, peak = ray.get(ref)
                except ray.exceptions.RayError as err:
                    raise WorkerFailure(
                        f"{worker.name()} failed in batch {self.batch + 1} "
                        f"({type(err).__name__}): resume=<run dir> continues from the last "
                        "checkpoint"
                    ) from None
                worker.record(data.numel(), seconds, peak)
                pieces.append(data)
            self.traffic.sent += self.count * serialized_size(state)
            self.traffic.received += sum(serialized_size(piece) for piece in pieces)
            self.steps += 1
            self.batch += 1
            frames -= frames_per_batch
            self.step_seconds.append(time.perf_counter() - began)
            self.log_progress("batch")
            yield torch.cat(pieces, dim=0)

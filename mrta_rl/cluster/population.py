"""An evolution-strategies population played on Ray workers (``train.workers``).

Each worker is a Ray actor that holds a learner of the run's class and settings, built on the
worker for the team the run trains on. Per ES step it receives:

* the population (:class:`~mrta_rl.learners.search.reserve_es.Population`): the current weights
  and the generator state the step's perturbations are drawn from, so the worker redraws the
  members rather than receiving them;
* the episode's start state of the common task streams, one copy per stream (a member's copy
  ``b`` plays stream ``b mod copies``, as in the single-process run);
* the range of members it plays.

It returns its members' per-copy returns. The members are cut into contiguous chunks, one per
worker, and the returns are put back in member order, so every copy plays what it plays in one
process and the ES update sees the same numbers in the same order: the run is bit-identical to
the single-process run of the same seed, whatever the number of workers.

A worker lost during a step (its process killed, its node gone) has its chunk re-run on another
worker; a new worker takes its place for the next steps, and the log names both. A chunk that
fails :data:`ATTEMPTS` times, a worker that cannot be replaced, or an error raised by the
learner on a worker stops the run with one line naming the worker.
"""

from __future__ import annotations

import logging
import time
from typing import Any

import numpy as np

from mrta_rl.cluster.workers import (
    Actor,
    RayWorkers,
    WorkerFailure,
    serialized_size,
)
from mrta_rl.envs import AuctionEnv
from mrta_rl.learners.base import Learner
from mrta_rl.metrics.usage import process_peak_mib

logger = logging.getLogger(__name__)

ATTEMPTS = 3  # tries of one chunk of members before the run stops


class EpisodeWorker(Actor):
    """The Ray actor: plays chunks of an ES step's members on its own env copies.

    Args:
        learner_class: The run's learner class.
        settings: Its checked settings (``learner.hp``).
    """

    def __init__(self, learner_class: type[Learner], settings: dict[str, Any]) -> None:
        self.learner_class, self.settings = learner_class, settings
        self.team_key: int | None = None
        self.envs: dict[int, AuctionEnv] = {}

    def play(
        self, team_key: int, team: tuple, population: Any, start: dict, lo: int, hi: int
    ) -> tuple[np.ndarray, np.ndarray, float, float]:
        """Members ``lo:hi`` of the population play one episode from ``start``.

        Args:
            team_key: Names the team; a new key rebuilds the learner and the envs.
            team: ``(system, params, active_tasks)`` of the team's env.
            population: The step's :class:`Population`.
            start: The env state of the ``population.copies`` common streams.
            lo: First member played.
            hi: One past the last.

        Returns:
            ``(returns, team_returns, seconds, peak MiB)``: per copy, member-major, the time
            played and the process's peak memory.
        """
        system, params, active = team
        copies = population.copies
        if team_key != self.team_key:
            probe = AuctionEnv(system, params, 2 * population.pairs, active)
            rng = np.random.default_rng(0)  # the worker's learner only plays given weights
            self.learner = self.learner_class(env=probe, rng=rng, **self.settings)
            self.team_key, self.envs = team_key, {}
        batch = (hi - lo) * copies
        if batch not in self.envs:
            self.envs[batch] = AuctionEnv(system, params, batch, active)
        env = self.envs[batch]
        env.set_state({name: array[np.arange(batch) % copies] for name, array in start.items()})
        began = time.perf_counter()
        returns, team_returns = self.learner.play_members(env, population.members()[lo:hi], copies)
        return returns, team_returns, time.perf_counter() - began, process_peak_mib()


class PopulationWorkers(RayWorkers):
    """Ray workers that play each ES step's members (module docstring).

    Args:
        learner: The run's learner (``population_on_workers``).
        workers: Worker processes.
        address: A Ray cluster's address, or None for a local Ray instance of ``workers`` CPUs.
        log_every_s: Seconds between the log lines that name the workers and their throughput.
    """

    actor_class = EpisodeWorker

    def __init__(
        self, learner: Learner, workers: int, address: str | None, log_every_s: float
    ) -> None:
        super().__init__(learner, workers, address, log_every_s)
        self.retries: list[str] = []
        self.members = 0  # members of the last step
        self._team_env: AuctionEnv | None = None
        self._team_key = 0

    # ------------------------------------------------------------------ steps
    def play(self, env: AuctionEnv) -> tuple[np.ndarray, np.ndarray]:
        """The learner's current members play one episode on ``env``'s team and streams.

        Args:
            env: The training env, at the start of the episode; copy ``b`` of member ``j``
                (``b < copies``) plays the stream of its copy ``b``.

        Returns:
            ``(returns, team_returns)`` ``[B]``, as the single-process run plays them.
        """
        import ray  # noqa: PLC0415

        began = time.perf_counter()
        population = self.learner.population()
        copies = population.copies
        if env is not self._team_env:  # the first team, or the next team of a family
            self._team_env, self._team_key = env, self._team_key + 1
            recipe = (env.system, env.params, env.active_tasks)
            self._team_ref = ray.put(recipe)
            self.traffic.team = serialized_size(recipe)
        start = env.get_state(np.arange(copies))
        start_ref = ray.put(start)
        members = self.members = 2 * population.pairs
        chunks = [(int(c[0]), int(c[-1]) + 1) for c in np.array_split(range(members), self.count)]
        chunks = [chunk for chunk in chunks if chunk[0] < chunk[1]]
        self.steps += 1
        population_bytes, start_bytes = serialized_size(population), serialized_size(start)
        pending: dict[Any, tuple[int, int, int]] = {}  # ref -> chunk, worker, attempt

        def submit(chunk: int, worker: int, attempt: int) -> None:
            lo, hi = chunks[chunk]
            ref = self.workers[worker].actor.play.remote(
                self._team_key, self._team_ref, population, start_ref, lo, hi
            )
            pending[ref] = (chunk, worker, attempt)
            self.traffic.sent += population_bytes + start_bytes + serialized_size((lo, hi))

        for chunk in range(len(chunks)):
            submit(chunk, chunk % self.count, 1)
        results: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        while pending:
            ready, _ = wait_for(list(pending))
            for ref in ready:
                chunk, worker, attempt = pending.pop(ref)
                try:
                    returns, team_returns, seconds, peak = ray.get(ref)
                except ray.exceptions.RayTaskError as err:  # the learner raised: a bug or bad state
                    cause = str(err.cause if err.cause is not None else err).splitlines()[0]
                    raise WorkerFailure(
                        f"{self.workers[worker].name()} failed in ES step {self.steps}: {cause}"
                    ) from None
                except (ray.exceptions.RayActorError, ray.exceptions.WorkerCrashedError) as err:
                    submit(chunk, self._replace(worker, chunk, chunks, attempt, err), attempt + 1)
                    continue
                results[chunk] = returns, team_returns
                self.workers[worker].record(len(returns) * env.params.horizon, seconds, peak)
                self.traffic.received += serialized_size((returns, team_returns, seconds, peak))
        self.step_seconds.append(time.perf_counter() - began)
        self.log_progress("ES step")
        order = range(len(chunks))
        return (
            np.concatenate([results[chunk][0] for chunk in order]),
            np.concatenate([results[chunk][1] for chunk in order]),
        )

    def _replace(
        self, lost: int, chunk: int, chunks: list[tuple[int, int]], attempt: int, err: Exception
    ) -> int:
        """Restart worker ``lost`` and pick the worker that re-runs ``chunk``; log both."""
        gone = self.workers[lost]
        lo, hi = chunks[chunk]
        if attempt >= ATTEMPTS:
            raise WorkerFailure(
                f"{gone.name()}: members {lo}-{hi - 1} of ES step {self.steps} failed "
                f"{attempt} times ({type(err).__name__}); the last checkpoint stays"
            )
        self.workers[lost] = self._start(lost)
        others = [w.index for w in self.workers if w.index != lost]
        rerun = others[chunk % len(others)] if others else lost
        message = (
            f"{gone.name()} lost in ES step {self.steps} ({type(err).__name__}): members "
            f"{lo}-{hi - 1} re-run on {self.workers[rerun].name()}; "
            f"{self.workers[lost].name()} takes its place"
        )
        logger.warning("retry: %s", message)
        self.retries.append(message)
        return rerun

    def summary(self) -> dict[str, Any]:
        """The base's record, the members of a step and the retries."""
        return super().summary() | {"members": self.members, "retries": list(self.retries)}


def wait_for(refs: list[Any]) -> tuple[list[Any], list[Any]]:
    """Ray's wait for the first finished of ``refs`` (a seam the tests use to kill a worker)."""
    import ray  # noqa: PLC0415

    return ray.wait(refs, num_returns=1)

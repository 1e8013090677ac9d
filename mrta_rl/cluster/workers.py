"""Ray workers of one run: joining Ray, starting actors, naming them, what crossed the network.

:class:`RayWorkers` is the base of the pools that spread a run's work (``cluster/population.py``:
an ES step's members; ``cluster/collection.py``: the torch learners' collection). It joins the
Ray cluster of ``train.ray_address`` (or starts a local instance of ``train.workers`` CPUs, and
stops it at the end), starts one actor of one CPU per worker, and logs which process on which
node each is; a line at most every ``train.log_every_s`` seconds gives each worker's
throughput, and :meth:`RayWorkers.summary` is what ``metrics.json`` records.
"""

from __future__ import annotations

import logging
import os
import socket
import time
from dataclasses import dataclass
from typing import Any

from mrta_rl.config import UserError
from mrta_rl.learners.base import Learner

logger = logging.getLogger(__name__)

START_TIMEOUT_S = 300.0  # a worker that has not started by then (no free CPU) fails for good


class WorkerFailure(UserError):
    """A Ray worker failed for good: the run stops with one line; its checkpoints stay."""


class Actor:
    """What every worker actor answers: where it runs."""

    def where(self) -> dict[str, Any]:
        """The worker's process id, host, node address and Ray node id."""
        import ray  # noqa: PLC0415 - on the worker, where Ray runs it

        return {
            "pid": os.getpid(),
            "host": socket.gethostname(),
            "address": ray.util.get_node_ip_address(),
            "node": ray.get_runtime_context().get_node_id(),
        }


@dataclass
class Worker:
    """One actor of the pool and what is known of it."""

    index: int
    actor: Any
    pid: int
    host: str
    address: str  # the node's IP address
    node: str  # Ray's node id (nodes of a local test cluster share an address)
    copy_ticks: int = 0  # copy-ticks played (or collected)
    seconds: float = 0.0  # time spent on them
    peak_rss_mb: float = 0.0  # the worker process's peak memory, as it last reported

    def record(self, copy_ticks: int, seconds: float, peak_mb: float) -> None:
        """Count a piece of work the worker reports: its size, time and the process's peak."""
        self.copy_ticks += copy_ticks
        self.seconds += seconds
        self.peak_rss_mb = max(self.peak_rss_mb, peak_mb)

    def name(self) -> str:
        """``worker 1 (pid 4242 on 10.0.0.2, node <id>)``."""
        return f"worker {self.index} (pid {self.pid} on {self.address}, node {self.node[:8]})"

    def rate(self, unit: str) -> str:
        """Work done per second so far, as ``14.2k copy-ticks/s``."""
        rate = self.copy_ticks / self.seconds if self.seconds else 0.0
        return f"{rate / 1000:.1f}k {unit}/s"


@dataclass
class Traffic:
    """Bytes crossing the network per ES step (pickled payloads, Ray's own framing aside)."""

    sent: int = 0  # to every worker
    received: int = 0  # back
    team: int = 0  # the team's recipe, sent once per team and worker

    def summary(self, steps: int) -> dict[str, int]:
        """Means over ``steps`` steps (bytes) and the team recipe's size."""
        steps = max(steps, 1)
        return {
            "sent_per_step": self.sent // steps,
            "received_per_step": self.received // steps,
            "team_recipe": self.team,
        }


def serialized_size(value: Any) -> int:
    """Bytes of ``value`` as Ray serialises it (cloudpickle)."""
    from ray import cloudpickle  # noqa: PLC0415

    return len(cloudpickle.dumps(value, protocol=5))


class RayWorkers:
    """Ray actors of one run (module docstring); a subclass names the actor and its work.

    Args:
        learner: The run's learner.
        workers: Worker processes.
        address: A Ray cluster's address, or None for a local Ray instance of ``workers`` CPUs.
        log_every_s: Seconds between the log lines that name the workers and their throughput.
    """

    actor_class: type[Actor]  # the Ray actor of the subclass
    unit = "copy-ticks"  # what the throughput counts

    def __init__(
        self, learner: Learner, workers: int, address: str | None, log_every_s: float
    ) -> None:
        self.learner, self.count, self.address = learner, workers, address
        self.log_every_s = log_every_s
        self.workers: list[Worker] = []
        self.traffic = Traffic()
        self.steps = 0
        self.step_seconds: list[float] = []  # wall time of each step, seen from this process
        self._started_ray = False
        self._last_log = time.monotonic()

    def actor_arguments(self, index: int) -> tuple:
        """The arguments of worker ``index``'s actor; default: the learner's class and settings."""
        return type(self.learner), dict(self.learner.hp)

    # ------------------------------------------------------------------ life
    def __enter__(self) -> RayWorkers:
        import ray  # noqa: PLC0415 - the cluster extra, imported when workers are asked for

        if not ray.is_initialized():
            options: dict[str, Any] = {"include_dashboard": False, "logging_level": logging.WARNING}
            if self.address is None:
                options["num_cpus"] = self.count
            # "local" starts an instance of its own even when another one runs on this machine
            ray.init(address=self.address or "local", **options)
            self._started_ray = True
        self._remote = ray.remote(num_cpus=1, max_restarts=0)(self.actor_class)
        self.workers = [self._start(index) for index in range(self.count)]
        nodes = len({worker.node for worker in self.workers})
        logger.info(
            "%d Ray workers on %d node%s: %s",
            self.count,
            nodes,
            "" if nodes == 1 else "s",
            ", ".join(worker.name() for worker in self.workers),
        )
        return self

    def __exit__(self, *exc: object) -> None:
        import ray  # noqa: PLC0415

        for worker in self.workers:
            ray.kill(worker.actor)
        if self._started_ray:
            ray.shutdown()

    def _start(self, index: int) -> Worker:
        """A new actor in place ``index``, once it answers."""
        import ray  # noqa: PLC0415

        actor = self._remote.remote(*self.actor_arguments(index))
        try:
            where = ray.get(actor.where.remote(), timeout=START_TIMEOUT_S)
        except Exception as err:  # noqa: BLE001 - any failure to start is this worker's
            raise WorkerFailure(
                f"worker {index} did not start within {START_TIMEOUT_S:.0f} s "
                f"({type(err).__name__}): are there free CPUs in the Ray cluster?"
            ) from None
        return Worker(index, actor, **where)

    # ------------------------------------------------------------------ reporting
    def log_progress(self, what: str) -> None:
        """A line naming every worker and its throughput, at most every ``log_every_s``."""
        now = time.monotonic()
        if now - self._last_log < self.log_every_s:
            return
        self._last_log = now
        rates = "; ".join(f"{w.name()}: {w.rate(self.unit)}" for w in self.workers)
        logger.info("%s %d on %s", what, self.steps, rates)

    def summary(self) -> dict[str, Any]:
        """What the run records of its workers (metrics.json's ``train.workers``)."""
        return {
            "count": self.count,
            "address": self.address or "local",
            "nodes": len({worker.node for worker in self.workers}),
            "processes": [
                {key: getattr(w, key) for key in ("index", "pid", "host", "address", "node")}
                for w in self.workers
            ],
            f"{self.unit.replace('-', '_')}_per_s": [
                round(w.copy_ticks / w.seconds, 1) if w.seconds else 0.0 for w in self.workers
            ],
            "peak_rss_mb": [round(w.peak_rss_mb, 1) for w in self.workers],
            "step_seconds": [round(seconds, 4) for seconds in self.step_seconds],
            "bytes": self.traffic.summary(len(self.step_seconds)),
        }

"""ES on Ray workers: copy-ticks per second for several worker counts, and a model beyond them.

Each repeat trains the learner once per worker count, one after another, each run starting its
own local Ray instance of that many CPUs. A run's rate counts its ES steps after the first (the
first loads the compiled code in every worker): copy-ticks played over the steps' wall time, as
the training process sees it (transfers included). Ratios are taken within a repeat, so a busy
machine slows both sides of each ratio alike.

:func:`step_model` extends the measured points to many workers (docs/guide/cluster.md): a step
costs the training process's own work, the slowest worker's share of the members, and one message
out and one back per worker, sent one after another by the training process.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mrta_rl.bench.learners import train_once

# the model's assumptions about a cluster's network and Ray's driver (docs/guide/cluster.md)
BANDWIDTH = 125e6  # bytes/s out of the training process: 1 Gbit/s
MESSAGE_S = 0.5e-3  # the training process's cost per message: submitting a task, a reply


def measure(
    learner: str, system: str, workers: list[int], repeats: int, overrides: list[str]
) -> dict[str, Any]:
    """Train ``learner`` on ``system`` with each worker count, ``repeats`` times.

    Args:
        learner: A learner with ``population_on_workers`` (net_es, reserve_es).
        system: A shipped system name.
        workers: Worker counts; the first is the ratios' reference.
        repeats: Side-by-side repeats.
        overrides: More run settings (``train.episodes=5`` ...).

    Returns:
        ``rates`` and ``ratios`` per worker count and repeat (copy-ticks/s, to the first count),
        ``step_s`` (each repeat's median step), ``worker_rate`` (copy-ticks/s of one worker
        while it plays), ``bytes`` per step, and the step's ``members``, ``copies`` (per
        member) and ``horizon``.
    """
    rates: dict[int, list[float]] = {count: [] for count in workers}
    step_s: dict[int, list[float]] = {count: [] for count in workers}
    worker_rate: dict[int, list[float]] = {count: [] for count in workers}
    traffic: dict[int, dict[str, int]] = {}
    shape: dict[str, int] = {}
    for _ in range(repeats):
        for count in workers:
            _, _, _, batch, info = train_once(
                learner, system, [f"train.workers={count}", *overrides]
            )
            record = info["workers"]
            steps = record["step_seconds"][1:]
            horizon = info["env_ticks"] // (batch * len(record["step_seconds"]))
            rates[count].append(batch * horizon * len(steps) / sum(steps))
            step_s[count].append(statistics.median(steps))
            worker_rate[count].append(statistics.mean(record["copy_ticks_per_s"]))
            traffic[count] = record["bytes"]
            members = record["members"]
            shape = {"members": members, "copies": batch // members, "horizon": horizon}
    reference = rates[workers[0]]
    ratios = {
        count: [rate / base for rate, base in zip(rates[count], reference, strict=True)]
        for count in workers
    }
    return {
        "rates": rates,
        "ratios": ratios,
        "step_s": step_s,
        "worker_rate": worker_rate,
        "bytes": traffic,
        **shape,
    }


def format_table(result: dict[str, Any]) -> str:
    """Rates (k copy-ticks/s) and ratios to the first worker count: min and median."""
    lines = ["workers | k copy-ticks/s min / median | ratio min / median | bytes sent / received"]
    for count, rates in result["rates"].items():
        ratios = result["ratios"][count]
        sent = result["bytes"][count]
        lines.append(
            f"{count:7d} | {min(rates) / 1e3:8.1f} / {statistics.median(rates) / 1e3:8.1f} | "
            f"{min(ratios):5.2f} / {statistics.median(ratios):5.2f} | "
            f"{sent['sent_per_step']:,} / {sent['received_per_step']:,}"
        )
    return "\n".join(lines)


@dataclass(frozen=True)
class StepModel:
    """What one ES step costs, from one worker's measured run (:func:`fit_model`).

    Attributes:
        own_s: The training process's own work per step (update, start state, waiting aside).
        worker_rate: Copy-ticks per second of one worker while it plays.
        message_bytes: Bytes out and back per worker and step.
        copies: Copies per member.
        horizon: Ticks per episode.
    """

    own_s: float
    worker_rate: float
    message_bytes: float
    copies: int
    horizon: int

    def step_s(self, workers: int, members: int) -> float:
        """Seconds per step: own work, the largest chunk of members, the messages in turn."""
        chunk = math.ceil(members / min(workers, members))
        play = chunk * self.copies * self.horizon / self.worker_rate
        messages = min(workers, members) * (self.message_bytes / BANDWIDTH + 2 * MESSAGE_S)
        return self.own_s + play + messages


def fit_model(result: dict[str, Any]) -> StepModel:
    """The model of one worker's measured run: its own work is what the play does not explain.

    Raises:
        ValueError: if the measurement has no 1-worker run.
    """
    if 1 not in result["step_s"]:
        raise ValueError("the model is fitted on a 1-worker run: measure --workers 1 ...")
    members, copies, horizon = result["members"], result["copies"], result["horizon"]
    worker_rate = statistics.median(result["worker_rate"][1])
    step = statistics.median(result["step_s"][1])
    traffic = result["bytes"][1]
    message = traffic["sent_per_step"] + traffic["received_per_step"]
    play = members * copies * horizon / worker_rate
    own = max(step - play - message / BANDWIDTH - 2 * MESSAGE_S, 0.0)
    return StepModel(own, worker_rate, message, copies, horizon)


def format_model(result: dict[str, Any], workers: tuple[int, ...]) -> str:
    """The model's step time and speed-up next to the measured ones, for two populations.

    ``fixed``: the measured population (its members bound the useful workers); ``grown``: one
    member per worker (``pairs = workers / 2``, the way ES reaches many cores).
    """
    model = fit_model(result)
    members = result["members"]
    base = model.step_s(1, members)
    lines = [
        "workers | measured step s (speed-up) | model, fixed population | "
        "model, a member per worker: k copy-ticks/s",
    ]
    for count in workers:
        measured = result["step_s"].get(count)
        seen = "-"
        if measured:
            step = statistics.median(measured)
            seen = f"{step:6.3f} ({statistics.median(result['step_s'][1]) / step:4.2f}x)"
        fixed = model.step_s(count, members)
        grown = model.step_s(count, max(count, 1))
        rate = max(count, 1) * model.copies * model.horizon / grown
        lines.append(
            f"{count:7d} | {seen:>26} | {fixed:6.3f} s ({base / fixed:5.1f}x) | {rate / 1e3:10,.0f}"
        )
    return "\n".join(lines)


def read_result(path: Path) -> dict[str, Any]:
    """A measurement :func:`measure` returned and the script saved as JSON (worker counts as keys).

    Raises:
        ValueError: naming the file, if it is not such a measurement.
    """
    try:
        raw = json.loads(path.read_text())
        by_count = ("rates", "ratios", "step_s", "worker_rate", "bytes")
        result = {key: {int(k): v for k, v in raw[key].items()} for key in by_count}
        return result | {key: int(raw[key]) for key in ("members", "copies", "horizon")}
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as err:
        raise ValueError(f"{path}: not a bench_workers measurement ({err})") from None


MODEL_WORKERS = (1, 2, 4, 8, 24, 64, 256, 1000)  # the model's table


def main() -> None:
    """``scripts/bench_workers.py``: measure, save, print the tables (the script's docstring)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--learner", default="net_es")
    parser.add_argument("--system", default="system2")
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--episodes", type=int, default=5, help="ES steps per run (first: warm-up)")
    parser.add_argument("--out", type=Path, default=Path("bench_workers.json"))
    parser.add_argument("--from", dest="saved", type=Path, help="a saved measurement's tables")
    args = parser.parse_args()
    if args.saved:
        result = read_result(args.saved)
    else:
        episodes = [f"train.episodes={args.episodes}"]
        result = measure(args.learner, args.system, args.workers, args.repeats, episodes)
        args.out.write_text(json.dumps(result, indent=1) + "\n")
    print(format_table(result), format_model(result, MODEL_WORKERS), sep="\n\n")

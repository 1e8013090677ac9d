"""Where the wall time of a neural training run goes: collection, training, evaluation.

:func:`profile_run` runs :func:`mrta_rl.runners.train.train` unchanged, with wall-clock timers
wrapped around its parts (class attributes, restored afterwards). A timer costs about a
microsecond per call, so the shares are those of a normal run, not of a profiler's (cProfile
doubles the cost of the many small Python calls of a collection tick). Timers nest: a part is
counted inside its parent only (the core dynamics inside the TorchRL view's step, not during
the evaluation), and a part re-entered through itself is counted once.

Collection and training seconds are the runner's own (``metrics.json["train"]``: frames /
``fps_collection``, replayed transitions / ``fps_training``); what the timers do not cover inside
them is shown as the rest (the TorchRL Collector and ``EnvBase.step`` plumbing and TensorDict
handling for collection; the loss forward for training).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Any

from omegaconf import DictConfig

# (label, owner, attribute, parent label or None): a timer on owner.attribute
PARTS: list[tuple[str, str, str, str | None]] = [
    ("env: TorchRL view step/reset", "mrta_rl.envs.torchrl_env.AuctionTorchRLEnv", "_step", None),
    ("env: TorchRL view step/reset", "mrta_rl.envs.torchrl_env.AuctionTorchRLEnv", "_reset", None),
    (
        "env: core dynamics (kernel)",
        "mrta_rl.envs.auction.AuctionEnv",
        "step",
        "env: TorchRL view step/reset",
    ),
    (
        "env: core dynamics (kernel)",
        "mrta_rl.envs.auction.AuctionEnv",
        "reset",
        "env: TorchRL view step/reset",
    ),
    (
        "env: observation features",
        "mrta_rl.envs.encodings",
        "local_features",
        "env: TorchRL view step/reset",
    ),
    (
        "env: observation features",
        "mrta_rl.envs.encodings",
        "global_features",
        "env: TorchRL view step/reset",
    ),
    (
        "policy forward (Q-net, argmax, epsilon-greedy)",
        "tensordict.nn.TensorDictSequential",
        "forward",
        "collect",
    ),
    ("replay write (transitions, extend)", "torchrl.data.TensorDictReplayBuffer", "extend", None),
    ("replay sampling", "torchrl.data.TensorDictReplayBuffer", "sample", None),
    ("gradient step", "mrta_rl.learners.neural.torch_learner.TorchLearner", "train_step", None),
    ("backward", "torch.Tensor", "backward", "gradient step"),
    ("gradient clipping + Adam step", "torch.nn.utils", "clip_grad_norm_", "gradient step"),
    ("gradient clipping + Adam step", "torch.optim.Adam", "step", "gradient step"),
    ("target network update", "torchrl.objectives.utils.TargetNetUpdater", "step", "gradient step"),
    ("evaluation (learner and greedy)", "mrta_rl.runners.train", "evaluate_run", None),
]


def _resolve(path: str) -> Any:
    """The module or class named by a dotted path."""
    import importlib

    parts = path.split(".")
    for cut in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:cut]))
        except ImportError:
            continue
        for name in parts[cut:]:
            obj = getattr(obj, name)
        return obj
    raise ImportError(path)


class Timers:
    """Seconds per label, with a stack of the labels being timed (nesting and re-entry)."""

    def __init__(self) -> None:
        """Start with no time and no active label."""
        self.seconds: dict[str, float] = {}
        self.stack: list[str] = []

    def wrap(self, label: str, parent: str | None, func: Callable) -> Callable:
        """``func`` timed under ``label`` when ``parent`` (None: always) is being timed."""

        def timed(*args: Any, **kwargs: Any) -> Any:
            if label in self.stack or (parent is not None and parent not in self.stack):
                return func(*args, **kwargs)
            self.stack.append(label)
            start = time.perf_counter()
            try:
                return func(*args, **kwargs)
            finally:
                self.seconds[label] = self.seconds.get(label, 0.0) + time.perf_counter() - start
                self.stack.pop()

        return timed

    @contextmanager
    def section(self, label: str):
        """Mark ``label`` as being timed (a parent for the timers), without timing it."""
        self.stack.append(label)
        try:
            yield
        finally:
            self.stack.pop()


def _collector_section(timers: Timers, stack: ExitStack) -> None:
    """Mark the Collector's iteration as the "collect" section (parent of the policy timer)."""
    from torchrl.collectors import Collector

    original = Collector.iterator

    def iterator(self: Any) -> Any:
        inner = original(self)
        while True:
            with timers.section("collect"):
                try:
                    batch = next(inner)
                except StopIteration:
                    return
            yield batch

    Collector.iterator = iterator
    stack.callback(setattr, Collector, "iterator", original)


def profile_run(cfg: DictConfig, run_dir: Path) -> tuple[dict[str, Any], list[tuple[str, float]]]:
    """Train and evaluate as ``scripts/train.py`` does, timing the parts of :data:`PARTS`.

    Args:
        cfg: The composed run config.
        run_dir: Output folder of the run.

    Returns:
        ``(metrics, rows)``: the run's ``metrics.json`` content and ``(label, seconds)`` rows,
        the whole run first, parts indented under collection, training and evaluation.
    """
    train_module = _resolve("mrta_rl.runners.train")  # the module (the package exports train())
    timers = Timers()
    with ExitStack() as stack:
        for label, owner, attribute, parent in PARTS:
            target = _resolve(owner)
            original = getattr(target, attribute)
            setattr(target, attribute, timers.wrap(label, parent, original))
            stack.callback(setattr, target, attribute, original)
        _collector_section(timers, stack)
        start = time.perf_counter()
        metrics = train_module.train(cfg, run_dir)
        total = time.perf_counter() - start
    info, s = metrics["train"], timers.seconds
    collect = info["env_ticks"] / info["fps_collection"]
    steps = info["gradient_steps"] * int(cfg.learner.batch_size)
    train = steps / info["fps_training"] if info["fps_training"] else 0.0
    env = s.get("env: TorchRL view step/reset", 0.0)
    core = s.get("env: core dynamics (kernel)", 0.0)
    features = s.get("env: observation features", 0.0)
    policy = s.get("policy forward (Q-net, argmax, epsilon-greedy)", 0.0)
    step = s.get("gradient step", 0.0)
    sampled = s.get("replay sampling", 0.0)
    backward = s.get("backward", 0.0)
    optimizer = s.get("gradient clipping + Adam step", 0.0)
    target = s.get("target network update", 0.0)
    evaluation = s.get("evaluation (learner and greedy)", 0.0)
    rows = [
        ("whole run (build, train, evaluate)", total),
        ("collection (Collector)", collect),
        ("  env: core dynamics (kernel)", core),
        ("  env: observation features", features),
        ("  env: TorchRL view (TensorDicts of step/reset, masks)", env - core - features),
        ("  policy forward (Q-net, argmax, epsilon-greedy)", policy),
        ("  TorchRL Collector / EnvBase.step plumbing (rest)", collect - env - policy),
        ("training (gradient steps and their sampling)", train),
        ("  replay sampling", sampled),
        (
            "  loss forward (TorchRL loss, online and target nets)",
            step - backward - optimizer - target,
        ),
        ("  backward", backward),
        ("  gradient clipping + Adam step", optimizer),
        ("  target network update", target),
        ("rest of the training loop", info["wall_s"] - collect - train),
        ("  replay write (transitions, extend)", s.get("replay write (transitions, extend)", 0.0)),
        ("evaluation (learner and greedy)", evaluation),
        ("setup (config, build, compile cache) and writing", total - info["wall_s"] - evaluation),
    ]
    return metrics, rows


def format_profile(rows: list[tuple[str, float]]) -> str:
    """Markdown table of :func:`profile_run` rows: seconds and share of the whole run."""
    total = rows[0][1]
    lines = ["| part | seconds | share of the run |", "| :--- | ---: | ---: |"]
    for label, seconds in rows:
        lines.append(f"| {label} | {seconds:.1f} | {100 * seconds / total:.1f} % |")
    return "\n".join(lines)

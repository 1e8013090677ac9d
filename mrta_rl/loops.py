"""The training loops of ``mrta_rl.runners`` by name, and the counters each keeps in a checkpoint.

A learner names its loop as ``"module:function"`` without importing the runners (they import the
learners); the runner imports it when used. A loop has the signature ``loop(run: RunSetup, cfg:
DictConfig, run_dir: Path) -> dict`` and returns ``{"env_ticks": int, "wall_s": float,
"episodes": int}``; it writes curve.csv. This module imports nothing, so that the readers of run
dirs (``mrta_rl/run_files.py``, the reports) check a checkpoint's counters without loading a
learner.
"""

from __future__ import annotations

TICK_LOOP = "mrta_rl.runners.tick_loop:train_loop"  # numpy learners: one update per tick
TORCHRL_LOOP = "mrta_rl.runners.torchrl:train_loop"  # TorchRL Collector, replay, target nets
PPO_LOOP = "mrta_rl.runners.ppo:train_loop"  # on-policy: collect a batch, GAE, PPO epochs
NO_TRAINING = "mrta_rl.runners.tick_loop:skip_training"  # fixed policies: evaluated as they are

# the counters of each loop in a checkpoint's training.json, besides ``episode`` and ``curve``
LOOP_COUNTERS: dict[str, tuple[str, ...]] = {
    TICK_LOOP: ("env_ticks",),
    TORCHRL_LOOP: ("frames", "replayed"),
    PPO_LOOP: ("frames", "replayed"),
}

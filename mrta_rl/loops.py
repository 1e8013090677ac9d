"""The training loops of ``mrta_rl.runners`` by name.

A learner names its loop as ``"module:function"`` without importing the runners (they import the
learners); the runner imports it when used. A loop has the signature ``loop(run: RunSetup, cfg:
DictConfig, run_dir: Path) -> dict`` and returns ``{"env_ticks": int, "wall_s": float,
"episodes": int}``; it writes curve.csv. Its module declares the counters its checkpoints keep
besides the episode (``COUNTERS``), which resuming checks.
"""

from __future__ import annotations

NUMPY_LOOP = "mrta_rl.runners.numpy_loop:train_loop"  # numpy learners: one update per tick
TORCH_LOOP = "mrta_rl.runners.torch_loop:train_loop"  # TorchRL learners: Collector, buffer
NO_TRAINING = "mrta_rl.runners.numpy_loop:skip_training"  # fixed policies: evaluated as they are

"""Which task streams each run plays: training's, and evaluation's test and validation splits.

A copy's task arrivals depend only on its env seed and its episode counter
(``docs/spec/auction_env.md``), so a seed names a stream. Training copy ``b`` of run seed ``s``
plays seed ``s * SEED_STRIDE + b``. Evaluation copy ``b`` plays ``SPLIT_SEEDS[split] + b``:

* ``test`` (``1_000_000 + b``): the streams the docs report; no choice is made on them;
* ``validation`` (``2_000_000 + b``): the streams every choice is made on (a hyperparameter
  screen, a design choice, a best snapshot, an early stop).

Each split owns :data:`SPLIT_WIDTH` seeds (``runners/validation.py`` refuses more evaluation
copies), so the two never share a stream; both lie below ``SEED_STRIDE``, before the training
copies of every run seed but 0, and past those of run seed 0 (it refuses more training copies
than the test split's first seed). Every learner and run seed is evaluated on the same streams of
a split. Training on a family of teams (``systems/family.py``), copy ``b`` of training episode
``e`` plays ``s * SEED_STRIDE + FAMILY_SEEDS + e * B + b``: the upper half of the run seed's
stride, apart from one-team training and the splits.
"""

from __future__ import annotations

SEED_STRIDE = 2**32  # training env seed = seed * SEED_STRIDE + copy; evaluation seeds stay below it
SPLIT_SEEDS = {"test": 1_000_000, "validation": 2_000_000}  # eval.split -> seed of copy 0
DEFAULT_SPLIT = "test"  # the split of a run config without eval.split (written before it existed)
SPLIT_WIDTH = 1_000_000  # seeds a split owns: at most this many evaluation copies
FAMILY_SEEDS = SEED_STRIDE // 2  # first training seed of a run seed on a family of teams


def split_seed(split: str | None) -> int:
    """The env seed of evaluation copy 0 of a split (copy ``b`` plays it ``+ b``).

    Args:
        split: ``test``, ``validation``, or None for :data:`DEFAULT_SPLIT`.

    Raises:
        KeyError: for another name (``runners/validation.py`` refuses it first, naming the key).
    """
    return SPLIT_SEEDS[split or DEFAULT_SPLIT]

"""Tables of the four tabular learners after a few hundred training ticks, for regression tests.

``python tests/learners/tabular/tabular_tables.py OUT.npz`` plays every learner of :data:`CASES` on
System-II and saves its tables (what ``learner.save`` writes, keys ``<case>/<array>``). The
fixture ``data/tabular_tables_v1.npz`` holds these tables for these seeds, computed by an
implementation of the learners in plain numpy and Python dicts (no compiled loops; git history
keeps it); ``test_tabular.py`` checks that the learners build exactly the same tables, so a
change of an update rule, a tie-break or a random draw fails there.
"""

from __future__ import annotations

import importlib
import sys
import tempfile
from pathlib import Path

import numpy as np
import yaml

from mrta_rl.checked_files import read_arrays
from mrta_rl.envs import AuctionEnv, AuctionParams
from mrta_rl.learners.tabular.base import Q_FILE, TabularLearner
from mrta_rl.partition import subg_partition
from mrta_rl.systems import build_system

ROOT = Path(__file__).resolve().parents[3]
FIXTURE = Path(__file__).resolve().parent / "data" / "tabular_tables_v1.npz"
CLASSES = {
    "subg_cql": "mrta_rl.learners.tabular.subg_cql:SubGCQLLearner",
    "cql": "mrta_rl.learners.tabular.cql:CQLLearner",
    "semi_cql": "mrta_rl.learners.tabular.semi_cql:SemiCQLLearner",
    "dql": "mrta_rl.learners.tabular.dql:DQLLearner",
}
EXPLORE = {"epsilon_start": 0.5, "epsilon_end": 0.3, "alpha": 1.0, "alpha_power": 1.0}
# the fixture's semi-CQL learns over the paper's whole-system state and its subG-CQL over the
# paper's group state and features (the learners' defaults are coarser states)
PAPER_STATES = {
    "semi_cql": {"state": "system"},
    "subg_cql": {"state": "group", "features": "paper"},
}
# (learner, hyperparameters): the defaults, and much exploration with 1/n learning rates
# the settings the fixture's tables were computed with, where a learner's yaml has others: a
# constant learning rate of 0.1, exploration decaying from 0.2 to 0, the max target and no
# visits before an entry competes with the prior
FIXTURE_SETTINGS = {
    "alpha": 0.1,
    "alpha_power": 0.0,
    "alpha_min": 0.0,
    "gamma": 0.9,
    "epsilon_start": 0.2,
    "epsilon_end": 0.0,
    "epsilon_decay_episodes": 20,
    "target": "max",
    "min_visits": 0,
}
CASES = {
    f"{name}/{hp}": (name, {**FIXTURE_SETTINGS, **PAPER_STATES.get(name, {}), **kw})
    for name in CLASSES
    for hp, kw in (("default", {}), ("explore", EXPLORE))
}
TICKS, BATCH, SEED, HORIZON = 250, 4, 7, 60  # several episodes: resets and truncations included


def play(env, learner, ticks: int, explore: bool = True, learn: bool = True) -> None:
    """The training loop of ``runners/tabular.py`` for ``ticks`` ticks; checks every action."""
    view = learner.encode(env)
    for _ in range(ticks):
        mask = env.action_mask
        actions = learner.act(view, mask, explore=explore)
        assert mask[np.arange(len(mask))[:, None], np.arange(mask.shape[1]), actions].all()
        result = env.step(actions)
        next_view = learner.encode(env)
        if learn:
            learner.update(view, actions, result, next_view, env.action_mask)
        view = next_view
        if env.done.any():
            env.reset()
            learner.end_episode()
            view = learner.encode(env)


def play_fused(env, learner, ticks: int, after_tick=None) -> None:
    """:func:`play` through ``train_tick`` (one compiled call per tick), ``ticks`` ticks.

    ``train_tick`` acts as soon as it has learned, so the tables match :func:`play`'s when the
    ticks end an episode (the last call does not act). ``after_tick(learner)``, if given, is
    called after every tick.
    """
    actions = None
    for _ in range(ticks):
        if actions is None:  # an episode starts
            actions = learner.train_tick(env, None)
        actions = learner.train_tick(env, env.step(actions))  # env.step checks every action
        if after_tick is not None:
            after_tick(learner)
        if actions is None:
            env.reset()
            learner.end_episode()


def build(name: str, hyperparameters: dict) -> tuple[AuctionEnv, TabularLearner]:
    """One learner of :data:`CLASSES` on System-II, untrained, and its env."""
    module, cls_name = CLASSES[name].split(":")
    cls = getattr(importlib.import_module(module), cls_name)
    system = build_system(yaml.safe_load((ROOT / "conf" / "system" / "system2.yaml").read_text()))
    partition = subg_partition(system) if cls.requires_partition else None
    active = partition.active_tasks(system) if partition is not None else None
    params = AuctionParams(horizon=HORIZON)
    env = AuctionEnv(system, params, batch_size=BATCH, seed=SEED, active_tasks=active)
    rng = np.random.default_rng(SEED)
    return env, cls(env=env, rng=rng, partition=partition, **hyperparameters)


def train(name: str, hyperparameters: dict, ticks: int = TICKS, fused: bool = False):
    """One learner trained for ``ticks`` ticks of System-II (:func:`play` or :func:`play_fused`)."""
    env, learner = build(name, hyperparameters)
    (play_fused if fused else play)(env, learner, ticks)
    return learner


def saved_tables(learner: TabularLearner) -> dict[str, np.ndarray]:
    """The tables as ``learner.save`` writes them (``q_tables.npz``): ``{name: array}``."""
    with tempfile.TemporaryDirectory() as folder:
        learner.save(Path(folder))
        return read_arrays(Path(folder) / Q_FILE, learner.state_schema())


def play_tables(name: str, hyperparameters: dict) -> dict[str, np.ndarray]:
    """The tables of one learner trained for :data:`TICKS` ticks of System-II."""
    return saved_tables(train(name, hyperparameters))


if __name__ == "__main__":
    tables = {}
    for case, (learner_name, hp) in CASES.items():
        tables.update({f"{case}/{k}": v for k, v in play_tables(learner_name, hp).items()})
    np.savez_compressed(sys.argv[1], **tables)

"""Trained bases: a learner that plays another run's trained learner, named by its run dir.

A learner may play a trained run as its base policy (``rollout``'s ``learner.base=<run dir>``).
The learner class says which setting names a run dir
(:meth:`~mrta_rl.learners.base.Learner.base_run`) and loads nothing: the runner checks the run
dir and its chain of bases here, before anything is built (:func:`check_base`, called by
:func:`~mrta_rl.runners.validation.validate_config`), then loads the run's learner
(:func:`~mrta_rl.runners.train.load_base`) and passes it to the learner as the runner argument
``base_policy``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from mrta_rl.config import ConfigError, UserError
from mrta_rl.learners import Learner
from mrta_rl.learners.base import learner_from_target
from mrta_rl.runners.run_config import read_run_config

MAX_BASES = 16  # run dirs in a chain of trained bases (a base whose own base is a run...)


def check_base(cls: type[Learner], hyperparameters: dict[str, Any]) -> Path | None:
    """The run dir of the trained learner a learner plays (``learner.base``), checked.

    The learner class says which setting names a run dir (:meth:`Learner.base_run`); the runner
    loads that run's learner and passes it as ``base_policy``. The run dir must exist and its
    chain of bases must end (:func:`check_base_chain`); that it is a run of the same team is
    checked when it is loaded (:func:`~mrta_rl.runners.train.load_base`).

    Raises:
        ConfigError: naming ``learner.base`` and what is wrong.
    """
    run_dir = cls.base_run(hyperparameters)
    if run_dir is None:
        return None
    if not run_dir.is_dir():
        raise ConfigError(f"learner.base: no such run dir: {run_dir}")
    check_base_chain(run_dir)
    return run_dir


def check_base_chain(run_dir: Path) -> None:
    """Follow the trained bases from ``run_dir`` through their configs; refuse a loop.

    A run dir's learner may itself play a run dir as its base, and so on: loading such a base
    loads the chain. A run dir that is its own base, or a chain that comes back to one of its
    run dirs, would load forever; it is refused before anything is loaded. A config that cannot
    be read ends the walk (loading the run names what is wrong with it).

    Raises:
        ConfigError: naming ``learner.base`` and the loop (or a chain of more than
            :data:`MAX_BASES` run dirs).
    """
    chain: list[Path] = []
    current = Path(run_dir)
    while True:
        chain.append(current)
        try:
            learner = read_run_config(current).get("learner")
            base = learner_from_target(learner.get("_target_"), "learner._target_").base_run(
                learner
            )
        except (UserError, AttributeError):
            return
        if base is None:
            return
        current = base
        seen = [p.resolve() for p in chain]
        if current.resolve() in seen:
            loop = chain[seen.index(current.resolve()) :]
            if len(loop) == 1:
                raise ConfigError(
                    f"learner.base: {loop[0]} is its own base; give a rule or another run dir"
                )
            shown = " -> ".join(str(p) for p in loop[:3])
            more = f" -> {len(loop) - 3} more" if len(loop) > 3 else ""
            raise ConfigError(
                f"learner.base: the bases loop: {shown}{more} -> back to the first; give a rule "
                "or another run dir"
            )
        if len(chain) >= MAX_BASES:
            raise ConfigError(
                f"learner.base: {run_dir}: a chain of more than {MAX_BASES} trained bases"
            )

"""The learners by name: the ``learner/`` yaml files of the config search path and their classes.

The learners are the yaml files of the ``learner/`` config group: the shipped ones
(:func:`~mrta_rl.conf_paths.conf_dir`) and those of any user config dir (Hydra's
``--config-dir`` or ``hydra.searchpath``), each naming its class with ``_target_``.
:func:`~mrta_rl.conf_paths.learner_files` lists them and :func:`learner_named` imports a class;
the validation, the benchmarks and the learning space table ask a learner by its name here and
keep no list.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from typing import Any

from mrta_rl.conf_paths import learner_block, learner_files, learner_settings
from mrta_rl.config import UserError, short_list
from mrta_rl.envs import AuctionEnv, AuctionParams
from mrta_rl.learners.base import Learner, learner_from_target
from mrta_rl.metrics.learning_space import TABULAR_LEARNERS, TabularLearnerName
from mrta_rl.partition import Partition, subg_partition
from mrta_rl.systems import RobotSystem


def learner_named(name: str, config_dirs: Iterable[str | os.PathLike] = ()) -> type[Learner]:
    """The learner class of ``learner/<name>.yaml`` in the config search path, imported.

    The configs are the user's own (like the code they run), so their ``_target_`` is imported.

    Args:
        name: The learner's name (``subg_cql``).
        config_dirs: User config dirs after the shipped ``conf/``
            (:func:`~mrta_rl.conf_paths.learner_files`).

    Returns:
        The :class:`~mrta_rl.learners.base.Learner` subclass.

    Raises:
        UserError: naming the learner or the file and key.
    """
    files = learner_files(config_dirs)
    if name not in files:
        raise UserError(f"unknown learner {name!r}; known: {short_list(files, 12)}")
    target = learner_block(name, files).get("_target_")
    return learner_from_target(target, f"{files[name]}: _target_")


def any_team_learners() -> list[str]:
    """The shipped learners that learn a state fitting any team, at their settings or another.

    ``vdn (learner.network=set)``: a learner whose settings decide it
    (``Learner.fits_any_team``) is listed with the setting that makes it fit.
    """
    names = []
    files = learner_files()
    for name in files:
        cls = learner_named(name)
        if not cls.trains():
            continue
        defaults = learner_settings(learner_block(name, files))
        if cls.fits_any_team(defaults):
            names.append(name)
        elif cls.fits_any_team({**defaults, "network": "set"}):
            names.append(f"{name} (learner.network=set)")
    return names


def learning_space_dimension(
    learner: str,
    env: AuctionEnv,
    partition: Partition | None = None,
    features: str = "paper",
    **settings: Any,
) -> int:
    """Analytic learning space dimension of one learner of ``conf/learner`` on ``env``.

    The formula is the learner class's own (``learning_space_dimension``, see
    :class:`~mrta_rl.learners.base.Learner`); settings it does not pass take the paper's
    values (semi-CQL's ``state="system"``, subG-CQL's ``state="group"``).

    Args:
        learner: The learner's name (``"cql"``, ``"semi_cql"``, ``"dql"``, ``"subg_cql"``...).
        env: The env the learner runs on (for subG-CQL: built with the partition's ``Lambda_i``).
        partition: The subG partition (required for ``"subg_cql"``).
        features: The learner's encoding, ``"paper"`` or ``"time_to_free"``
            (``envs/encodings.py``).
        **settings: Further settings of the learner's state (``state``).

    Returns:
        The exact dimension.

    Raises:
        ValueError: on a learner without a learning space, or ``"subg_cql"`` without a
            partition.
    """
    cls = learner_named(learner)
    dimension = cls.learning_space_dimension(env, partition, {"features": features, **settings})
    if dimension is None:
        raise ValueError(f"learner {learner!r} ({cls.__name__}) has no learning space dimension")
    return dimension


def learning_space_table(
    system: RobotSystem, params: AuctionParams | None = None
) -> dict[TabularLearnerName, int]:
    """Table-9 analogue for one system: the dimension of every tabular learner.

    Args:
        system: The robot team.
        params: Dynamics parameters (default: spec defaults plus the system's overrides); only
            ``slots`` and the durations matter.

    Returns:
        ``{learner: dimension}`` in :data:`~mrta_rl.metrics.learning_space.TABULAR_LEARNERS` order.
    """
    env = AuctionEnv(system, params, batch_size=1)
    partition = subg_partition(system)
    sub_env = AuctionEnv(system, params, batch_size=1, active_tasks=partition.active_tasks(system))
    return {
        name: learning_space_dimension(name, sub_env if name == "subg_cql" else env, partition)
        for name in TABULAR_LEARNERS
    }

"""What the Gymnasium and PettingZoo views accept, shared by both: systems, params, bad actions.

* **Systems** by name (``"system1"``, ``"system2"``, ``"random"``: the files of ``conf/system/``,
  shipped in the package), by the path of a team yaml anywhere
  (:func:`mrta_rl.conf_paths.system_file`), as a system config mapping (the content of such a
  file) or as a :class:`RobotSystem`.
* **Params** as :class:`AuctionParams` or as a mapping of overrides on top of the spec defaults
  and the system file's ``env:`` block (``{"horizon": 200}``).
* **Invalid actions** (docs/spec/auction_env.md, step 4: the core rejects them with a
  ``ValueError``). Outside clients sample unmasked actions (Gymnasium's and SB3's ``check_env``,
  PettingZoo's ``parallel_api_test`` and ``parallel_seed_test``, ``action_space.sample()``), so
  the views' default, ``"wait"``, turns every invalid or out-of-range sub-action into 0 (wait)
  and flags it in ``info["invalid_action"]``; ``"raise"`` keeps the core's error.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from typing import Any, Literal

import numpy as np

from mrta_rl.checked_files import read_yaml
from mrta_rl.conf_paths import system_file
from mrta_rl.envs.auction import AuctionEnv
from mrta_rl.envs.params import AuctionParams
from mrta_rl.systems import RobotSystem, build_system

InvalidAction = Literal["raise", "wait"]
INVALID_ACTION_MODES: tuple[str, ...] = ("raise", "wait")
DEFAULT_INVALID_ACTION: InvalidAction = "wait"

SystemLike = RobotSystem | str | os.PathLike | Mapping[str, Any]


def check_invalid_action(invalid_action: str) -> None:
    """Reject an unknown invalid-action mode.

    Raises:
        ValueError: naming the mode and the known ones.
    """
    if invalid_action not in INVALID_ACTION_MODES:
        raise ValueError(
            f"invalid_action must be one of {INVALID_ACTION_MODES}, got {invalid_action!r}"
        )


def resolve_system(system: SystemLike) -> RobotSystem:
    """The robot team named or described by ``system`` (see the module docstring).

    Raises:
        UserError: for an unknown name or a missing file, naming it and the known systems (a
            ``ValueError``).
        SystemConfigError: for a malformed system description (naming the culprit).
    """
    if isinstance(system, RobotSystem):
        return system
    if isinstance(system, Mapping):
        return build_system(system)
    if isinstance(system, str | os.PathLike):
        return build_system(read_yaml(system_file(system)))
    raise TypeError(
        f"system must be a RobotSystem, a name, a yaml path or a mapping, got {type(system)}"
    )


def resolve_params(
    system: RobotSystem, params: AuctionParams | Mapping[str, Any] | None
) -> AuctionParams | None:
    """``params`` as :class:`AuctionParams`; a mapping overrides the system's own parameters.

    ``None`` stays ``None``: the core then uses the spec defaults and the system's ``env:`` block.
    """
    if params is None or isinstance(params, AuctionParams):
        return params
    return AuctionParams.merged(system.env_overrides, params)


def build_core(
    system: SystemLike,
    params: AuctionParams | Mapping[str, Any] | None,
    active_tasks: np.ndarray | None,
    invalid_action: str,
) -> AuctionEnv:
    """The one-copy core of a view, after checking every argument (nothing is built before).

    Raises:
        ValueError: on an unknown ``invalid_action``, system or parameter, naming it.
    """
    check_invalid_action(invalid_action)
    system = resolve_system(system)
    return AuctionEnv(
        system, resolve_params(system, params), batch_size=1, active_tasks=active_tasks
    )


def sanitize_actions(
    actions: np.ndarray, mask: np.ndarray, invalid_action: InvalidAction
) -> tuple[np.ndarray, np.ndarray]:
    """Apply the invalid-action mode to ``[B, m]`` actions under ``mask`` ``[B, m, K + 1]``.

    Args:
        actions: Joint actions.
        mask: The core's action mask.
        invalid_action: ``"raise"`` leaves the actions for the core to reject (spec step 4);
            ``"wait"`` turns every invalid or out-of-range action into 0 (wait).

    Returns:
        The actions to send to the core and ``[B, m]`` bool flags of the replaced ones (all
        False under ``"raise"``).
    """
    if invalid_action == "raise":
        return actions, np.zeros(actions.shape, bool)
    in_range = (actions >= 0) & (actions < mask.shape[-1])
    safe = np.where(in_range, actions, 0)
    valid = in_range & np.take_along_axis(mask, safe[..., None], axis=-1)[..., 0]
    return np.where(valid, actions, 0), ~valid


def fresh_seed(rng: np.random.Generator) -> int:
    """A core seed drawn from ``rng`` (for a first reset without a seed: fresh entropy)."""
    return int(rng.integers(1 << 62))

"""A torch learner's files: weights, description and training state, written and checked.

A torch learner saves ``weights.pt`` (a ``state_dict``), ``learner.json`` (class, groups, settings)
and, in training checkpoints, ``training.pt`` (optimizer and its own training state). They are
written through Python file objects (:func:`write_tensors`: a refused write is an ``OSError``
naming the file) and read with ``weights_only`` loading through the checked reader
(``mrta_rl/checked_files.py``), then checked against the learner built for the run: names, shapes,
dtypes, finite values, an optimizer's settings and moments. Training stops at the first loss or
weight that is not finite (:func:`check_loss`, :func:`check_finite_weights`), before it is used or
saved.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import torch
from torch import nn

from mrta_rl.checked_files import read_tensors, tensor_file_limit
from mrta_rl.config import UserError, short_list
from mrta_rl.learners.base import NonFiniteState, read_description
from mrta_rl.run_layout import RunDirError

WEIGHTS_FILE = "weights.pt"  # state_dict of the networks, torch.load(weights_only)
META_FILE = "learner.json"  # class, groups and settings, to check a saved state fits the run
TRAINING_FILE = "training.pt"  # optimizer and the learner's training state (checkpoints)


def read_meta(path: Path, schema: dict[str, Any]) -> dict[str, Any]:
    """A neural learner's ``learner.json``, checked against its schema (``run_layout``).

    Raises:
        RunDirError: naming the file and the key.
    """
    meta = read_description(path, schema)
    if meta["gradient_steps"] < 0:
        raise RunDirError(f"{path}: gradient_steps: must be >= 0, got {meta['gradient_steps']}")
    return meta


def write_tensors(payload: Any, path: Path) -> None:
    """``torch.save`` through a Python file object, so that a refused write is an ``OSError``.

    Given a path, torch's own writer turns a full disk or a file size limit into a
    ``RuntimeError`` that names neither the fault nor the file; through a file object the
    ``OSError`` is that error's context, which the commands report in one line naming the file
    (``mrta_rl/errors.py``). The bytes written are the same.
    """
    with open(path, "wb") as file:
        torch.save(payload, file)


def read_weights(path: Path, networks: nn.Module) -> dict[str, torch.Tensor]:
    """``weights.pt`` of a learner's networks, checked against them (:func:`check_state_dict`).

    Raises:
        RunDirError: naming the file, if it is not a regular file, too big for these networks,
            not a weights file, or its tensors are not the networks' (names, shapes, dtypes,
            finite values).
    """
    expected = networks.state_dict()
    device = next(iter(expected.values())).device if expected else torch.device("cpu")
    state = read_tensors(
        path, device, tensor_file_limit(expected), "a weights file written by this package"
    )
    check_state_dict(state, expected, path)
    return state


def check_state_dict(
    state: Any,
    expected: dict[str, torch.Tensor],
    path: Path | str,
    error: type[UserError] = RunDirError,
) -> None:
    """Saved tensors against the learner's own: names, shapes, dtypes and finite values.

    Args:
        state: The loaded state dict.
        expected: The learner's own (``state_dict()``).
        path: The file (and key), or what made the tensors, for messages.
        error: The error to raise.

    Raises:
        RunDirError: (or ``error``) naming the file and the first mismatch.
    """
    if not isinstance(state, dict) or set(state) != set(expected):
        names = short_list(sorted(state)) if isinstance(state, dict) else type(state).__name__
        raise error(
            f"{path}: holds tensors {names}, this run's learner has {short_list(sorted(expected))} "
            "(saved for another system, partition or learner?)"
        )
    for name, want in expected.items():
        got = state[name]
        if not isinstance(got, torch.Tensor) or got.shape != want.shape or got.dtype != want.dtype:
            shape = tuple(got.shape) if isinstance(got, torch.Tensor) else type(got).__name__
            raise error(
                f"{path}: tensor {name} is {shape}, expected {tuple(want.shape)} {want.dtype}"
            )
        if got.is_floating_point() and not torch.isfinite(got).all():
            raise error(f"{path}: tensor {name} holds NaN or infinite values")


def check_finite_weights(state: dict[str, torch.Tensor], source: str) -> None:
    """Refuse to keep weights that hold NaN or infinity (before they are saved).

    Raises:
        NonFiniteState: naming the learner, the step and the tensor.
    """
    check_state_dict(state, state, source, NonFiniteState)


def check_loss(value: float, label: str, step: int) -> None:
    """Stop training at a NaN or infinite loss, before the gradient step would use it.

    Raises:
        NonFiniteState: naming the learner and the gradient step.
    """
    if not math.isfinite(value):
        raise NonFiniteState(f"{label}: gradient step {step}: the loss is {value}")


def check_optimizer_state(saved: Any, optimizer: torch.optim.Optimizer, path: Path) -> None:
    """An optimizer's saved state (Adam's) against the optimizer the run built.

    The parameter groups must hold the same parameters and settings (learning rate, betas...);
    each parameter's state tensors are finite and of its shape, its ``step`` and its second
    moments (``*_sq``) >= 0.

    Raises:
        RunDirError: naming the file and the key.
    """
    fresh = optimizer.state_dict()
    where = f"{path}: optimizer"
    if not isinstance(saved, dict) or set(saved) != set(fresh):
        raise RunDirError(f"{where}: expected the keys {short_list(sorted(fresh))}")
    groups = saved["param_groups"]
    if not isinstance(groups, list) or len(groups) != len(fresh["param_groups"]):
        raise RunDirError(f"{where}.param_groups: expected {len(fresh['param_groups'])} groups")
    shapes = {}
    for g, (group, want, live) in enumerate(
        zip(groups, fresh["param_groups"], optimizer.param_groups, strict=True)
    ):
        if not isinstance(group, dict) or group.get("params") != want["params"]:
            raise RunDirError(f"{where}.param_groups[{g}]: not this run's parameters")
        for key, value in want.items():
            if key != "params" and key in group and group[key] != value:
                raise RunDirError(
                    f"{where}.param_groups[{g}].{key}: {str(group[key])[:40]}, the run's is {value}"
                )
        shapes.update(zip(want["params"], (p.shape for p in live["params"]), strict=True))
    state = saved["state"]
    if not isinstance(state, dict) or not set(state) <= set(shapes):
        raise RunDirError(f"{where}.state: not the state of this run's parameters")
    for index, entries in state.items():
        if not isinstance(entries, dict):
            raise RunDirError(f"{where}.state.{index}: must be a mapping of tensors")
        for key, value in entries.items():
            name = f"{where}.state.{index}.{key}"
            if not isinstance(value, torch.Tensor) or not value.is_floating_point():
                raise RunDirError(f"{name}: must be a float tensor")
            if value.numel() != 1 and value.shape != shapes[index]:
                raise RunDirError(
                    f"{name}: shape {tuple(value.shape)}, the parameter's is {tuple(shapes[index])}"
                )
            if not torch.isfinite(value).all():
                raise RunDirError(f"{name}: holds NaN or infinite values")
            if (key == "step" or key.endswith("_sq")) and bool((value < 0).any()):
                raise RunDirError(f"{name}: holds {float(value.min())}, must be >= 0")

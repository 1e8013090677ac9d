"""Compiled code takes its arrays in named records: no numba function has more than 8 parameters."""

from __future__ import annotations

import importlib
import inspect
from pathlib import Path

import mrta_rl

PACKAGE = Path(mrta_rl.__file__).parent
MAX_PARAMETERS = 8  # more arrays travel in a record (e.g. envs/state_codes.py's)


def numba_modules() -> list[str]:
    """Every module of the package that uses numba, by its source."""
    names = []
    for path in sorted(PACKAGE.rglob("*.py")):
        if "numba" in path.read_text():
            parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
            names.append(".".join(parts[:-1] if parts[-1] == "__init__" else parts))
    return names


def dispatchers() -> dict[str, object]:
    """``module.name`` -> every numba dispatcher (an object with ``py_func``) of those modules."""
    found: dict[int, tuple[str, object]] = {}
    for module_name in numba_modules():
        module = importlib.import_module(module_name)
        for name, obj in vars(module).items():
            if hasattr(obj, "py_func") and id(obj) not in found:
                found[id(obj)] = (f"{module_name}.{name}", obj)
    return dict(found.values())


def test_the_walk_finds_the_kernels_and_the_rules():
    from mrta_rl import rules
    from mrta_rl.envs import kernel, state_codes
    from mrta_rl.learners.tabular import group_kernels, robot_kernels

    found = list(dispatchers().values())
    for kernel_function in (
        kernel.step,
        kernel.unpack,  # generated from the field table
        state_codes.encode_local,
        state_codes.encode_groups,
        group_kernels.tick_groups,
        robot_kernels.tick_local,
        rules.reserve,
    ):
        assert any(f is kernel_function for f in found), kernel_function


def test_no_compiled_function_takes_more_than_8_parameters():
    too_many = {
        name: list(inspect.signature(f.py_func).parameters)
        for name, f in dispatchers().items()
        if len(inspect.signature(f.py_func).parameters) > MAX_PARAMETERS
    }
    assert not too_many, f"group these arrays in a record: {too_many}"

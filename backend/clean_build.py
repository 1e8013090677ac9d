"""The package's build backend: setuptools', leaving the source tree as it found it.

``pip wheel .`` and ``pip install .`` build with setuptools, which writes ``build/`` and
``mrta_rl.egg-info/`` into the source tree. Each build hook removes those it made; one that was
there before the build (an editable install's ``mrta_rl.egg-info``) stays. Editable installs
(``pip install -e .``) are setuptools' own, unchanged.
"""

from __future__ import annotations

import functools
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

from setuptools import build_meta
from setuptools.build_meta import (  # noqa: F401  (the editable install's hooks, PEP 660)
    build_editable,
    get_requires_for_build_editable,
    prepare_metadata_for_build_editable,
)

BUILD_FILES = ("build", "mrta_rl.egg-info")  # what setuptools writes into the source tree


def _leaving_no_files(hook: Callable[..., Any]) -> Callable[..., Any]:
    """The hook, removing the :data:`BUILD_FILES` it made (pip runs it in the source tree)."""

    @functools.wraps(hook)
    def run(*args: Any, **kwargs: Any) -> Any:
        made = [Path(name) for name in BUILD_FILES if not Path(name).exists()]
        try:
            return hook(*args, **kwargs)
        finally:
            for path in made:
                shutil.rmtree(path, ignore_errors=True)

    return run


get_requires_for_build_wheel = _leaving_no_files(build_meta.get_requires_for_build_wheel)
get_requires_for_build_sdist = _leaving_no_files(build_meta.get_requires_for_build_sdist)
prepare_metadata_for_build_wheel = _leaving_no_files(build_meta.prepare_metadata_for_build_wheel)
build_wheel = _leaving_no_files(build_meta.build_wheel)
build_sdist = _leaving_no_files(build_meta.build_sdist)

"""Config files read with bounds: size, text encoding, nesting depth and YAML aliases.

A system file may come from anyone (``hydra.searchpath=[file://<dir>]``), and so may a run
dir's ``.hydra/*.yaml``. Hydra and OmegaConf read YAML without bounds: a 5 MB file of robots
takes minutes to compose (OmegaConf loads about 90 kB of robots per second), an alias-expansion
file ("billion laughs") grows exponentially as OmegaConf copies every alias, 5,000 nested lists
overflow Python's stack and binary garbage fails to decode. :func:`check_yaml_file` refuses each
of these in one line naming the file, before any of it is parsed into a config, with the checks of
``mrta_rl/checked_files.py`` (:func:`~mrta_rl.checked_files.read_yaml`): a regular file, at most
:data:`~mrta_rl.checked_files.MAX_YAML_BYTES`, composed without expanding an alias, its syntax
errors named by line and column. No config of this package uses an alias.

:func:`guard_config_files` puts the check in front of Hydra's ``file://`` config source, so a
system file (or any other file of a search path or of ``conf/``) is checked before Hydra composes
it; the runners install it at import, next to their resolvers.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from mrta_rl.checked_files import read_yaml


def check_yaml_file(path: Path | str) -> None:
    """Refuse a YAML file that is unsafe to compose or does not parse (``read_yaml``'s checks).

    Refused: anything but a regular file, a file too big, not UTF-8 text, nested too deeply,
    using aliases, or with a syntax error.

    Args:
        path: The file.

    Raises:
        RunDirError: naming the file and what it passes (a syntax error: the line and column).
    """
    read_yaml(path)


def guard_config_files() -> None:
    """Check every file Hydra's ``file://`` config source loads with :func:`check_yaml_file`.

    Hydra has no hook before it parses a file; its registry of config sources keeps the first
    class registered for a scheme, so a checking subclass registered before Hydra's own plugin
    scan (at import of the runners, before ``@hydra.main`` runs) reads every ``file://`` config.
    Idempotent.
    """
    from hydra._internal.core_plugins.file_config_source import FileConfigSource as HydraSource
    from hydra._internal.sources_registry import SourcesRegistry

    class FileConfigSource(HydraSource):  # Hydra's name: the registry keeps the first of a name
        def load_config(self, config_path: str) -> Any:
            name = self._normalize_file_name(config_path)
            full_path = os.path.realpath(os.path.join(self.path, name))
            if os.path.isfile(full_path):
                check_yaml_file(full_path)
            return super().load_config(config_path)

    SourcesRegistry.instance().register(FileConfigSource)

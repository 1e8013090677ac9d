"""Config files read with bounds: size, text encoding, nesting depth and YAML aliases.

A system file may come from anyone (``hydra.searchpath=[file://<dir>]``), and so may a run
dir's ``.hydra/*.yaml``. Hydra and OmegaConf read YAML without bounds: a 5 MB file of robots
takes minutes to compose (OmegaConf loads about 90 kB of robots per second), an alias-expansion
file ("billion laughs") grows exponentially as OmegaConf copies every alias, 5,000 nested lists
overflow Python's stack and binary garbage fails to decode. :func:`check_yaml_file` refuses each
of these in one line naming the file, before any of it is parsed into a config: it composes the
YAML (a linear pass over the text that never expands an alias) and refuses aliases and deep
nesting. No config of this package uses an alias.

:func:`guard_config_files` puts the check in front of Hydra's ``file://`` config source, so a
system file (or any other file of a search path or of ``conf/``) is checked before Hydra composes
it; the runners install it at import, next to their resolvers.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import yaml

from mrta_rl.config import UserError

MAX_FILE_BYTES = 2**20  # 1 MiB, about 40,000 robots in table form (random teams have no limit)
MAX_DEPTH = 64  # nesting of mappings and lists; a system file needs 4


class ConfigFileError(UserError):
    """A config file that is refused before it is parsed; the message names the file."""


class _BoundedComposer(yaml.SafeLoader):
    """YAML composer that refuses aliases and nesting deeper than :data:`MAX_DEPTH`."""

    depth = 0
    source = ""

    def compose_node(self, parent: Any, index: Any) -> Any:
        if self.check_event(yaml.AliasEvent):
            mark = self.peek_event().start_mark
            raise ConfigFileError(
                f"{self.source}: line {mark.line + 1}: YAML aliases (*name) are refused "
                "(write the values out)"
            )
        self.depth += 1
        try:
            if self.depth > MAX_DEPTH:
                mark = self.peek_event().start_mark
                raise ConfigFileError(
                    f"{self.source}: line {mark.line + 1}: nested deeper than {MAX_DEPTH} levels"
                )
            return super().compose_node(parent, index)
        finally:
            self.depth -= 1


def check_yaml_file(path: Path | str, *, max_bytes: int = MAX_FILE_BYTES) -> None:
    """Refuse a YAML file that is too big, not UTF-8 text, too deeply nested or uses aliases.

    Args:
        path: The file.
        max_bytes: Its largest allowed size.

    Raises:
        ConfigFileError: naming the file and the limit it passes (a YAML syntax error is left to
            the reader, which names the line).
    """
    path = Path(path)
    try:
        size = path.stat().st_size
    except OSError as err:
        raise ConfigFileError(f"{path}: cannot be read ({err.strerror})") from None
    if size > max_bytes:
        raise ConfigFileError(
            f"{path}: {size:,} bytes, more than the limit of {max_bytes:,} bytes for a config "
            "file (a larger team: system=random with n_robots)"
        )
    try:
        text = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as err:
        raise ConfigFileError(
            f"{path}: not UTF-8 text (byte {err.start}); a config file is YAML"
        ) from None
    except OSError as err:
        raise ConfigFileError(f"{path}: cannot be read ({err.strerror})") from None
    if "\x00" in text:
        raise ConfigFileError(f"{path}: not a text file (it holds NUL bytes); a config is YAML")
    loader = _BoundedComposer(text)
    loader.source = str(path)
    try:
        while loader.check_node():
            loader.get_node()
    except yaml.YAMLError:
        return  # the reader's own message names the line
    finally:
        loader.dispose()


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

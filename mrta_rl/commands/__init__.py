"""The console commands (``[project.scripts]``: ``mrta-train``, ``mrta-evaluate``, ...).

Each module is one command and is named as its script in ``scripts/`` (Hydra names the job,
and so the run dir's log file, after the module: ``train.log``). The scripts are thin wrappers
over these modules, so ``python scripts/train.py ARGS`` and ``mrta-train ARGS`` run the same code
with the same overrides, from any directory.

A team yaml from anywhere: ``system=/path/to/team.yaml`` (or ``system=team.yaml`` relative to the
working directory; a comma-separated list in a sweep) is read before Hydra starts, checked as a
shipped system is, and given to Hydra under its file name (``team``), which the run then
reports as its system; a team without a ``name:`` is named so too.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from typing import Any, NoReturn

from hydra.core.config_store import ConfigStore

from mrta_rl.checked_files import read_yaml
from mrta_rl.conf_paths import is_system_path, shipped_systems, system_file
from mrta_rl.config import UserError
from mrta_rl.systems import build_system

SYSTEM_OVERRIDE = "system="


class CommandLineParser(argparse.ArgumentParser):
    """``argparse`` for the commands that take options: a bad option is a one-line user error.

    ``argparse`` prints its usage and exits; here the error is a :class:`UserError`, which the
    command prints as one ``error: ...`` line with the exit code of every user error
    (``mrta_rl/errors.py``). ``--help`` prints the usage as usual.
    """

    def error(self, message: str) -> NoReturn:
        """Raise the parse error as a user error (``argument --repeats: invalid int value``)."""
        raise UserError(f"{message} (see {self.prog} --help)")


def use_team_files(
    argv: list[str] | None = None, check: Callable[[dict[str, Any]], Any] = build_system
) -> list[str]:
    """Turn ``system=<team yaml>`` overrides into names of Hydra's ``system`` group.

    Every yaml path of a ``system=`` override (several: a sweep) is read, checked with
    ``check`` and stored in Hydra's config store under the file's name; the override then
    names it. Names of shipped systems pass unchanged.

    Args:
        argv: The command line, changed in place; default ``sys.argv``.
        check: Builds the team from the file's content, or raises a :class:`UserError`; default
            :func:`~mrta_rl.systems.build_system`. A command whose limits are known before
            Hydra composes its config checks them here, before a big team reaches Hydra.

    Returns:
        The command line.

    Raises:
        UserError: for a missing file, a malformed team (the message names the file and the
            culprit) or a file named as a shipped system or as another team file.
    """
    argv = sys.argv if argv is None else argv
    taken: dict[str, str] = {}
    for i, arg in enumerate(argv):
        if not arg.startswith(SYSTEM_OVERRIDE):
            continue
        names = []
        for item in arg[len(SYSTEM_OVERRIDE) :].split(","):
            if not is_system_path(item):
                names.append(item)
                continue
            path = system_file(item).resolve()
            name = path.stem
            if name in shipped_systems() or taken.get(name, str(path)) != str(path):
                raise UserError(
                    f"system={item}: the file name {name!r} is taken by "
                    f"{'a shipped system' if name in shipped_systems() else taken[name]}; "
                    "rename the file"
                )
            taken[name] = str(path)
            team = read_yaml(path)
            try:
                check(team)
            except (UserError, TypeError) as err:
                raise UserError(f"{item}: {err}") from None  # the name typed, not a link's target
            if isinstance(team, dict) and "name" not in team:  # the name the run reports
                team = {"name": name, **team}
            ConfigStore.instance().store(group="system", name=name, node=team)
            names.append(name)
        argv[i] = SYSTEM_OVERRIDE + ",".join(names)
    return argv

"""``mrta-report``: a sweep (or run dirs) as report.md, CSV tables, figures and marl-eval JSON.

Usage: ``mrta-report multirun/paper/<date> [--out DIR]`` or
``mrta-report outputs/<run1> outputs/<run2> ...`` (or ``python scripts/report.py ...``).
Default output: ``<input>/report`` (several inputs: ``<their common parent>/report``). See
mrta_rl/reports/report.py. A report reads run dirs only: this command loads no runner, learner
or torch.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys

import yaml
from hydra.errors import HydraException

from mrta_rl.config import UserError
from mrta_rl.reports import build_report

# the exit codes of every script (mrta_rl/runners/cli.py): a user error as argparse, Ctrl-C as
# the shell; runners/cli.py is not imported, since it loads the runners and the learners
EXIT_USER_ERROR, EXIT_INTERRUPTED = 2, 130


def _task() -> None:
    parser = argparse.ArgumentParser(prog="mrta-report", description=__doc__.splitlines()[0])
    parser.add_argument("inputs", nargs="+", help="multirun dir, run dirs, or folders of run dirs")
    parser.add_argument("--out", default=None, help="output folder (default: <input>/report)")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    files = build_report(args.inputs, args.out)
    runs, missing = len(files.collection.runs), len(files.collection.missing)
    left_out = len(files.collection.unreadable)
    counts = f"{runs} runs, {missing} missing" + (f", {left_out} left out" if left_out else "")
    print(
        f"{files.report} ({counts}; "
        f"{len(files.csvs)} CSV files, {len(files.figures)} figures in {files.out_dir})"
    )


def main() -> None:
    """Run the command; a user error is one ``error: ...`` line, Ctrl-C ``interrupted``."""
    try:
        _task()
    except (UserError, HydraException, yaml.YAMLError, KeyboardInterrupt) as err:
        if os.environ.get("HYDRA_FULL_ERROR") == "1":  # the traceback is wanted
            raise
        if isinstance(err, KeyboardInterrupt):
            print("interrupted", file=sys.stderr)
            sys.exit(EXIT_INTERRUPTED)
        syntax = "YAML syntax error: " if isinstance(err, yaml.YAMLError) else ""
        print(f"error: {syntax}{err}", file=sys.stderr)
        sys.exit(EXIT_USER_ERROR)

"""``mrta-report``: a sweep (or run dirs) as report.md, CSV tables, figures and marl-eval JSON.

Usage: ``mrta-report multirun/paper/<date> [--out DIR]`` or
``mrta-report outputs/<run1> outputs/<run2> ...`` (or ``python scripts/report.py ...``).
Default output: ``<input>/report`` (several inputs: ``<their common parent>/report``). See
mrta_rl/reports/report.py. A report reads run dirs only: this command loads no runner, learner
or torch.
"""

from __future__ import annotations

import logging
import os
import sys

from mrta_rl.commands import CommandLineParser
from mrta_rl.errors import EXIT_INTERRUPTED, EXIT_USER_ERROR, check_output_folder, user_message
from mrta_rl.reports import build_report, default_out_dir


def _task() -> None:
    parser = CommandLineParser(prog="mrta-report", description=__doc__.splitlines()[0])
    parser.add_argument("inputs", nargs="+", help="multirun dir, run dirs, or folders of run dirs")
    parser.add_argument("--out", default=None, help="output folder (default: <input>/report)")
    args = parser.parse_args()
    # before any run is read: a report that could not be written is not made
    out = args.out if args.out is not None else default_out_dir(args.inputs)
    check_output_folder(out, "--out" if args.out is not None else "the report folder")
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
    """Run the command; a user error is one ``error: ...`` line, Ctrl-C ``interrupted``.

    The exit codes and messages are those of every command (``mrta_rl/errors.py``); this
    command does not use ``runners/cli.py``, which loads the runners and the learners.
    """
    try:
        _task()
    except (Exception, KeyboardInterrupt) as err:
        if os.environ.get("HYDRA_FULL_ERROR") == "1":  # the traceback is wanted
            raise
        if isinstance(err, KeyboardInterrupt):
            print("interrupted", file=sys.stderr)
            sys.exit(EXIT_INTERRUPTED)
        message = user_message(err)
        if message is None:
            raise  # a bug: its traceback
        print(f"error: {message}", file=sys.stderr)
        sys.exit(EXIT_USER_ERROR)

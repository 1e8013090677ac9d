"""``mrta-report``: turn a sweep (or run dirs) into report.md, CSV tables and PNG figures.

Usage: ``mrta-report multirun/paper/<date> [--out DIR]`` or
``mrta-report outputs/<run1> outputs/<run2> ...`` (or ``python scripts/report.py ...``).
Default output: ``<input>/report`` (several inputs: ``<their common parent>/report``). See
mrta_rl/reports/report.py.
"""

from __future__ import annotations

import argparse
import logging

from mrta_rl.reports import build_report
from mrta_rl.runners import cli


def _task() -> None:
    parser = argparse.ArgumentParser(prog="mrta-report", description=__doc__.splitlines()[0])
    parser.add_argument("inputs", nargs="+", help="multirun dir, run dirs, or folders of run dirs")
    parser.add_argument("--out", default=None, help="output folder (default: <input>/report)")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    files = build_report(args.inputs, args.out)
    runs, missing = len(files.collection.runs), len(files.collection.missing)
    print(
        f"{files.report} ({runs} runs, {missing} missing; "
        f"{len(files.csvs)} CSV files, {len(files.figures)} figures in {files.out_dir})"
    )


def main() -> None:
    """Run the command with the arguments of the command line."""
    cli.run(_task)

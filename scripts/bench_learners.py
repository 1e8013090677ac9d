"""Training copy-ticks/s of every learner, next to the bare env and a plain per-copy Python loop.

Usage: python scripts/bench_learners.py [--learners subg_cql dql ...] [--episodes 2] [--repeats 3]
       [--horizon 200] [--baseline /path/to/other/checkout] [--experiment NAME]
       [--config-dir DIR ...] [--override KEY=VALUE ...] [--list] [--out bench_learners.json]

The learners are the ``learner/`` yaml files of the shipped ``conf/`` and of each
``--config-dir`` (as ``scripts/train.py --config-dir``); by default every one that trains.
``--list`` prints them and exits. ``--override KEY=VALUE`` sets a config key of every learner
run (``--override learner.network=set``); the ``system.*`` and ``env.*`` ones also set the team
of the yardsticks. With ``--baseline`` the same measurements run, in turns, on another checkout
of mrta_rl (e.g. today's main) and the table shows the speed-up over it.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

from tqdm import tqdm

from mrta_rl.bench.learners import (
    format_neural_table,
    format_table,
    run_worker,
    summarize,
    trained_learners,
)
from mrta_rl.commands import CommandLineParser
from mrta_rl.config import Range, UserError, check_arguments, short_list
from mrta_rl.errors import check_output_file
from mrta_rl.learners.registry import learner_files
from mrta_rl.runners import cli


@dataclass(frozen=True)
class LearnerBenchArguments:
    """The numbers of the command line, checked before any work."""

    episodes: Annotated[int, Range(1)]  # training episodes per learner
    horizon: Annotated[int, Range(0)]  # ticks per episode, 0: the config's
    repeats: Annotated[int, Range(1)]  # repeats (min and median)
    seconds: Annotated[float, Range(0, low_open=True)]  # least wall time per yardstick, finite


def main() -> None:
    parser = CommandLineParser(prog="bench_learners.py", description=__doc__.splitlines()[0])
    parser.add_argument("--learners", nargs="+", help="learner names (default: all that train)")
    parser.add_argument(
        "--config-dir", action="append", default=[], help="a user config dir with learner/*.yaml"
    )
    parser.add_argument(
        "--override", action="append", default=[], help="KEY=VALUE of every run (repeatable)"
    )
    parser.add_argument("--list", action="store_true", help="print the learners and exit")
    parser.add_argument("--system", default="system2", help="conf/system name")
    parser.add_argument("--episodes", type=int, default=2, help="training episodes per learner")
    parser.add_argument("--horizon", type=int, default=0, help="ticks per episode (0: config's)")
    parser.add_argument("--repeats", type=int, default=3, help="repeats (min and median)")
    parser.add_argument("--seconds", type=float, default=2.0, help="least wall time per yardstick")
    parser.add_argument("--baseline", type=Path, help="another checkout to measure in turns")
    parser.add_argument("--experiment", default="", help="conf/experiment for this checkout's runs")
    parser.add_argument("--out", default="bench_learners.json")
    args = parser.parse_args()
    check_arguments(LearnerBenchArguments, args)  # before any work
    known = learner_files(args.config_dir)
    unknown = sorted(set(args.learners or ()) - set(known))
    if unknown:
        raise UserError(
            f"--learners: unknown {', '.join(unknown)} (known: {short_list(sorted(known))})"
        )
    learners = args.learners or trained_learners(args.config_dir)
    if args.list:
        print("\n".join(learners))
        return
    check_output_file(args.out, "--out")
    codes = {"baseline": args.baseline, "this": None} if args.baseline else {"this": None}
    runs: dict[str, list] = {code: [] for code in codes}
    for _ in tqdm(range(args.repeats), desc="bench_learners", unit="repeat"):
        for code, root in codes.items():
            runs[code].append(
                run_worker(
                    root,
                    learners,
                    args.system,
                    args.episodes,
                    args.seconds,
                    args.horizon,
                    args.experiment if root is None else "",  # the baseline keeps its defaults
                    args.config_dir,
                    args.override,
                )
            )
    rows = summarize(runs)
    print(format_table(rows))
    neural = format_neural_table(rows)  # collection and training rates of the TorchRL learners
    if neural:
        print(f"\n{neural}")
    Path(args.out).write_text(json.dumps({"rows": rows, "runs": runs}, indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    cli.run(main)

"""Training copy-ticks/s of every learner, next to the bare env and a plain per-copy Python loop.

Usage: python scripts/bench_learners.py [--learners subg_cql dql ...] [--episodes 2] [--repeats 3]
       [--horizon 200] [--baseline /path/to/other/checkout] [--experiment NAME]
       [--out bench_learners.json]

With ``--baseline`` the same measurements run, in turns, on another checkout of mrta_rl (e.g.
today's main) and the table shows the speed-up over it.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from tqdm import tqdm

from mrta_rl.bench.learners import (
    LEARNERS,
    format_neural_table,
    format_table,
    run_worker,
    summarize,
)

if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--learners", nargs="+", default=list(LEARNERS), choices=LEARNERS)
    parser.add_argument("--system", default="system2", help="conf/system name")
    parser.add_argument("--episodes", type=int, default=2, help="training episodes per learner")
    parser.add_argument("--horizon", type=int, default=0, help="ticks per episode (0: config's)")
    parser.add_argument("--repeats", type=int, default=3, help="repeats (min and median)")
    parser.add_argument("--seconds", type=float, default=2.0, help="least wall time per yardstick")
    parser.add_argument("--baseline", type=Path, help="another checkout to measure in turns")
    parser.add_argument("--experiment", default="", help="conf/experiment for this checkout's runs")
    parser.add_argument("--out", default="bench_learners.json")
    args = parser.parse_args()
    codes = {"baseline": args.baseline, "this": None} if args.baseline else {"this": None}
    runs: dict[str, list] = {code: [] for code in codes}
    for _ in tqdm(range(args.repeats), desc="bench_learners", unit="repeat"):
        for code, root in codes.items():
            runs[code].append(
                run_worker(
                    root,
                    args.learners,
                    args.system,
                    args.episodes,
                    args.seconds,
                    args.horizon,
                    args.experiment if root is None else "",  # the baseline keeps its defaults
                )
            )
    rows = summarize(runs)
    print(format_table(rows))
    neural = format_neural_table(rows)  # collection and training rates of the TorchRL learners
    if neural:
        print(f"\n{neural}")
    Path(args.out).write_text(json.dumps({"rows": rows, "runs": runs}, indent=2))
    print(f"wrote {args.out}")

"""ES on Ray workers: copy-ticks per second for several worker counts, side by side.

Usage: ``python scripts/bench_workers.py [--learner net_es] [--system system2] [--workers 1 2]
[--repeats 3] [--episodes 5]``; run it alone on the machine.
"""

from __future__ import annotations

import argparse
import json

from mrta_rl.bench.workers import format_table, measure

if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--learner", default="net_es")
    parser.add_argument("--system", default="system2")
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument(
        "--episodes", type=int, default=5, help="ES steps per run (the first is warm-up)"
    )
    args = parser.parse_args()
    result = measure(
        args.learner, args.system, args.workers, args.repeats, [f"train.episodes={args.episodes}"]
    )
    print(format_table(result))
    print(json.dumps(result, indent=1))

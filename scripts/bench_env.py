"""Env-ticks per second of the auction env under greedy, for several batch sizes and systems.

Usage: python scripts/bench_env.py [--batch-sizes 1 64 1024 8192] [--threads 1 2] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import yaml
from tqdm import tqdm

from mrta_rl.envs.benchmark import bench_env, format_table
from mrta_rl.systems import build_system, random_system

CONF = Path(__file__).resolve().parents[1] / "conf" / "system"

if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch-sizes", type=int, nargs="+", default=[1, 64, 1024, 8192])
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2], help="thread counts")
    parser.add_argument("--seconds", type=float, default=2.0, help="least wall time per cell")
    parser.add_argument("--out", default="bench_env.json")
    args = parser.parse_args()
    systems = [
        build_system(yaml.safe_load((CONF / f"{name}.yaml").read_text()))
        for name in ("system1", "system2")
    ]
    systems.append(random_system(100, 20, 0.15, seed=0, name="random100"))
    cells = [(s, b, n) for s in systems for n in args.threads for b in args.batch_sizes if b >= n]
    results = [
        bench_env(s, b, threads=n, min_seconds=args.seconds)
        for s, b, n in tqdm(cells, desc="bench_env", unit="cell")
    ]
    print(format_table(results))
    Path(args.out).write_text(json.dumps([r.as_dict() for r in results], indent=2))
    print(f"wrote {args.out}")

"""``mrta-bench``: env-ticks per second of the auction env under greedy, plain-loop ratios.

Usage: ``mrta-bench [--batch-sizes 1 16 64 1024 8192] [--threads 1 2] [--paths step play]
[--repeats 3] [--seconds 1.0] [--systems system1 system2 random100 scaled1000] [--clock wall|cpu]
[--out FILE]`` (or ``python scripts/bench_env.py ...``; ``make bench``). A system is a shipped
one, ``random100`` (100 random robots), ``scaled1000`` (1,000 random robots with the scaled
auction: 300 slots in 100 zones) or the path of a team yaml. A cell whose action mask
(copies x robots x (slots + 1)) exceeds :data:`MAX_MASK` is left out: its memory and time grow
with it (``scaled1000`` runs 1 and 16 copies). The plain loop is the spec's reference reading,
:mod:`mrta_rl.envs.reference`.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

from tqdm import tqdm

from mrta_rl.bench.env import bench_env, bench_plain_loop, format_table
from mrta_rl.checked_files import read_yaml
from mrta_rl.commands import CommandLineParser
from mrta_rl.conf_paths import system_file
from mrta_rl.config import Range, check_arguments
from mrta_rl.envs.params import AuctionParams
from mrta_rl.errors import check_output_file
from mrta_rl.runners import cli
from mrta_rl.systems import RobotSystem, build_system, random_system

# entries of the largest action mask benchmarked: random100 at 8,192 copies holds 3.3 million
MAX_MASK = 1 << 23
# the benchmark's random teams by name: robots, task types, density, scaled auction
RANDOM_TEAMS = {"random100": (100, 20, 0.15, False), "scaled1000": (1000, 20, 0.15, True)}


@dataclass(frozen=True)
class BenchArguments:
    """The numbers of the command line (``--batch-sizes`` ...), checked before any work."""

    batch_sizes: Annotated[tuple[int, ...], Range(1)]  # env copies per cell
    threads: Annotated[tuple[int, ...], Range(1)]  # thread counts (a cell needs copies >= threads)
    repeats: Annotated[int, Range(1)]  # side-by-side repeats of every cell
    seconds: Annotated[float, Range(0, low_open=True)]  # least wall time per cell, finite


def _system(name: str) -> RobotSystem:
    """A benchmark team: one of :data:`RANDOM_TEAMS` (team seed 0), a shipped one or a yaml."""
    if name in RANDOM_TEAMS:
        m, n, density, scaled = RANDOM_TEAMS[name]
        return random_system(m, n, density, seed=0, scale_auction=scaled, name=name)
    return build_system(read_yaml(system_file(name)))


def _mask_size(system: RobotSystem, batch_size: int) -> int:
    """Entries of the action mask of ``batch_size`` copies of ``system``."""
    slots = AuctionParams.merged(system.env_overrides).slots
    return batch_size * system.n_robots * (slots + 1)


def _task() -> None:
    parser = CommandLineParser(prog="mrta-bench", description=__doc__.splitlines()[0])
    parser.add_argument("--batch-sizes", type=int, nargs="+", default=[1, 16, 64, 1024, 8192])
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2], help="thread counts")
    parser.add_argument("--paths", nargs="+", default=["step", "play"], choices=["step", "play"])
    parser.add_argument("--repeats", type=int, default=3, help="side-by-side repeats (ratios)")
    parser.add_argument("--seconds", type=float, default=1.0, help="least wall time per cell")
    parser.add_argument(
        "--systems", nargs="+", default=["system1", "system2", "random100", "scaled1000"]
    )
    parser.add_argument("--clock", default="wall", choices=["wall", "cpu"], help="cpu: steadier")
    parser.add_argument("--out", default="bench_env.json")
    args = parser.parse_args()
    check_arguments(BenchArguments, args)  # before any work, and before the systems are built
    check_output_file(args.out, "--out")
    systems = [_system(name) for name in args.systems]
    plain = [(s, None, 1, 1) for s in systems]
    cells = plain + [
        (s, path, b, n)
        for s in systems
        for path in args.paths
        for n in args.threads
        for b in args.batch_sizes
        if b >= n and _mask_size(s, b) <= MAX_MASK
    ]
    results = []
    with tqdm(total=args.repeats * len(cells), desc="bench_env", unit="cell") as bar:
        for _ in range(args.repeats):  # one repeat = every cell, side by side
            for system, path, b, n in cells:
                if path is None:
                    results.append(bench_plain_loop(system, args.seconds, args.clock))
                else:
                    results.append(
                        bench_env(system, b, n, args.seconds, path=path, clock=args.clock)
                    )
                bar.update()
    print(format_table(results))
    Path(args.out).write_text(json.dumps([r.as_dict() for r in results], indent=2))
    print(f"wrote {args.out}")


def main() -> None:
    """Run the command with the arguments of the command line."""
    cli.run(_task)

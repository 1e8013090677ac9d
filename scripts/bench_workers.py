"""ES on Ray workers: copy-ticks per second for several worker counts, and a model beyond them.

Usage: ``python scripts/bench_workers.py [--learner net_es] [--system system2] [--workers 1 2]
[--repeats 3] [--episodes 5] [--out bench_workers.json]``; run it alone on the machine.
``--from FILE`` prints the tables of a saved measurement without running anything.
"""

from __future__ import annotations

from mrta_rl.bench.workers import main

if __name__ == "__main__":
    main()

"""A Ray cluster of several nodes on this machine, and an ES run spread over its workers.

A head without CPUs and ``--workers`` nodes of one CPU each stand for the machines of a cluster:
``net_es`` trains with one Ray worker on each node (``train.workers``, ``train.ray_address``), as
it would on real machines, and the same run in one process ends with the same weights to the bit.

    python examples/local_cluster.py                  # 2 nodes, a short System-I run
    python examples/local_cluster.py --workers 3 --out runs/cluster
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

from ray.cluster_utils import Cluster

TRAIN = Path(sys.executable).with_name("mrta-train")  # the console command of the install
RUN = ["learner=net_es", "system=system1", "debug=smoke", "train.episodes=4", "learner.pairs=2",
       "train.batch_size=8"]  # fmt: skip


def train(run_dir: Path, *overrides: str) -> bytes:
    """Train with ``overrides``; the learned weights (``learner/net_es.npz``)."""
    subprocess.run([TRAIN, *RUN, *overrides, f"hydra.run.dir={run_dir}"], check=True)
    return (run_dir / "learner" / "net_es.npz").read_bytes()


def main() -> None:
    """Start the cluster, train on its workers and alone, compare the weights."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workers", type=int, default=2, help="nodes of one CPU, one worker each")
    parser.add_argument(
        "--out", type=Path, default=None, help="run dirs here (default: a temp dir)"
    )
    args = parser.parse_args()
    out = args.out or Path(tempfile.mkdtemp(prefix="local_cluster_"))
    cluster = Cluster(
        initialize_head=True, head_node_args={"num_cpus": 0, "include_dashboard": False}
    )
    for _ in range(args.workers):
        cluster.add_node(num_cpus=1)
    cluster.wait_for_nodes()
    try:
        spread = train(
            out / "workers",
            f"train.workers={args.workers}",
            f"train.ray_address={cluster.address}",  # join this cluster, as auto would on a node
        )
    finally:
        cluster.shutdown()
    alone = train(out / "alone")
    print(f"{args.workers} workers and one process: same weights: {spread == alone}")


if __name__ == "__main__":
    main()

#!/usr/bin/env bash
# Ray on Slurm: one Ray node per Slurm node, then one net_es run on all their CPUs.
#   sbatch examples/ray_on_slurm.sh
# The first node is Ray's head and runs the training process; every node's CPUs hold workers.
# One worker plays at least one ES member, so the population grows with the workers (pairs).
#SBATCH --job-name=mrta-es
#SBATCH --nodes=4
#SBATCH --ntasks-per-node=1
#SBATCH --cpus-per-task=32
#SBATCH --mem=16G
#SBATCH --time=02:00:00
set -euo pipefail

nodes=($(scontrol show hostnames "$SLURM_JOB_NODELIST"))
head_ip=$(srun --nodes=1 --ntasks=1 -w "${nodes[0]}" hostname --ip-address | awk '{print $1}')
port=6379
srun --nodes=1 --ntasks=1 -w "${nodes[0]}" \
  ray start --head --node-ip-address="$head_ip" --port=$port --num-cpus="$SLURM_CPUS_PER_TASK" --block &
sleep 30  # the head listens before the others join
for node in "${nodes[@]:1}"; do
  srun --nodes=1 --ntasks=1 -w "$node" \
    ray start --address="$head_ip:$port" --num-cpus="$SLURM_CPUS_PER_TASK" --block &
done
sleep 30

workers=$((SLURM_JOB_NUM_NODES * SLURM_CPUS_PER_TASK - 1))  # one CPU for the training process
pairs=$(((workers + 1) / 2))                               # a member per worker at least
python scripts/train.py learner=net_es system=system2 \
  learner.pairs=$pairs train.batch_size=$((2 * pairs * 24)) \
  train.workers=$workers train.ray_address="$head_ip:$port" train.progress_bar=false

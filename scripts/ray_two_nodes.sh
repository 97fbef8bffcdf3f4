#!/usr/bin/env bash
# `knotlab bench` on a two-node Ray cluster started on this machine (one CPU per node), then the
# per-node throughput. Shows that the bench scales over cluster nodes (each node runs one bench
# actor); on real machines, run `ray start --address HEAD:PORT` on each node instead.
# Usage: scripts/ray_two_nodes.sh OUT_DIR [knotlab bench flags, e.g. --policies nn --tasks 40]
# Writes only OUT_DIR (a resumable bench directory). Stops the cluster on exit.
set -euo pipefail
cd "$(dirname "$0")/.."
out=${1:?usage: scripts/ray_two_nodes.sh OUT_DIR [bench flags]}
shift
bin=.venv/bin
port=${RAY_PORT:-6390}
export RAY_USAGE_STATS_ENABLED=0 RAY_AUTH_MODE=disabled
export OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1
trap '$bin/ray stop --force >/dev/null 2>&1 || true' EXIT
$bin/ray start --head --port "$port" --num-cpus 1 --include-dashboard=false \
  --disable-usage-stats >/dev/null
$bin/ray start --address "127.0.0.1:$port" --num-cpus 1 --disable-usage-stats >/dev/null
$bin/knotlab bench --engine ray --ray-address "127.0.0.1:$port" --workers 2 --out "$out" "$@"
$bin/python bench/node_throughput.py "$out/outcomes.jsonl"

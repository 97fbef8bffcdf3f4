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
source scripts/ray_cluster.sh
trap ray_down EXIT
ray_up
$bin/knotlab bench --engine ray --ray-address "$RAY_ADDRESS_LOCAL" --workers 2 --out-dir "$out" "$@"
$bin/python bench/node_throughput.py "$out/outcomes.jsonl"

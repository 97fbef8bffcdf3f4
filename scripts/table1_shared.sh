#!/usr/bin/env bash
# The full-size Table I (five policies, 500 main + 500 hard test tasks) with
# --share-simulations, into results/table1_shared_{main,hard}/ (never the committed
# results/table1_{main,hard}/), logging every resumed segment's wall time, so that issue 15's
# target (the whole table within 4 hours on 2 cores) is measured even when no session lasts that
# long: the table's wall time is the sum of the "seconds=" of the segments in segments.log, all
# on one kind of machine (the log names the CPU and the commit of each segment).
# Usage: scripts/table1_shared.sh [WORKERS]   (default 2; stop it with Ctrl-C or kill: resumable)
set -euo pipefail
cd "$(dirname "$0")/.."
bin=.venv/bin
workers=${1:-2}
cpu=$(lscpu | sed -n 's/^Model name: *//p' | head -1)
flags=$(grep -q avx512f /proc/cpuinfo && echo avx512 || echo avx2)
for lv in main hard; do
  out="results/table1_shared_${lv}"
  mkdir -p "$out"
  start=$(date +%s)
  echo "start $(date -u +%FT%TZ) cpu='${cpu} ${flags}' workers=${workers}" \
    "commit=$(git rev-parse --short HEAD)" >> "$out/segments.log"
  stop_line() { echo "stop  $(date -u +%FT%TZ) seconds=$(( $(date +%s) - start ))" >> "$out/segments.log"; }
  $bin/knotlab bench --policies nn,greedy,la2x5,oracle,la1x10 --tasks 500 --level "$lv" \
    --model results/model_main.npz --out "$out" --workers "$workers" --share-simulations &
  bench=$!
  # `|| true`: under set -e a failing kill (the bench already gone) would end the trap early
  trap 'kill -TERM "$bench" 2>/dev/null || true; wait "$bench" || true; stop_line; exit 143' TERM INT
  wait "$bench"
  trap - TERM INT
  echo "end   $(date -u +%FT%TZ) seconds=$(( $(date +%s) - start ))" >> "$out/segments.log"
done

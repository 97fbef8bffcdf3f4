#!/usr/bin/env bash
# The full-size Table I (five policies, 500 main + 500 hard test tasks) with
# --share-simulations, into results/table1_shared_{main,hard}/ (never the committed
# results/table1_{main,hard}/), logging every resumed segment's wall time, so that the speed
# target (the whole table within 4 hours on 2 cores) is measured even when no session lasts that
# long: the table's wall time is the sum of the "seconds=" of the segments in segments.log, all
# on one kind of machine (the log names the CPU and the commit of each segment;
# `bench/table1_report.py --run table1_shared` adds them up).
# ENGINE=ray runs the same table on a two-node Ray cluster started on this machine (one CPU a
# node, scripts/ray_cluster.sh) into results/table1_ray_shared_{main,hard}/, and prints each
# level's per-node throughput when it finishes.
# Usage: [ENGINE=local|ray] [TASKS=500] [POLICIES=nn,greedy,la2x5,oracle,la1x10] [RESULTS=results]
#        scripts/table1_shared.sh [WORKERS]
#   (default 2 workers; stop it with Ctrl-C or kill -TERM: resumable, the stop is logged)
set -euo pipefail
cd "$(dirname "$0")/.."
bin=.venv/bin
workers=${1:-2}
engine=${ENGINE:-local}
tasks=${TASKS:-500}
policies=${POLICIES:-nn,greedy,la2x5,oracle,la1x10}
results=${RESULTS:-results}
case "$engine" in
  local) prefix=table1_shared; engine_flags=() ;;
  ray)
    prefix=table1_ray_shared
    source scripts/ray_cluster.sh
    trap ray_down EXIT
    ray_up
    engine_flags=(--engine ray --ray-address "$RAY_ADDRESS_LOCAL")
    ;;
  *) echo "table1_shared.sh: ENGINE must be local or ray, not '$engine'" >&2; exit 2 ;;
esac
cpu=$(lscpu | sed -n 's/^Model name: *//p' | head -1)
flags=$(grep -q avx512f /proc/cpuinfo && echo avx512 || echo avx2)
for lv in main hard; do
  out="${results}/${prefix}_${lv}"
  mkdir -p "$out"
  start=$(date +%s)
  echo "start $(date -u +%FT%TZ) cpu='${cpu} ${flags}' workers=${workers}" \
    "commit=$(git rev-parse --short HEAD) engine=${engine}" >> "$out/segments.log"
  stop_line() { echo "stop  $(date -u +%FT%TZ) seconds=$(( $(date +%s) - start ))" >> "$out/segments.log"; }
  $bin/knotlab bench --policies "$policies" --tasks "$tasks" --level "$lv" \
    --model results/model_main.npz --out-dir "$out" --force --workers "$workers" \
    --share-simulations "${engine_flags[@]}" &
  bench=$!
  # `|| true`: under set -e a failing kill (the bench already gone) would end the trap early;
  # the EXIT trap (ray_down) still runs after `exit`
  trap 'kill -TERM "$bench" 2>/dev/null || true; wait "$bench" || true; stop_line; exit 143' TERM INT
  wait "$bench"
  trap - TERM INT
  echo "end   $(date -u +%FT%TZ) seconds=$(( $(date +%s) - start ))" >> "$out/segments.log"
  if [ "$engine" = ray ]; then $bin/python bench/node_throughput.py "$out/outcomes.jsonl"; fi
done

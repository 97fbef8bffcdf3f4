# Sourced by scripts that run `knotlab bench` on a two-node Ray cluster started on this machine
# (one CPU per node, so each node runs one bench actor at a time). Defines ray_up / ray_down and
# RAY_ADDRESS_LOCAL (the head's address); the caller sets `bin` (the venv's bin folder). On real machines run
# `ray start --address HEAD:PORT` on each node instead of ray_up's second line.
port=${RAY_PORT:-6390}
RAY_ADDRESS_LOCAL="127.0.0.1:$port"
export RAY_USAGE_STATS_ENABLED=0 RAY_AUTH_MODE=disabled
export OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1

ray_up() {
  "$bin/ray" start --head --port "$port" --num-cpus 1 --include-dashboard=false \
    --disable-usage-stats >/dev/null
  "$bin/ray" start --address "$RAY_ADDRESS_LOCAL" --num-cpus 1 --disable-usage-stats >/dev/null
}

ray_down() {
  "$bin/ray" stop --force >/dev/null 2>&1 || true
}

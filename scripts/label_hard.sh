#!/usr/bin/env bash
# Oracle labels and tried candidates of the hard level's 300 training starts (resumable: each
# step skips what its output already holds). Outputs: results/labels_oracle_hard.jsonl and
# results/tries_hard.jsonl; the labelling database is runs/hard/labels.db (not committed).
# Usage: scripts/label_hard.sh [WORKERS]
set -euo pipefail
cd "$(dirname "$0")/.."
W="${1:-2}"
export OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1
K=.venv/bin/knotlab
mkdir -p runs/hard
DB=sqlite:///runs/hard/labels.db
$K label --oracle --level hard --db "$DB" --workers "$W" --no-progress
$K labels export --db "$DB" --source oracle --out runs/hard/labels_oracle_hard.jsonl --force
cp runs/hard/labels_oracle_hard.jsonl results/labels_oracle_hard.jsonl
$K labels tries --labels results/labels_oracle_hard.jsonl --out results/tries_hard.jsonl \
  --force --workers "$W" --no-progress

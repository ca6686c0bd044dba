#!/usr/bin/env bash
# Build the four D4RL-style locomotion datasets of one env at size paper or paper-fast (docs/datasets.md).
#   scripts/build_paper_locomotion.sh hopper [seed]      # or walker2d
#   SIZE=paper-fast scripts/build_paper_locomotion.sh walker2d 0   # the paper-fast size (smaller SAC)
# Resumable: run it again after a kill; SAC continues from its last checkpoint and finished
# datasets are reused. Data goes to $SPOT_DATA_DIR (SAC cache and checkpoint in $SPOT_DATA_DIR/_work).
# medium-expert comes last: it is joined from the built medium and expert files (no new rollouts).
# Progress bars refresh once a minute (TQDM_MININTERVAL) so that a log file stays small.
set -euo pipefail
env_name=${1:?usage: $0 hopper|walker2d [seed]}
seed=${2:-0}
size=${SIZE:-paper}
spot=${SPOT:-"$(dirname "$0")/../.venv/bin/spot"}
export TQDM_MININTERVAL=${TQDM_MININTERVAL:-60}
for kind in medium-replay medium expert medium-expert; do
  echo "== $(date -u +%FT%TZ) building $env_name-$kind ($size, seed $seed)"
  "$spot" data build "$env_name-$kind" --size "$size" --seed "$seed"
done
echo "== $(date -u +%FT%TZ) done"

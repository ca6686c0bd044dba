#!/usr/bin/env bash
# Table 1 cells at budget paper on one GPU, recorded as files (no MLflow needed on the GPU machine):
# Oracle, MR, PT and SPOT's seeds as ONE program (`spot run --methods ... --seeds ...`): the reward
# models and CVAEs vmapped per method (SPOT reuses PT's reward models), then IQL vmapped over all
# runs. One process on purpose: two spot processes shared one H200 badly (Oracle's 3-seed IQL ran
# ~720 updates/s beside PT's training; `spot bench iql --seeds 3` alone: ~16,000, in IQL's other
# update order; experiments/gpu-paper-budget/NOTES.md, "Paper budget on one GPU"). The run stops
# cleanly at LIMIT_S (its records end KILLED with their curves so far). Afterwards, where MLflow is:
#   spot results import RECORDS --tracking-uri URI
#   spot results export --experiment gpu_paper_hopper_fr_pf --tracking-uri URI \
#       --out experiments/gpu-paper-budget/results/gpu_paper_hopper_fr_pf.csv
# Environment: RECORDS (default ./records), SEEDS (0,1,2), METHODS (oracle,mr,pt,spot), LIMIT_S
# (seconds; default none), SPOT (the spot command; default python3 -m spot.cli), and the usual
# SPOT_DATA_DIR and SPOT_CACHE_DIR. Extra arguments are overrides for every run (eval.every=100000).
set -u
RECORDS=${RECORDS:-./records}
SEEDS=${SEEDS:-0,1,2}
METHODS=${METHODS:-oracle,mr,pt,spot}
LIMIT_S=${LIMIT_S:-0}
SPOT=${SPOT:-python3 -m spot.cli}
export XLA_PYTHON_CLIENT_PREALLOCATE=false PYTHONUNBUFFERED=1
common=(budget=paper variant=paper data.name=hopper-full-replay data.size=paper-fast
        tracking.experiment=gpu_paper_hopper_fr_pf "$@" --seeds "$SEEDS" --record "$RECORDS" --quiet)
pre=(); [ "$LIMIT_S" -gt 0 ] && pre=(timeout -s TERM -k 120 "$LIMIT_S")
mkdir -p "$RECORDS"
t0=$(date +%s)
"${pre[@]}" $SPOT run "${common[@]}" --methods "$METHODS" > "$RECORDS/run.log" 2>&1 & a=$!
while kill -0 $a 2>/dev/null; do
  sleep 30
  echo "--- $(( $(date +%s) - t0 ))s: last eval/score per record"
  for f in "$RECORDS"/*/metrics.jsonl; do
    [ -e "$f" ] || continue
    name=$(grep -o '"run_name": "[^"]*"' "$(dirname "$f")/record.json" | cut -d'"' -f4)
    echo "$name $(grep '"eval/score"' "$f" | tail -n 1 | grep -o '"value": [^,]*, "step": [0-9]*')"
  done
done
wait $a; rc=$?
echo "rc $rc after $(( $(date +%s) - t0 ))s"
tail -n 60 "$RECORDS/run.log"
exit $rc

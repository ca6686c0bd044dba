#!/usr/bin/env bash
# Table 1 cells at budget paper on one GPU, recorded as files (no MLflow needed on the GPU machine):
# two processes share the GPU: Oracle's seeds (IQL from the first second) and MR, PT and SPOT's seeds
# as one program (reward models and CVAEs vmapped per method, then IQL vmapped over all nine runs;
# SPOT reuses PT's reward models). Both stop cleanly at LIMIT_S (their records end KILLED with
# their curves so far). Afterwards, where MLflow is:
#   spot results import RECORDS --tracking-uri URI
#   spot results export --experiment gpu_paper_hopper_fr_pf --tracking-uri URI --out results/gpu_paper_hopper_fr_pf.csv
# Environment: RECORDS (default ./records), SEEDS (0,1,2), LIMIT_S (seconds per process; default
# none), SPOT (the spot command; default python3 -m spot.cli), and the usual SPOT_DATA_DIR and
# SPOT_CACHE_DIR. Extra arguments are overrides for every run (e.g. eval.every=100000).
set -u
RECORDS=${RECORDS:-./records}
SEEDS=${SEEDS:-0,1,2}
LIMIT_S=${LIMIT_S:-0}
SPOT=${SPOT:-python3 -m spot.cli}
export XLA_PYTHON_CLIENT_PREALLOCATE=false PYTHONUNBUFFERED=1
common=(budget=paper variant=paper data.name=hopper-full-replay data.size=paper-fast
        tracking.experiment=gpu_paper_hopper_fr_pf "$@" --seeds "$SEEDS" --record "$RECORDS" --quiet)
pre=(); [ "$LIMIT_S" -gt 0 ] && pre=(timeout -s TERM -k 120 "$LIMIT_S")
mkdir -p "$RECORDS"
t0=$(date +%s)
"${pre[@]}" $SPOT run "${common[@]}" --methods oracle > "$RECORDS/oracle.log" 2>&1 & a=$!
"${pre[@]}" $SPOT run "${common[@]}" --methods mr,pt,spot > "$RECORDS/learned.log" 2>&1 & b=$!
# Report progress; stop both at once if one fails in its first two minutes (a broken setup).
while kill -0 $a 2>/dev/null || kill -0 $b 2>/dev/null; do
  sleep 30
  now=$(( $(date +%s) - t0 ))
  for p in $a $b; do
    if ! kill -0 $p 2>/dev/null && [ $now -lt 150 ]; then
      wait $p; rc=$?
      if [ $rc -ne 0 ]; then
        echo "a process failed after ${now}s (rc $rc): stopping"; kill -TERM $a $b 2>/dev/null
        tail -n 30 "$RECORDS"/*.log; wait; exit 1
      fi
    fi
  done
  echo "--- ${now}s: last eval/score per record"
  for f in "$RECORDS"/*/metrics.jsonl; do
    [ -e "$f" ] || continue
    name=$(grep -o '"run_name": "[^"]*"' "$(dirname "$f")/record.json" | cut -d'"' -f4)
    echo "$name $(grep '"eval/score"' "$f" | tail -n 1 | grep -o '"value": [^,]*, "step": [0-9]*')"
  done
done
wait $a; ra=$?; wait $b; rb=$?
echo "oracle rc $ra, mr/pt/spot rc $rb, $(( $(date +%s) - t0 ))s"
tail -n 40 "$RECORDS/oracle.log" "$RECORDS/learned.log"

#!/usr/bin/env bash
# A paper-budget Table 1 row on one GPU as ONE call of at most 9 minutes (issue 40, item 4):
#   spot run --methods oracle,mr,pt,spot --seeds 0,1,2 budget=paper variant=paper
#            data.name=hopper-full-replay data.size=paper-fast [overrides] --record OUT/records
# ONE process on purpose: MR's and PT's reward models vmapped per method (SPOT reuses PT's), SPOT's
# CVAEs vmapped, then IQL vmapped over all 12 runs, the evaluations on the CPU cores beside it
# (docs/benchmarks.md, "A paper-budget Table 1 row on one H100", has the per-stage estimate; two
# spot processes shared one H200 badly: experiments/gpu-paper-budget/NOTES.md).
#
# What comes back, all under OUT (default ./gpu-out; with the device tool, its $OUT):
#   OUT/records/     the runs recorded as files; those stopped by the limit end KILLED with their
#                    curves and the times of the stages before IQL (spot results import OUT/records)
#   OUT/run.log      the process's output (last 60 lines printed at the end)
#   OUT/timings.txt  every POLL_S seconds: the elapsed seconds and, per run, its status, last IQL
#                    step, last eval/score and time/*_s so far; then the exit code and wall time
#   OUT/device.txt   nvidia-smi (when there is one) and jax's devices
# The process gets LIMIT_S seconds (default 480), then SIGTERM (its records end KILLED) and SIGKILL
# 30 s later: the script ends by LIMIT_S + ~40 s (about 520 s at the default), inside a 9-minute
# call. With BENCH=1 it first prints `spot bench programs --small` (each stage's per-step overhead
# on this device; counted in LIMIT_S).
#
# Environment: OUT, LIMIT_S, POLL_S (30), SEEDS (0,1,2), METHODS (oracle,mr,pt,spot), BUDGET (paper),
# DATA (hopper-full-replay, or an .hdf5 path), SIZE (paper-fast), EXPERIMENT (gpu_paper_hopper_fr_pf),
# PY (python3), SPOT ("$PY -m spot.cli"), BENCH (0), and the usual SPOT_DATA_DIR, SPOT_CACHE_DIR,
# SPOT_GIT_COMMIT. Extra arguments are overrides for every run (eval.every=100000 eval.final_episodes=30).
# The CPU dry path (tests/test_paper_row_script.py): BUDGET=tiny DATA=hopper-medium-replay SIZE=tiny.
#
# Afterwards, where MLflow is:
#   spot results import OUT/records --tracking-uri URI
#   spot results export --experiment gpu_paper_hopper_fr_pf --tracking-uri URI \
#       --out experiments/gpu-paper-budget/results/gpu_paper_hopper_fr_pf.csv
set -u
OUT=${OUT:-./gpu-out}
LIMIT_S=${LIMIT_S:-480}
POLL_S=${POLL_S:-30}
SEEDS=${SEEDS:-0,1,2}
METHODS=${METHODS:-oracle,mr,pt,spot}
BUDGET=${BUDGET:-paper}
DATA=${DATA:-hopper-full-replay}
SIZE=${SIZE:-paper-fast}
EXPERIMENT=${EXPERIMENT:-gpu_paper_hopper_fr_pf}
PY=${PY:-python3}
SPOT=${SPOT:-$PY -m spot.cli}
RECORDS="$OUT/records"
export XLA_PYTHON_CLIENT_PREALLOCATE=false PYTHONUNBUFFERED=1 MUJOCO_GL=${MUJOCO_GL:-disable}
mkdir -p "$RECORDS"
t0=$(date +%s)

summary() {  # one line per record: name, status, last IQL step, last eval/score, time/*_s so far
  "$PY" - "$RECORDS" <<'EOF'
import json, sys
from pathlib import Path
for rec in sorted(Path(sys.argv[1]).glob("*/record.json")):
    head = json.loads(rec.read_text())
    iql, score, times = 0, None, {}
    metrics = rec.parent / "metrics.jsonl"
    for line in (metrics.read_text().splitlines() if metrics.exists() else []):
        try:
            m = json.loads(line)
        except ValueError:  # a line being written
            continue
        if m["key"].startswith("iql/") and m.get("step") is not None:
            iql = max(iql, int(m["step"]))
        elif m["key"] == "eval/score":
            score = (m["value"], m["step"])
        elif m["key"].startswith("time/"):
            times[m["key"][5:]] = round(m["value"], 1)
    shown = f"{score[0]:.1f} at {score[1]}" if score else "-"
    print(f"  {head.get('run_name', rec.parent.name)}: {head.get('status')}, iql step {iql}, eval/score {shown}, {times}")
EOF
}

{
  command -v nvidia-smi > /dev/null && nvidia-smi
  "$PY" -c "import jax; print('jax', jax.__version__, jax.devices())"
} > "$OUT/device.txt" 2>&1
cat "$OUT/device.txt"
left=$LIMIT_S
if [ "${BENCH:-0}" = 1 ]; then
  timeout -s TERM -k 10 "$left" $SPOT bench programs --small 2>&1 | tee "$OUT/bench_programs.txt"
  left=$(( LIMIT_S - ($(date +%s) - t0) ))
  [ "$left" -lt 60 ] && left=60
fi
common=(budget="$BUDGET" variant=paper data.name="$DATA" data.size="$SIZE" tracking.experiment="$EXPERIMENT"
        "$@" --seeds "$SEEDS" --record "$RECORDS" --quiet)
timeout -s TERM -k 30 "$left" $SPOT run "${common[@]}" --methods "$METHODS" > "$OUT/run.log" 2>&1 & a=$!
while kill -0 $a 2> /dev/null; do
  for _ in $(seq "$POLL_S"); do kill -0 $a 2> /dev/null && sleep 1; done
  { echo "--- $(( $(date +%s) - t0 ))s"; summary; } >> "$OUT/timings.txt"
  tail -n "$(( $(echo "$METHODS" | tr ',' '\n' | wc -l) * $(echo "$SEEDS" | tr ',' '\n' | wc -l) + 1 ))" "$OUT/timings.txt"
done
wait $a; rc=$?
{ echo "--- end: rc $rc after $(( $(date +%s) - t0 ))s (limit $LIMIT_S s; 124: stopped by it)"; summary; } >> "$OUT/timings.txt"
tail -n 60 "$OUT/run.log"
tail -n 20 "$OUT/timings.txt"
exit $rc

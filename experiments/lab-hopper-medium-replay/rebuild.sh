#!/usr/bin/env bash
# Rebuilds this study's committed reports in place from its claims file(s) and results CSVs.
# Run from the repository root: bash experiments/lab-hopper-medium-replay/rebuild.sh
set -euo pipefail
D=experiments/lab-hopper-medium-replay
spot report "$D" --out "$D/report.md"                                       # claims.yaml: every lab row
spot report --claims "$D/claims_hopper.yaml" --out "$D/report_hopper.md"    # set P on hopper-medium-replay alone
spot tables --table 1 "$D" --out "$D/lab_table1.md"                         # from results/lab_table1.csv (claims.yaml, tables)

#!/usr/bin/env bash
# Rebuilds this study's committed reports in place from its claims file(s) and results CSVs.
# Run from the repository root: bash experiments/lab-hopper-full-replay/rebuild.sh
# Every results/*.csv is read: once the paired launch is exported to
# results/lab_hopper_fr_pf_paired.csv (paired.sh's header), its runs enter set P+ (claims.yaml):
# the paired controls CP and the like-for-like Oracle rows.
set -euo pipefail
D=experiments/lab-hopper-full-replay
spot report "$D" --out "$D/report_hopper_fr_pf.md"

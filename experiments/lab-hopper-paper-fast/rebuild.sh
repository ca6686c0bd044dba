#!/usr/bin/env bash
# Rebuilds this study's committed reports in place from its claims file(s) and results CSVs.
# Run from the repository root: bash experiments/lab-hopper-paper-fast/rebuild.sh
set -euo pipefail
D=experiments/lab-hopper-paper-fast
spot report "$D" --out "$D/report_hopper_pf.md"

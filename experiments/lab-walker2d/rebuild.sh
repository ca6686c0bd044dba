#!/usr/bin/env bash
# Rebuilds this study's committed reports in place from its claims file(s) and results CSVs.
# Run from the repository root: bash experiments/lab-walker2d/rebuild.sh
set -euo pipefail
D=experiments/lab-walker2d
spot report "$D" --out "$D/report_walker.md"

#!/usr/bin/env bash
# The loop of docs/guides/loop.md: fit, report, diagnose, add what is missing, watch the error fall.
# Run from an empty directory with posecorr on PATH (e.g. .venv/bin).
set -euxo pipefail
here=$(cd "$(dirname "$0")" && pwd)

# Experiment III with the default effect mix plus an effect outside the catalogue.
posecorr simulate --experiment 3 --seed 3 --effect-file "$here/periodic_sweep.py" -o data.csv

# 1. The usual first model: registration and mount only.
posecorr fit data.csv --effects station,mount --method none -o step1.onnx
posecorr report data.csv --model step1.onnx -o step1.html
posecorr diagnose data.csv --effects station,mount

# 2. Add what the diagnosis marked present.
posecorr fit data.csv --effects station,mount,range_scale,incidence,sweep,drift --method none -o step2.onnx
posecorr diagnose data.csv --effects station,mount,range_scale,incidence,sweep,drift

# 3. Nothing in the catalogue is missing, but the residual lives along azimuth: a user effect.
posecorr fit data.csv --effect-file "$here/periodic_sweep.py" \
    --effects station,mount,range_scale,incidence,sweep,drift,periodic_sweep --method none -o step3.onnx
posecorr report data.csv --model step3.onnx --effect-file "$here/periodic_sweep.py" -o step3.html

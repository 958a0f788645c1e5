#!/usr/bin/env bash
# The loop of docs/guides/loop.md on an error outside the catalogue: fit, diagnose, take the
# proposal, watch the error fall. Run from an empty directory with posecorr on PATH (.venv/bin).
set -euxo pipefail
here=$(cd "$(dirname "$0")" && pwd)

# A robot carries the tracker through 50 poses; the frames are unknown, and the tracking
# space is strained (examples/space_strain.py: not an effect of the catalogue).
posecorr simulate --session --robot ur5e --poses 50 --seed 1 \
    --effect-file "$here/space_strain.py" --effects space_strain -o session.csv

# 1. The usual first model: registration and mount only, leave-one-out.
posecorr fit session.csv --effects station,mount --method none --cv loo -o step1.onnx

# 2. What is missing? The diagnosis does not know space_strain; it proposes a form.
posecorr diagnose session.csv --effects station,mount --propose proposed.py

# 3. Fit the proposal, as written, and look at the page.
posecorr fit session.csv --effect-file proposed.py --effects station,mount,session_strain \
    --method none --cv loo -o step2.onnx
posecorr report session.csv --model step2.onnx --effect-file proposed.py -o step2.html

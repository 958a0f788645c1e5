#!/usr/bin/env bash
# Single-pose time of libposecorr's pc_run against a hand-written AVX2 C function of the same
# MLP (generated for the model by gen_hand.py: same weights, same activation formulas, same
# summation order, no FMA, the model's representation's encode/decode from hand_core.h),
# interleaved in rounds in one process, through the public API. The repository's copy of the
# host floor's run.sh, for every representation gen_hand.py writes (zhou, quat, eaa, R).
# Usage: bench/floor/run.sh [MODEL] [LIBDIR] [INCLUDEDIR]   (run from the repository root)
# Defaults: the shipped zhou MLP, the library pip builds, runtime_c/.
# Prints: pc_run and hand median ns per pose, their max abs output difference, and the ratio.
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
model=${1:-models/mlp-zhou-tansig-20x20x20x20-br.onnx}
lib=${2:-$(dirname "$(find . -path ./.git -prune -o -name 'libposecorr.so*' -print | head -1)")}
inc=${3:-runtime_c}
tmp=$(mktemp -d); trap 'rm -rf "$tmp"' EXIT
python3 -c 'import onnx' 2>/dev/null && py=python3 || py=.venv/bin/python
"$py" "$here/gen_hand.py" "$model" "$tmp" >/dev/null
so=$(ls "$lib"/libposecorr.so* | head -1)
mkdir -p "$tmp/lib" && cp "$so" "$tmp/lib/libposecorr.so.0" && ln -s libposecorr.so.0 "$tmp/lib/libposecorr.so"
gcc -O2 -march=native -I"$inc" -I"$here" "$here/floor.c" "$tmp/hand_any.c" \
    -L"$tmp/lib" -Wl,-rpath,"$tmp/lib" -lposecorr -lm -o "$tmp/floor"
"$tmp/floor" "$model"

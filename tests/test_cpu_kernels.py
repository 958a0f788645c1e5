"""The suite holds on any CPU: the tests that compare floats computed here with floats stored
from another machine (marked `cpu_floats`) pass again under another CPU's kernels.

Three libraries pick their kernels by CPU at run time, and each kernel rounds its own way: a
user's machine differs from the one that wrote the shipped models. numpy's OpenBLAS picks a
kernel family (OPENBLAS_CORETYPE names another), numpy its own loops' SIMD targets
(NPY_DISABLE_CPU_FEATURES turns this machine's off) and torch its ATen kernels
(ATEN_CPU_CAPABILITY=default: no SIMD). Setting all three reproduces another CPU anywhere; MKL,
torch's BLAS, is asked for SSE4.2's kernels too (MKL_ENABLE_INSTRUCTIONS: it cannot be read
back)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PROBE = """
import json, numpy, threadpoolctl
try:
    from numpy._core import _multiarray_umath as umath
except ImportError:   # numpy 1.x
    from numpy.core import _multiarray_umath as umath
try:
    import torch
    capability = torch.backends.cpu.get_cpu_capability()
except ImportError:
    capability = None
print(json.dumps({
    "openblas": next(i["architecture"] for i in threadpoolctl.threadpool_info() if i["internal_api"] == "openblas"),
    "numpy_targets": [f for f in umath.__cpu_dispatch__ if umath.__cpu_features__.get(f)],
    "torch": capability}))
"""


def _kernels(env: dict[str, str]) -> dict:
    return json.loads(subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, env=env,
                                     check=True, timeout=60).stdout)


@pytest.mark.slow
def test_float_sensitive_tests_pass_under_another_cpus_kernels():
    own = _kernels({**os.environ})
    other = "Haswell" if own["openblas"].lower() == "sandybridge" else "Sandybridge"
    env = {**os.environ, "OPENBLAS_CORETYPE": other, "ATEN_CPU_CAPABILITY": "default",
           "NPY_DISABLE_CPU_FEATURES": " ".join(own["numpy_targets"]), "MKL_ENABLE_INSTRUCTIONS": "SSE4_2"}
    theirs = _kernels(env)
    assert theirs["openblas"].lower() == other.lower(), "OPENBLAS_CORETYPE was not honoured"
    assert theirs["numpy_targets"] == [], "NPY_DISABLE_CPU_FEATURES was not honoured"
    assert theirs["torch"] in (None, "DEFAULT"), "ATEN_CPU_CAPABILITY was not honoured"
    r = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-m", "cpu_floats",
                        "tests"], cwd=ROOT, env=env, capture_output=True, text=True, timeout=900)
    tail = "\n".join(r.stdout.splitlines()[-15:])
    assert r.returncode == 0, f"under {own} -> {theirs}:\n{tail}"
    assert " passed" in tail and "deselected" in tail, tail

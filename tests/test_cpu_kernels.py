"""The suite holds on any CPU: the tests that compare floats computed here with floats stored
from another machine (marked `cpu_floats`) pass again under another BLAS kernel family.

numpy's OpenBLAS picks its kernels by CPU at run time, and each family rounds matrix products
its own way: a user's machine differs from the one that wrote the shipped models. Setting
OPENBLAS_CORETYPE to a family other than this machine's own reproduces that anywhere."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PROBE = "import numpy, threadpoolctl; print(next(i['architecture'] for i in threadpoolctl.threadpool_info() " \
        "if i['internal_api'] == 'openblas'))"


def _kernel_family(env: dict[str, str]) -> str:
    return subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, env=env,
                          check=True, timeout=60).stdout.strip()


@pytest.mark.slow
def test_float_sensitive_tests_pass_under_another_kernel_family():
    own = _kernel_family({**os.environ})
    other = "Haswell" if own.lower() == "sandybridge" else "Sandybridge"
    env = {**os.environ, "OPENBLAS_CORETYPE": other}
    assert _kernel_family(env).lower() == other.lower(), "OPENBLAS_CORETYPE was not honoured"
    r = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-m", "cpu_floats",
                        "tests"], cwd=ROOT, env=env, capture_output=True, text=True, timeout=900)
    tail = "\n".join(r.stdout.splitlines()[-15:])
    assert r.returncode == 0, f"under OPENBLAS_CORETYPE={other} (this machine: {own}):\n{tail}"
    assert " passed" in tail and "deselected" in tail, tail

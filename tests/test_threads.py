"""--threads: the default leaves busy cores alone, and the limit reaches torch and BLAS."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from posecorr import threads
from posecorr.cli import build_parser, main


@pytest.mark.parametrize("cores,load,workers,want", [(2, 0.0, 1, 2), (2, 1.0, 1, 1), (2, 0.0, 2, 1),
                                                     (2, 3.5, 1, 1), (8, 2.4, 2, 3), (8, 0.2, 3, 2)])
def test_default_threads_share_the_idle_cores(monkeypatch, cores, load, workers, want):
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(cores)), raising=False)
    monkeypatch.setattr(os, "getloadavg", lambda: (load, load, load))
    assert threads.default_threads(workers) == want


def _run(code: str) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS",
                                                               "MKL_NUM_THREADS")}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_set_threads_limits_torch_and_blas_loaded_before_and_after():
    pytest.importorskip("torch")
    before = _run("import json, torch, scipy.linalg; from posecorr.threads import set_threads, threads_in_use;"
                  "set_threads(1); print(json.dumps(threads_in_use()))")
    assert "torch" in before and any(k != "torch" for k in before)
    assert set(before.values()) == {1}
    after = _run("import json; from posecorr.threads import set_threads; set_threads(1);"
                 "import torch, scipy.linalg; from posecorr.threads import threads_in_use;"
                 "print(json.dumps(threads_in_use()))")
    assert set(after.values()) == {1} and "torch" in after


@pytest.mark.parametrize("verb", [["fit", "d.csv", "-o", "m.onnx"], ["sweep", "d.csv"], ["demo"],
                                  ["diagnose", "d.csv"], ["report", "d.csv", "--model", "m.onnx", "-o", "r.html"]])
def test_every_training_verb_takes_threads(verb):
    args = build_parser().parse_args(verb + ["--threads", "3"])
    assert args.threads == 3
    assert build_parser().parse_args(verb).threads is None  # None = the default of posecorr.threads


def test_threads_below_one_is_a_usage_error(capsys):
    assert main(["diagnose", "missing.csv", "--threads", "0"]) == 2
    assert "argument --threads: expected an integer in 1..1024, got 0" in capsys.readouterr().err

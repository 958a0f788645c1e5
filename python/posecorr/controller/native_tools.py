"""`posecorr-run`, `posecorr-bench` and `posecorr-plan` on PATH after `pip install`: the C tools are built
beside libposecorr (posecorr/_native/) and these entry points start them in place of the
Python process (exec: same pid, stdin/stdout and exit status untouched, no Python between
a tracker's pipe and the tool)."""
from __future__ import annotations

import os
import sys
from pathlib import Path

NATIVE = Path(__file__).resolve().parents[1] / "_native"


def _exec(name: str) -> int:
    tool = NATIVE / name
    if not os.access(tool, os.X_OK):
        print(f"{name}: {tool} is missing; reinstall posecorr (pip install .) to build the C tools",
              file=sys.stderr)
        return 2
    os.execv(str(tool), [name, *sys.argv[1:]])
    return 2  # not reached: execv replaces the process or raises


def run() -> int:
    return _exec("posecorr-run")


def bench() -> int:
    return _exec("posecorr-bench")


def plan() -> int:
    return _exec("posecorr-plan")

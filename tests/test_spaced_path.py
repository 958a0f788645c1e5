"""A checkout in a folder whose path holds a space ("~/My Projects/posecorr") builds the
microcontroller firmware: GNU make cannot name a target whose path holds a space, so the
firmware's Makefile names its targets by relative paths and quotes the paths it is given.

make's dry run (-n) parses both Makefiles and plans every recipe without the ARM toolchain,
in a copy of what they read (make resolves symbolic links, so a link would not do)."""
from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
READ = ("Makefile", "pyproject.toml", "setup.py", "runtime_c", "export/operators.txt",
        "python/posecorr/controller/to_c.py",
        "models/mlp-zhou-tansig-20x20x20x20-br.onnx")


@pytest.fixture(scope="module")
def checkout(tmp_path_factory) -> Path:
    if shutil.which("make") is None:
        pytest.skip("make is not on PATH")
    root = tmp_path_factory.mktemp("spaced") / "My Projects" / "posecorr"
    for name in READ:
        source, target = ROOT / name, root / name
        target.parent.mkdir(parents=True, exist_ok=True)
        if source.is_dir():
            shutil.copytree(source, target, ignore=shutil.ignore_patterns("build*", "__pycache__"))
        else:
            shutil.copy2(source, target)
    return root


@pytest.mark.parametrize("target", ["build", "small", "networks"])
def test_the_firmware_makefile_plans_every_target(checkout, target):
    r = subprocess.run(["make", "-n", "--no-print-directory", "-C", str(checkout / "runtime_c" / "embedded"),
                        f"PYTHON={sys.executable}", target], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and "Circular" not in r.stderr, r.stderr[-2000:]
    assert "arm-none-eabi-gcc" in r.stdout


def test_make_embedded_passes_the_interpreter_whole(checkout):
    """The root Makefile hands its .venv's interpreter, whose path holds the space, to the
    firmware's Makefile as one word."""
    r = subprocess.run(["make", "-n", "--no-print-directory", "-C", str(checkout), "embedded"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and "Circular" not in r.stderr, r.stderr[-2000:]
    assert f'"{checkout}/.venv/bin/python"' in r.stdout

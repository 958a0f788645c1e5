"""The figures a test measures reach the end of `make test`'s output, from whichever of the
parallel processes ran it (pytest-xdist shows nothing a worker prints)."""
from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent

MEASURING = '''
import pytest

@pytest.mark.parametrize("k", range(4))
def test_measures(k, summary):
    summary(f"figure {k}: {k * k}\\nsecond line of {k}")

def test_fails_after_measuring(summary):
    summary("measured before failing")
    assert False
'''


def test_figures_of_every_process_end_the_run(tmp_path):
    shutil.copy(HERE / "conftest.py", tmp_path / "conftest.py")
    (tmp_path / "test_measuring.py").write_text(MEASURING)
    (tmp_path / "test_other.py").write_text("def test_nothing_to_say():\n    pass\n")
    (tmp_path / "pytest.ini").write_text("[pytest]\n")   # not the checkout's settings
    r = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-n", "2", "--dist", "load",
                        "-c", str(tmp_path / "pytest.ini"), "--rootdir", str(tmp_path), str(tmp_path)],
                       capture_output=True, text=True, timeout=300, cwd=tmp_path)
    out = r.stdout
    assert r.returncode == 1 and "1 failed, 5 passed" in out, out[-3000:]
    section = out[out.index("what the tests measured"):]
    for k in range(4):
        assert f"test_measuring.py::test_measures[{k}]:\n  figure {k}: {k * k}\n  second line of {k}\n" in section
    assert "test_measuring.py::test_fails_after_measuring:\n  measured before failing\n" in section
    assert "test_nothing_to_say" not in section

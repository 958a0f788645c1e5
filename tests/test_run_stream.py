"""`posecorr-run` on a controller pipe (issue 14): a bad line is answered (an error line on
stderr, a NaN line on stdout so that output line k still answers input line k) and the
stream goes on; --strict stops at the first; lines of any length; a trailing partial
binary record is reported."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "runtime_c" / "tests"))

import graphs  # noqa: E402
from posecorr.controller.runtime import Corrector  # noqa: E402

MODEL = ROOT / "models" / "pmc-zhou.onnx"
GOOD = np.array([[0.02, -0.61, 0.48, 1.0, 0.0, 0.0, 0.0],
                 [-0.05, -0.55, 0.52, 0.9238795325, 0.0, 0.3826834324, 0.0]])


@pytest.fixture(scope="module")
def run_tool() -> Path:
    return graphs.build_test_runtime() / "posecorr-run"


def _run(tool: Path, data: str | bytes, *flags: str) -> subprocess.CompletedProcess:
    return subprocess.run([str(tool), str(MODEL), *flags], input=data, capture_output=True, timeout=60,
                          text=isinstance(data, str))


def _csv(pose: np.ndarray) -> str:
    return ",".join(f"{v:.10g}" for v in pose)


def test_bad_lines_are_answered_and_the_stream_goes_on(run_tool) -> None:
    lines = ["x,y,z,qw,qx,qy,qz", _csv(GOOD[0]), "0.1,oops,0.3,1,0,0,0", "0.1,-0.6,0.5,0,0,0,0",
             "nan,0,0,1,0,0,0", "0.1,-0.6", _csv(GOOD[1])]
    r = _run(run_tool, "\n".join(lines) + "\n")
    assert r.returncode == 1
    out = r.stdout.splitlines()
    assert out[0] == lines[0] and len(out) == len(lines)  # one answer per line
    got = np.array([[float(v) for v in line.split(",")] for line in out[1:]])
    want = Corrector(MODEL).correct(GOOD)
    np.testing.assert_allclose(got[[0, -1]], want, atol=1e-7)
    assert np.isnan(got[1:-1]).all()
    errors = r.stderr.splitlines()
    assert [e.split(":")[1].strip() for e in errors] == ["line 3", "line 4", "line 5", "line 6"]
    assert "unit quaternion" in errors[1] and "non-finite" in errors[2]


def test_strict_stops_at_the_first_bad_line(run_tool) -> None:
    r = _run(run_tool, f"{_csv(GOOD[0])}\n0.1,oops,0.3,1,0,0,0\n{_csv(GOOD[1])}\n", "--strict")
    assert r.returncode == 1 and "line 2" in r.stderr
    assert len(r.stdout.splitlines()) == 1


def test_a_line_of_any_length(run_tool) -> None:
    padded = " " * 1_000_000 + _csv(GOOD[0]).replace(",", " ," + " " * 10_000) + " " * 50_000
    r = _run(run_tool, padded + "\n" + _csv(GOOD[1]))  # the last line has no newline
    assert r.returncode == 0, r.stderr
    got = np.array([[float(v) for v in line.split(",")] for line in r.stdout.splitlines()])
    np.testing.assert_allclose(got, Corrector(MODEL).correct(GOOD), atol=1e-7)


def test_binary_partial_record_and_bad_record_are_reported(run_tool) -> None:
    records = np.concatenate([GOOD[:1], [[np.nan, 0, 0, 1, 0, 0, 0]], GOOD[1:]]).astype("<f4")
    r = _run(run_tool, records.tobytes() + b"\x00" * 10, "--binary")
    assert r.returncode == 1
    got = np.frombuffer(r.stdout, dtype="<f4").reshape(-1, 7)
    assert got.shape == (3, 7) and np.isnan(got[1]).all()
    np.testing.assert_allclose(got[[0, 2]], Corrector(MODEL).correct(GOOD), atol=1e-7)
    errors = r.stderr.decode().splitlines()
    assert "record 2" in errors[0] and "record 4: partial record of 10 bytes" in errors[1]
    r = _run(run_tool, records[:1].tobytes(), "--binary")
    assert r.returncode == 0 and len(r.stdout) == 28 and r.stderr == b""


def test_an_endless_line_costs_no_memory_and_a_nul_is_not_ignored(run_tool) -> None:
    """10 MB of NUL bytes (what /dev/zero gives) is one bad line answered with NaN; a NUL
    inside a pose line makes it a bad line, not a pose cut at the NUL; `pose,abc` on line 1
    is a bad line, not a header echoed back."""
    r = _run(run_tool, b"\x00" * 10_000_000 + b"\n" + _csv(GOOD[0]).encode() + b"\x00junk\npose,abc\n")
    out = r.stdout.decode().splitlines()
    assert r.returncode == 1 and len(out) == 3
    assert all(np.isnan([float(v) for v in line.split(",")]).all() for line in out)
    assert "line 1:" in r.stderr.decode() and "NUL" in r.stderr.decode()


def test_a_hexadecimal_number_is_a_bad_line_as_in_a_table(run_tool) -> None:
    """The table reader refuses 0x1p-5; so does posecorr-run, in a pose and in its time."""
    good = _csv(GOOD[0])
    r = _run(run_tool, f"0x1p-5{good[good.index(','):]}\n{good}, -0X1p-5\n{good}\n")
    assert r.returncode == 1
    out = r.stdout.splitlines()
    assert len(out) == 3 and all(v == "nan" for v in out[0].split(",") + out[1].split(","))
    errors = r.stderr.splitlines()
    assert [e.split(":")[1].strip() for e in errors] == ["line 1", "line 2"]
    assert all("plain decimal notation" in e and "hexadecimal" in e for e in errors)


def test_a_number_longer_than_4096_bytes_reads(run_tool) -> None:
    """Any length, not only blanks: 0.0...01 with 10,000 zeros is x = 1e-10001 = 0 in float32."""
    pose = GOOD[0].copy()
    pose[0] = 0.0
    r = _run(run_tool, "0." + "0" * 10_000 + "1" + _csv(pose)[1:] + "\n")
    assert r.returncode == 0, r.stderr
    got = np.array([float(v) for v in r.stdout.split(",")])
    np.testing.assert_allclose(got, Corrector(MODEL).correct(pose), atol=1e-7)


@pytest.mark.parametrize("kind", ["FIFO", "folder"])
def test_a_fifo_or_a_folder_as_the_model_is_refused_at_once(run_tool, tmp_path, kind) -> None:
    """A FIFO blocked forever, a folder read as 'out of memory': the command line's words."""
    import os

    model = tmp_path / "m.onnx"
    os.mkfifo(model) if kind == "FIFO" else model.mkdir()
    r = subprocess.run([str(run_tool), str(model)], input="", capture_output=True, text=True, timeout=60)
    word = {"FIFO": "a FIFO", "folder": "a folder"}[kind]
    assert r.returncode == 1 and r.stderr == f"posecorr-run: {model}: is {word}, expected a file\n"

"""bench/floor/gen_hand.py, the hand-written floor of issue 33: for an MLP of each
representation with its paper activation (quat tansig, eaa radbas, R logsig; zhou tansig),
the function it writes, built with the host's C compiler for AVX2, corrects poses as pc_run
does (libposecorr through the shim, one pose a call); a wrong activation shows; no fused
multiply-add where the target has FMA; what it cannot write is refused in one line."""
from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "runtime_c" / "tests"))
import graphs  # noqa: E402
from posecorr.controller.runtime import Corrector  # noqa: E402

FLOOR = ROOT / "bench" / "floor"
CC = shutil.which("cc") or shutil.which("gcc")


def _avx2_host() -> bool:
    try:
        return " avx2 " in Path("/proc/cpuinfo").read_text().replace("\n", " ")
    except OSError:
        return False


pytestmark = pytest.mark.skipif(CC is None or not _avx2_host(), reason="no C compiler or no AVX2 CPU")

# Reads float32 poses of 7 on stdin, writes the hand-written function's outputs.
DRIVER = r"""
#include <stdio.h>
void hand_avx_correct(const float *in, float *out);
int main(void)
{
    float in[7], out[7];
    while (fread(in, sizeof in, 1, stdin) == 1) {
        hand_avx_correct(in, out);
        fwrite(out, sizeof out, 1, stdout);
    }
    return 0;
}
"""


def generate(model: Path, tmp: Path) -> Path:
    subprocess.run([sys.executable, str(FLOOR / "gen_hand.py"), str(model), str(tmp)], check=True,
                   capture_output=True, text=True)
    return tmp / "hand_any.c"


def hand_outputs(source: Path, x: np.ndarray) -> np.ndarray:
    driver = source.with_name("driver.c")
    driver.write_text(DRIVER)
    exe = source.with_name("hand")
    # -mfma as well: the generated code must keep the compiler from contracting
    subprocess.run([CC, "-O2", "-mavx2", "-mfma", f"-I{ROOT / 'runtime_c'}", f"-I{FLOOR}", str(source),
                    str(driver), "-lm", "-o", str(exe)], check=True, capture_output=True, text=True)
    r = subprocess.run([str(exe)], input=x.astype(np.float32).tobytes(), capture_output=True, check=True)
    return np.frombuffer(r.stdout, dtype=np.float32).reshape(len(x), 7)


def pc_run_outputs(model: Path, x: np.ndarray) -> np.ndarray:
    c = Corrector(model, backend="c", max_batch=1)
    return np.vstack([c.correct(x[i]) for i in range(len(x))]).astype(np.float32)


@pytest.mark.parametrize("name", ["mlp-quat-tansig-20x20-br", "mlp-eaa-radbas-20x20-br",
                                  "mlp-R-logsig-20x20-br", "mlp-zhou-tansig-20x20x20x20-br"])
def test_hand_function_corrects_as_pc_run(name, tmp_path):
    model = ROOT / "models" / f"{name}.onnx"
    x = graphs.poses_in_box(model, 1000, seed=11)
    got, want = hand_outputs(generate(model, tmp_path), x), pc_run_outputs(model, x)
    assert np.abs(got - want).max() <= 1e-6
    # the networks move the poses: the comparison is not of inputs handed through
    assert np.abs(want[:, :3] - x[:, :3]).max() > 1e-4


def test_a_wrong_activation_shows(tmp_path):
    model = ROOT / "models" / "mlp-eaa-radbas-20x20-br.onnx"
    source = generate(model, tmp_path)
    assert "act_radbas(" in source.read_text()
    source.write_text(source.read_text().replace("act_radbas(", "act_sigmoid("))
    x = graphs.poses_in_box(model, 200, seed=12)
    assert np.abs(hand_outputs(source, x) - pc_run_outputs(model, x)).max() > 1e-3


def test_no_fused_multiply_add_on_an_fma_target(tmp_path):
    source = generate(ROOT / "models" / "mlp-R-logsig-20x20-br.onnx", tmp_path)
    asm = subprocess.run([CC, "-O2", "-mavx2", "-mfma", f"-I{ROOT / 'runtime_c'}", f"-I{FLOOR}", "-S", "-o", "-",
                          str(source)], capture_output=True, text=True, check=True).stdout
    assert "_mm256" not in asm and "vmulps" in asm
    assert "vfmadd" not in asm and "vfmsub" not in asm and "vfnmadd" not in asm


@pytest.mark.parametrize("name, message", [
    ("mlp-pos-tansig-15x15x15x15-lm", "representation 'pos' has no hand encode/decode"),
    ("pmc-quat", "method 'pmc': an MLP (method 'mlp', Gemm layers) is expected"),
])
def test_what_it_cannot_write_is_refused_in_one_line(name, message, tmp_path):
    r = subprocess.run([sys.executable, str(FLOOR / "gen_hand.py"), str(ROOT / "models" / f"{name}.onnx"),
                        str(tmp_path)], capture_output=True, text=True)
    assert r.returncode != 0 and message in r.stderr and len(r.stderr.strip().splitlines()) == 1

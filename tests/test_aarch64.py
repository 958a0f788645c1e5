"""libposecorr on a 64-bit ARM controller (a Jetson, a Raspberry Pi): the runtime cross-built
with Debian's aarch64-linux-gnu-gcc and run under QEMU's user-mode emulator.

The C unit tests pass there, and `posecorr-run` corrects the same poses as on this machine:
within float32 rounding of onnxruntime for every shipped model, and bit for bit with the x86-64
build except where the two C libraries' trigonometric functions round differently (the eaa
encoding's atanf, sinf and cosf). Needs gcc-aarch64-linux-gnu and qemu-user (`.ci/run` installs them;
with POSECORR_REQUIRE_EMBEDDED=1 their absence is a failure, as for the microcontroller).
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "runtime_c" / "tests"))
from toolchains import require  # noqa: E402  (tests/, beside this file, as pytest imports it)

CC, QEMU, SYSROOT = "aarch64-linux-gnu-gcc", "qemu-aarch64", Path("/usr/aarch64-linux-gnu")
require("aarch64 cross toolchain", (CC, QEMU), "gcc-aarch64-linux-gnu qemu-user")

ort = pytest.importorskip("onnxruntime")
MODELS = sorted((ROOT / "models").glob("*.onnx"))


@pytest.fixture(scope="module")
def builds() -> dict[str, Path]:
    import graphs

    return {"x86-64": graphs.build_test_runtime(),
            "aarch64": graphs.build_runtime(ROOT / "build" / "aarch64-test", "-DPC_BUILD_TESTS=ON",
                                            "-DCMAKE_SYSTEM_NAME=Linux",
                                            "-DCMAKE_SYSTEM_PROCESSOR=aarch64",
                                            f"-DCMAKE_C_COMPILER={CC}")}


def on_arm(build: Path, program: str, *args: str, data: bytes | None = None):
    return subprocess.run([QEMU, str(build / program), *args], input=data, capture_output=True,
                          env={**os.environ, "QEMU_LD_PREFIX": str(SYSROOT)}, timeout=300)


def test_the_build_is_for_arm(builds):
    header = (builds["aarch64"] / "pc_unit_tests").read_bytes()[:20]
    assert header[:4] == b"\x7fELF" and int.from_bytes(header[18:20], "little") == 183  # EM_AARCH64


def test_unit_tests_pass_on_arm(builds):
    r = on_arm(builds["aarch64"], "pc_unit_tests", *map(str, MODELS))
    tail = r.stdout.decode().strip().splitlines()[-1]
    assert r.returncode == 0 and tail.endswith(" 0 failed"), r.stdout.decode() + r.stderr.decode()


def poses_in_bounds(session, n: int = 2000) -> np.ndarray:
    """n poses in the model's fitted box (its metadata input_bounds), turned up to ~0.2 rad."""
    from scipy.spatial.transform import Rotation

    lo, hi = np.array(json.loads(session.get_modelmeta().custom_metadata_map["input_bounds"]))
    rng = np.random.default_rng(0)
    q = Rotation.from_rotvec(rng.normal(scale=0.2, size=(n, 3))).as_quat(canonical=True)
    return np.concatenate([rng.uniform(lo, hi, (n, 3)), q[:, [3, 0, 1, 2]]], 1).astype(np.float32)


@pytest.mark.parametrize("model", MODELS, ids=[m.stem for m in MODELS])
def test_arm_corrects_as_x86_and_onnxruntime(model, builds):
    session = ort.InferenceSession(str(model))
    x = poses_in_bounds(session)
    arm = on_arm(builds["aarch64"], "posecorr-run", str(model), "--binary", data=x.tobytes())
    here = subprocess.run([str(builds["x86-64"] / "posecorr-run"), str(model), "--binary"],
                          input=x.tobytes(), capture_output=True, timeout=300)
    assert arm.returncode == 0 and here.returncode == 0, arm.stderr[-500:] + here.stderr[-500:]
    arm_out, here_out = (np.frombuffer(r.stdout, np.float32).reshape(-1, 7) for r in (arm, here))
    want = session.run(None, {session.get_inputs()[0].name: x})[0]
    np.testing.assert_allclose(arm_out, want, rtol=0, atol=2e-6)
    bits_equal = np.all(arm_out.view(np.uint32) == here_out.view(np.uint32), axis=1).mean()
    print(f"{model.stem}: {bits_equal:.2%} of {len(x)} poses bit-equal to x86-64, max |arm - x86| "
          f"{np.abs(arm_out - here_out).max():.2g}, max |arm - onnxruntime| {np.abs(arm_out - want).max():.2g}")
    if "eaa" in model.stem:   # atanf, sinf, cosf of glibc's two builds round a few ties apart
        assert bits_equal >= 0.99 and np.abs(arm_out - here_out).max() <= 1e-6
    else:
        assert bits_equal == 1.0, f"{1 - bits_equal:.2%} of poses differ in their bits"

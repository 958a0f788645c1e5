"""libposecorr on other processors: the runtime cross-built with Debian's GCC cross compilers
and run under QEMU's user-mode emulator, on three hosts that differ from this one where a C
runtime can go wrong:

- aarch64: a 64-bit ARM controller (a Jetson, a Raspberry Pi);
- s390x: big-endian (the ONNX file's raw weights and posecorr-run's binary records are
  little-endian whatever the host), and C evaluates float arithmetic in double there
  (FLT_EVAL_METHOD 1);
- i686: 32-bit pointers and sizes, and the x87 unit, which evaluates float arithmetic in
  long double (FLT_EVAL_METHOD 2).

On each the C unit tests pass, and `posecorr-run` corrects 2,000 poses per shipped model within
float32 rounding of onnxruntime and of this machine's build (bit for bit on aarch64 but for
the eaa encoding's trigonometry). Needs each target's gcc-TARGET-linux-gnu and qemu-user
(`.ci/run` installs them; with POSECORR_REQUIRE_EMBEDDED=1 their absence is a failure, as for
the microcontroller).
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "runtime_c" / "tests"))
from toolchains import require  # noqa: E402  (tests/, beside this file, as pytest imports it)

ort = pytest.importorskip("onnxruntime")
MODELS = sorted((ROOT / "models").glob("*.onnx"))


@dataclass(frozen=True)
class Target:
    processor: str       # CMAKE_SYSTEM_PROCESSOR and Debian's triplet's first part
    emulator: str
    elf_machine: int     # e_machine of its executables
    # IEEE single-precision arithmetic as on x86-64, so the same bits: only glibc's atanf,
    # sinf and cosf (the eaa encoding) round a few ties apart. Where C evaluates float
    # arithmetic wider (FLT_EVAL_METHOD 1 or 2), most poses differ in their last bits.
    same_arithmetic: bool

    @property
    def compiler(self) -> str:
        return f"{self.processor}-linux-gnu-gcc"

    @property
    def sysroot(self) -> Path:
        return Path(f"/usr/{self.processor}-linux-gnu")


TARGETS = {t.processor: t for t in (
    Target("aarch64", "qemu-aarch64", 183, same_arithmetic=True),
    Target("s390x", "qemu-s390x", 22, same_arithmetic=False),
    Target("i686", "qemu-i386", 3, same_arithmetic=False),
)}


@pytest.fixture(scope="module", params=list(TARGETS))
def target(request) -> tuple[Target, Path]:
    import graphs

    t = TARGETS[request.param]
    require(f"{t.processor} cross toolchain", (t.compiler, t.emulator),
            f"gcc-{t.processor}-linux-gnu qemu-user")
    build = graphs.build_runtime(ROOT / "build" / f"{t.processor}-test", "-DPC_BUILD_TESTS=ON",
                                 "-DCMAKE_SYSTEM_NAME=Linux", f"-DCMAKE_SYSTEM_PROCESSOR={t.processor}",
                                 f"-DCMAKE_C_COMPILER={t.compiler}")
    return t, build


@pytest.fixture(scope="module")
def here() -> Path:
    import graphs

    return graphs.build_test_runtime()


def emulated(target: tuple[Target, Path], program: str, *args: str, data: bytes | None = None):
    t, build = target
    return subprocess.run([t.emulator, str(build / program), *args], input=data, capture_output=True,
                          env={**os.environ, "QEMU_LD_PREFIX": str(t.sysroot)}, timeout=300)


def test_the_build_is_for_the_target(target):
    t, build = target
    header = (build / "pc_unit_tests").read_bytes()[:20]
    order = "little" if header[5] == 1 else "big"  # EI_DATA
    assert header[:4] == b"\x7fELF" and int.from_bytes(header[18:20], order) == t.elf_machine
    assert (order == "big") == (t.processor == "s390x")


def test_unit_tests_pass(target):
    r = emulated(target, "pc_unit_tests", *map(str, MODELS))
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
def test_corrects_as_x86_and_onnxruntime(model, target, here):
    """posecorr-run --binary: little-endian float32 records in and out on every host."""
    t, _ = target
    session = ort.InferenceSession(str(model))
    x = poses_in_bounds(session)
    there = emulated(target, "posecorr-run", str(model), "--binary", data=x.astype("<f4").tobytes())
    mine = subprocess.run([str(here / "posecorr-run"), str(model), "--binary"], input=x.tobytes(),
                          capture_output=True, timeout=300)
    assert there.returncode == 0 and mine.returncode == 0, there.stderr[-500:] + mine.stderr[-500:]
    there_out = np.frombuffer(there.stdout, "<f4").reshape(-1, 7)
    mine_out = np.frombuffer(mine.stdout, np.float32).reshape(-1, 7)
    want = session.run(None, {session.get_inputs()[0].name: x})[0]
    np.testing.assert_allclose(there_out, want, rtol=0, atol=2e-6)
    bits_equal = np.all(there_out.view(np.uint32) == mine_out.view(np.uint32), axis=1).mean()
    print(f"{t.processor} {model.stem}: {bits_equal:.2%} of {len(x)} poses bit-equal to x86-64, max |{t.processor} - "
          f"x86| {np.abs(there_out - mine_out).max():.2g}, max |{t.processor} - onnxruntime| "
          f"{np.abs(there_out - want).max():.2g}")
    assert np.abs(there_out - mine_out).max() <= 1e-6
    if t.same_arithmetic and "eaa" in model.stem:
        assert bits_equal >= 0.99
    elif t.same_arithmetic:
        assert bits_equal == 1.0, f"{1 - bits_equal:.2%} of poses differ in their bits"

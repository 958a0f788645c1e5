"""libposecorr on other processors: the runtime cross-built with Debian's GCC cross compilers
and run under QEMU's user-mode emulator, on hosts that differ from this one where a C runtime
can go wrong:

- aarch64: a 64-bit ARM controller (a Jetson, a Raspberry Pi);
- s390x: big-endian (the ONNX file's raw weights and posecorr-run's binary records are
  little-endian whatever the host), and ISO C evaluates float arithmetic in double there
  (FLT_EVAL_METHOD 1), which the build turns off (-fexcess-precision=fast);
- i686: 32-bit pointers and sizes, with the x87 unit, which evaluates float arithmetic in long
  double (FLT_EVAL_METHOD 2) and has no float arithmetic to turn to, and built for SSE2.

On each the C unit tests pass and `posecorr-run` corrects 2,000 poses per shipped model within
float32 rounding of onnxruntime and of this machine's build: bit for bit where float
arithmetic is evaluated as float (every target here but x87), but for glibc's atanf, sinf and
cosf in the eaa encoding. The one-pose function `posecorr compile` writes for each model,
built with the same flags, gives `posecorr-run`'s bits there (on x87, its rounding).
Clang (macOS's compiler, and ARM's) and tcc (no GNU C extensions) build it here and give
GCC's bits; so does GCC over musl instead of glibc, but for the eaa encoding's trigonometry.
On x86-64 CPUs without AVX2, emulated, the runtime takes its portable kernels: the same bits.
Needs gcc-{aarch64,s390x,i686}-linux-gnu, qemu-user, clang, tcc and musl-tools (`.ci/run`
installs them; with POSECORR_REQUIRE_EMBEDDED=1 their absence is a failure, as for the
microcontroller).
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
    name: str
    processor: str       # CMAKE_SYSTEM_PROCESSOR and Debian's triplet's first part
    emulator: str
    elf_machine: int     # e_machine of its executables
    # What a user adds to build for float arithmetic evaluated as float (CMAKE_C_FLAGS and
    # the compiled function's flags); libposecorr's build adds s390x's itself.
    flags: tuple[str, ...] = ()
    # IEEE single-precision arithmetic as on x86-64, so the same bits. Where C evaluates
    # float arithmetic wider (x87) most poses differ in their last bits.
    same_bits: bool = True

    @property
    def compiler(self) -> str:
        return f"{self.processor}-linux-gnu-gcc"

    @property
    def sysroot(self) -> Path:
        return Path(f"/usr/{self.processor}-linux-gnu")


TARGETS = {t.name: t for t in (
    Target("aarch64", "aarch64", "qemu-aarch64", 183),
    Target("s390x", "s390x", "qemu-s390x", 22, flags=("-fexcess-precision=fast",)),
    Target("i686-x87", "i686", "qemu-i386", 3, same_bits=False),
    Target("i686-sse2", "i686", "qemu-i386", 3, flags=("-msse2", "-mfpmath=sse")),
)}


@pytest.fixture(scope="module", params=list(TARGETS))
def target(request) -> tuple[Target, Path]:
    import graphs

    t = TARGETS[request.param]
    require(f"{t.processor} cross toolchain", (t.compiler, t.emulator),
            f"gcc-{t.processor}-linux-gnu qemu-user")
    flags = [] if t.processor == "s390x" else [f"-DCMAKE_C_FLAGS={' '.join(t.flags)}"] if t.flags else []
    build = graphs.build_runtime(ROOT / "build" / f"{t.name}-test", "-DPC_BUILD_TESTS=ON",
                                 "-DCMAKE_SYSTEM_NAME=Linux", f"-DCMAKE_SYSTEM_PROCESSOR={t.processor}",
                                 f"-DCMAKE_C_COMPILER={t.compiler}", *flags)
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
    # s390x's build evaluates float as float by itself; x87 cannot
    flags = (build / "CMakeFiles" / "posecorr_obj.dir" / "flags.make").read_text()
    assert ("-fexcess-precision=fast" in flags) == (t.processor == "s390x")


def test_unit_tests_pass(target):
    r = emulated(target, "pc_unit_tests", *map(str, MODELS))
    tail = r.stdout.decode().strip().splitlines()[-1]
    assert r.returncode == 0 and tail.endswith(" 0 failed"), r.stdout.decode() + r.stderr.decode()


# The compiled function between posecorr-run's records: little-endian float32 in and out,
# seven NaN where the function refuses the pose.
DRIVER = r"""
#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <string.h>
int m_run(const float in[7], float out[7]);
int main(void)
{
    unsigned char rec[28];
    float in[7], out[7];
    int i;
    while (fread(rec, 1, sizeof rec, stdin) == sizeof rec) {
        for (i = 0; i < 7; i++) {
            const unsigned char *b = rec + 4 * i;
            const uint32_t u = (uint32_t)b[0] | (uint32_t)b[1] << 8 | (uint32_t)b[2] << 16 |
                               (uint32_t)b[3] << 24;
            memcpy(&in[i], &u, 4);
        }
        if (m_run(in, out) != 0)
            for (i = 0; i < 7; i++)
                out[i] = NAN;
        for (i = 0; i < 7; i++) {
            uint32_t u;
            memcpy(&u, &out[i], 4);
            rec[4 * i] = (unsigned char)u;
            rec[4 * i + 1] = (unsigned char)(u >> 8);
            rec[4 * i + 2] = (unsigned char)(u >> 16);
            rec[4 * i + 3] = (unsigned char)(u >> 24);
        }
        fwrite(rec, 1, sizeof rec, stdout);
    }
    return 0;
}
"""


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
    print(f"{t.name} {model.stem}: {bits_equal:.2%} of {len(x)} poses bit-equal to x86-64, max |{t.name} - "
          f"x86| {np.abs(there_out - mine_out).max():.2g}, max |{t.name} - onnxruntime| "
          f"{np.abs(there_out - want).max():.2g}")
    assert np.abs(there_out - mine_out).max() <= 1e-6
    if t.same_bits and "eaa" in model.stem:
        assert bits_equal >= 0.99
    elif t.same_bits:
        assert bits_equal == 1.0, f"{1 - bits_equal:.2%} of poses differ in their bits"


@pytest.mark.parametrize("model", MODELS, ids=[m.stem for m in MODELS])
def test_compiled_function_gives_pc_run_bits(model, target, tmp_path):
    t, _ = target
    source, driver, exe = tmp_path / "m.c", tmp_path / "driver.c", tmp_path / "m"
    r = subprocess.run([sys.executable, "-m", "posecorr.cli", "compile", str(model), "-o", str(source),
                        "--name", "m"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    driver.write_text(DRIVER)
    r = subprocess.run([t.compiler, "-std=c99", "-O2", "-Wall", "-Wextra", "-Werror", "-pedantic", *t.flags,
                        str(source), str(driver), "-lm", "-o", str(exe)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-3000:]
    x = poses_in_bounds(ort.InferenceSession(str(model)), 1000).astype("<f4").tobytes()
    compiled = subprocess.run([t.emulator, str(exe)], input=x, capture_output=True, timeout=300,
                              env={**os.environ, "QEMU_LD_PREFIX": str(t.sysroot)})
    run = emulated(target, "posecorr-run", str(model), "--binary", data=x)
    assert compiled.returncode == 0 and run.returncode == 0, compiled.stderr[-500:] + run.stderr[-500:]
    got, want = (np.frombuffer(r.stdout, "<f4").reshape(-1, 7) for r in (compiled, run))
    if t.same_bits:
        same = np.all(got.view(np.uint32) == want.view(np.uint32), axis=1)
        assert same.all(), f"{t.name}: {np.sum(~same)} of {len(same)} poses differ from pc_run's bits"
    else:  # each rounds its wide sums where its own code stores them
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-6)


# Other compilers on this machine: clang (macOS's, and ARM's); tcc, which defines no __GNUC__,
# so it builds the paths a compiler without GNU C's extensions takes (MSVC's): no vector
# types, no AVX2 copy, no attributes; and GCC over musl, the C library of Alpine and many
# embedded Linux systems, whose atanf, sinf and cosf round a few eaa poses otherwise.
OTHER_COMPILERS = {"clang": "clang", "tcc": "tcc", "musl": "musl-gcc"}


@pytest.mark.parametrize("name", list(OTHER_COMPILERS))
def test_other_compiler_gives_gcc_bits(name, here):
    import graphs

    compiler = OTHER_COMPILERS[name]
    require(name, (compiler,), "musl-tools" if name == "musl" else compiler)
    build = graphs.build_runtime(ROOT / "build" / f"{name}-test", "-DPC_BUILD_TESTS=ON",
                                 f"-DCMAKE_C_COMPILER={compiler}")
    r = subprocess.run([str(build / "pc_unit_tests"), *map(str, MODELS)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0 and r.stdout.strip().endswith(" 0 failed"), r.stdout[-2000:] + r.stderr[-2000:]
    for model in MODELS:
        x = poses_in_bounds(ort.InferenceSession(str(model)), 1000).tobytes()
        other, gcc = (subprocess.run([str(b / "posecorr-run"), str(model), "--binary"], input=x, capture_output=True,
                                     timeout=300) for b in (build, here))
        assert other.returncode == 0 and gcc.returncode == 0, other.stderr[-500:] + gcc.stderr[-500:]
        mine, theirs = (np.frombuffer(out.stdout, np.float32).reshape(-1, 7) for out in (other, gcc))
        bits_equal = np.all(mine.view(np.uint32) == theirs.view(np.uint32), axis=1).mean()
        if name == "musl" and "eaa" in model.stem:
            assert bits_equal >= 0.9 and np.abs(mine - theirs).max() <= 1e-6, (bits_equal, np.abs(mine - theirs).max())
        else:
            assert bits_equal == 1.0, f"{model.stem}: {1 - bits_equal:.2%} of {name}'s outputs differ from GCC's bits"


# x86-64 processors without AVX2 (older PCs, many Atom and Celeron controllers): the runtime
# asks cpuid and XCR0 as it loads a model and takes its portable kernels, which sum in the AVX2
# kernels' order.
# QEMU's user-mode emulator reports the CPU it is told but still runs AVX2 instructions, so
# this checks the choice and the bits; an AVX2 instruction outside the guard would not fault.
X86_CPUS = {"Nehalem": 0, "SandyBridge": 0, "Haswell-v4": 1}   # SSE4.2; AVX but not AVX2; AVX2
CPU_PROBE = "#include <stdio.h>\nint pc_test_cpu_avx2(void);\nint main(void) { printf(\"%d\\n\", pc_test_cpu_avx2()); }\n"


@pytest.fixture(scope="module")
def x86_emulator() -> str:
    import platform

    if platform.machine() != "x86_64":
        pytest.skip("the host is not x86-64")
    require("x86-64 emulator", ("qemu-x86_64",), "qemu-user")
    return "qemu-x86_64"


@pytest.fixture(scope="module")
def cpu_probe(here, tmp_path_factory) -> Path:
    """A program that prints what the runtime's AVX2 check answers on the CPU it runs on."""
    folder = tmp_path_factory.mktemp("cpu")
    (folder / "cpu.c").write_text(CPU_PROBE)
    subprocess.run([os.environ.get("CC", "cc"), str(folder / "cpu.c"), "-o", str(folder / "cpu_avx2"), f"-L{here}",
                    "-lposecorr_testing", f"-Wl,-rpath,{here}"], check=True)
    return folder / "cpu_avx2"


@pytest.mark.parametrize("cpu", list(X86_CPUS))
def test_the_runtime_reads_the_cpu_it_runs_on(cpu, x86_emulator, cpu_probe):
    r = subprocess.run([x86_emulator, "-cpu", cpu, str(cpu_probe)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and r.stdout.strip() == str(X86_CPUS[cpu]), r.stdout + r.stderr[-500:]


def test_without_avx2_the_same_bits(x86_emulator, here):
    for model in MODELS:
        x = poses_in_bounds(ort.InferenceSession(str(model)), 500).tobytes()
        portable, native = (subprocess.run([*cpu, str(here / "posecorr-run"), str(model), "--binary"], input=x,
                                           capture_output=True, timeout=300)
                            for cpu in ([x86_emulator, "-cpu", "Nehalem"], []))
        assert portable.returncode == 0 and native.returncode == 0, portable.stderr[-500:] + native.stderr[-500:]
        assert portable.stdout == native.stdout, f"{model.stem}: without AVX2, other bits"

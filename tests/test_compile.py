"""`posecorr compile MODEL.onnx -o OUT.c`: the C file of a model's one-pose function, built
here with the host's C compiler, gives pc_run's bits (libposecorr through the shim) on
thousands of poses: the shipped zhou MLP, a table-1 MLP nobody shipped (one drawn from a
fixed seed per representation), and the demo's physics + PMC model. Refusals are one line, exit 2."""
from __future__ import annotations

import random
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "runtime_c" / "tests"))
import graphs  # noqa: E402
from posecorr.controller.onnx_meta import read_info  # noqa: E402
from posecorr.controller.runtime import Corrector  # noqa: E402

ZHOU = ROOT / "models" / "mlp-zhou-tansig-20x20x20x20-br.onnx"
N_POSES = 1500
CC = shutil.which("cc") or shutil.which("gcc")
pytestmark = pytest.mark.skipif(CC is None, reason="no C compiler")

# Reads float32 poses of 7 (and a time when the model takes one) on stdin, writes the
# outputs and the status of each call.
DRIVER = r"""
#include <stdio.h>
int NAME_run(const float in[7], TIME_PARAM float out[7]);
int main(void)
{
    float in[8], out[7] = {0};
    while (fread(in, sizeof(float), WIDTH, stdin) == WIDTH) {
        int status = NAME_run(in, TIME_ARG out);
        fwrite(out, sizeof out, 1, stdout);
        fwrite(&status, sizeof status, 1, stdout);
    }
    return 0;
}
"""


def compile_cli(model: Path, out: Path, *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "posecorr.cli", "compile", str(model), "-o", str(out), *extra],
                          capture_output=True, text=True)


def build(source: Path, name: str, takes_time: bool, *flags: str) -> Path:
    driver = source.with_name(source.stem + "_driver.c")
    text = DRIVER.replace("NAME", name).replace("WIDTH", "8" if takes_time else "7")
    driver.write_text(text.replace("TIME_PARAM", "float t," if takes_time else "")
                      .replace("TIME_ARG", "in[7]," if takes_time else ""))
    exe = source.with_suffix(".exe")
    r = subprocess.run([CC, "-std=c99", "-O2", "-Wall", "-Wextra", "-Werror", "-pedantic", *flags,
                        str(source), str(driver), "-lm", "-o", str(exe)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-3000:]
    return exe


def run_compiled(exe: Path, x: np.ndarray, t: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    rows = x if t is None else np.hstack([x, t[:, None].astype(np.float32)])
    r = subprocess.run([str(exe)], input=rows.astype(np.float32).tobytes(), capture_output=True, check=True)
    records = np.frombuffer(r.stdout, dtype=np.uint32).reshape(len(x), 8)
    return records[:, :7].copy().view(np.float32), records[:, 7]


def assert_same_bits(model: Path, tmp: Path, x: np.ndarray, *flags: str, **allow) -> str:
    """Compiles `model`, builds it, and compares with pc_run one pose at a time."""
    out = tmp / f"{model.stem.replace('-', '_')}.c"
    r = compile_cli(model, out, *flags)
    assert r.returncode == 0, r.stderr
    c = Corrector(model, backend="c", max_batch=1, **allow)
    exe = build(out, out.stem, c.takes_time)
    t = np.linspace(0.0, 600.0, len(x)).astype(np.float32) if c.takes_time else None
    got, status = run_compiled(exe, x, t)
    want = np.vstack([c.correct(x[i], t=None if t is None else float(t[i])) for i in range(len(x))])
    want = want.astype(np.float32)
    assert np.all(status == 0)
    same = np.all(got.view(np.uint32) == want.view(np.uint32), axis=1)
    assert same.all(), f"{model.name}: {np.sum(~same)} of {len(x)} poses differ, first {np.argmax(~same)}"
    # the correction moved the poses: outputs are not the inputs handed through
    assert np.abs(got[:, :3] - x[:, :3]).max() > 1e-4
    return out.read_text()


def test_shipped_zhou_mlp_gives_pc_run_bits(tmp_path):
    text = assert_same_bits(ZHOU, tmp_path, graphs.poses_in_box(ZHOU, N_POSES, seed=3))
    assert f"model_digest: {read_info(ZHOU)['model_digest']}" in text
    # the runtime's formulas, as they are, and the weights as constant arrays
    assert (ROOT / "runtime_c" / "formulas.h").read_text().strip() in text
    assert text.count("static const float w") == 5 and "dense_tanh(" in text


@pytest.mark.parametrize("path", sorted((ROOT / "models").glob("*.onnx")), ids=lambda p: p.name)
def test_every_shipped_model_gives_pc_run_bits(path, tmp_path):
    """MLPs of every activation (tansig, logsig through a Gemm with its sigmoid, radbas
    through a one-pose program) and the PMC models (pmc-R's 90 features gathered, multiplied
    and concatenated by node kernels, written as element operations)."""
    assert_same_bits(path, tmp_path, graphs.poses_in_box(path, 1000, seed=7))


def test_fused_multiply_add_stays_off_on_an_fma_target(tmp_path):
    """GNU C contracts a * b + c into one rounding where the target has FMA; the file turns
    that off itself, so a build for such a CPU keeps pc_run's bits."""
    if subprocess.run([CC, "-mfma", "-x", "c", "-c", "-o", "/dev/null", "-"], input="int x;",
                      capture_output=True, text=True).returncode:
        pytest.skip("the compiler has no -mfma")
    out = tmp_path / "zhou.c"
    assert compile_cli(ZHOU, out).returncode == 0
    asm = subprocess.run([CC, "-std=gnu99", "-O2", "-mfma", "-S", "-o", "-", str(out)],
                         capture_output=True, text=True, check=True).stdout
    assert "vfmadd" not in asm and "vfmsub" not in asm and "vfnmadd" not in asm


@pytest.mark.skipif(shutil.which("clang") is None, reason="no clang (Debian's clang; .ci/run installs it)")
def test_the_file_builds_without_a_warning_under_clang(tmp_path):
    """A firmware built with clang -Werror: the copied formulas a model leaves unused drew
    -Wunused-function (clang warns of a file's own unused static functions, not a header's)."""
    out = tmp_path / "zhou.c"
    assert compile_cli(ZHOU, out).returncode == 0
    r = subprocess.run(["clang", "-std=c99", "-O2", "-Wall", "-Wextra", "-Werror", "-pedantic", "-c", "-o",
                        str(tmp_path / "zhou.o"), str(out)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-3000:]


@pytest.mark.parametrize("rep", ["pos", "eaa", "quat", "R", "zhou"])
def test_unshipped_table1_mlp_gives_pc_run_bits(rep, tmp_path):
    """Each representation with a table-1 architecture drawn from a seed of its own (the same
    every run: a draw that changed with the run failed CI one run in five; every one of the
    80 passed when all were run), trained two epochs and exported by the project's exporter."""
    from posecorr.train.spec import ARCHITECTURES
    from tools.models import unshipped_mlp

    hidden = random.Random(f"compile {rep}").choice(ARCHITECTURES)
    path = unshipped_mlp(rep, hidden, tmp_path / f"mlp-{rep}-{'x'.join(map(str, hidden))}.onnx")
    try:
        assert_same_bits(path, tmp_path, graphs.poses_in_box(path, N_POSES, seed=4))
    except AssertionError as e:
        raise AssertionError(f"{rep} {hidden}: {e}") from None


def test_physics_pmc_model_gives_pc_run_bits(tmp_path):
    """The demo's physics + PMC model: sines, arctangents, Where and 3x3 products in its
    programs, its PMC layer a dense layer of no trained size."""
    from tools.models import demo_physics_pmc

    path = tmp_path / "physics_pmc.onnx"
    demo_physics_pmc(path)
    assert_same_bits(path, tmp_path, graphs.poses_in_box(path, N_POSES, seed=5))


def test_a_model_that_takes_time_gives_pc_run_bits(tmp_path):
    """A drift model has the input t: the function takes it after the pose."""
    from posecorr.export import to_onnx
    from posecorr.simulate import simulate
    from posecorr.train.physics import PhysicsModel

    table = simulate(3, seed=0).table
    idx = np.linspace(0, len(table.measured) - 1, 60).astype(int)
    m, r, t = table.measured[idx], table.reference[idx], table.extras["t"][idx]
    est = PhysicsModel(effects=("station", "mount", "drift")).fit(m, r, t=t)
    path = tmp_path / "drift.onnx"
    to_onnx(est, path, measured=m, reference=r, t=t)
    text = assert_same_bits(path, tmp_path, graphs.poses_in_box(path, 1000, seed=6))
    assert "int drift_run(const float in[7], float t, float out[7]);" in text
    # times outside the fitted span (time_bounds) or not finite: pc_run's refusals
    from posecorr.controller.onnx_meta import read_info

    t_lo, t_hi = (np.float32(v) for v in read_info(path)["time_bounds"])
    times = np.array([t_lo, t_hi, np.nextafter(t_lo, np.float32(-1e9)), np.nextafter(t_hi, np.float32(1e9)),
                      np.nan, np.inf], np.float32)
    x = np.repeat(graphs.poses_in_box(path, 1, seed=6), len(times), axis=0)
    codes, statuses = refusals(path, tmp_path, x, t=times)
    assert codes == [0, 0, 2, 2, 4, 4], codes
    from posecorr.controller.checks import Status

    assert statuses == [0, 0, Status.RANGE, Status.RANGE, Status.NONFINITE, Status.NONFINITE], statuses


def _refusal(r: subprocess.CompletedProcess) -> str:
    assert r.returncode == 2, (r.returncode, r.stderr)
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1, r.stderr
    return lines[0]


def test_not_an_onnx_file_is_refused_in_one_line(tmp_path):
    csv = tmp_path / "poses.csv"
    csv.write_text("x,y,z,qw,qx,qy,qz\n0,0,0,1,0,0,0\n")
    out = tmp_path / "m.c"
    line = _refusal(compile_cli(csv, out))
    assert line.startswith("posecorr compile: error: ") and str(csv) in line
    assert not out.exists()


def test_a_model_with_a_step_of_no_c_form_is_refused(tmp_path):
    """A sum over 70 columns of the pose runs k_reduce_sum_last (more terms than a one-pose
    program takes), a kernel with no C form: refused, naming the step and the kernel, and
    nothing written."""
    g = graphs.G()
    total = g.op("ReduceSum", [g.shaped("pose", [70]), g.i64([1])], keepdims=1)
    head = g.op("Slice", ["pose", g.i64([0]), g.i64([3]), g.i64([1])])
    tail = g.op("Slice", ["pose", g.i64([3]), g.i64([7]), g.i64([1])])
    pos = g.op("Add", [head, g.op("Mul", [total, g.f32([1e-3])])])
    model = tmp_path / "wide.onnx"
    model.write_bytes(g.model(g.op("Concat", [pos, tail], axis=1), metadata=graphs.BOUNDED).SerializeToString())
    out = tmp_path / "wide.c"
    line = _refusal(compile_cli(model, out, "--allow-unsigned"))
    assert "cannot compile: step 1 of its one-pose plan runs k_reduce_sum_last, which has no C form" in line
    assert not out.exists()
    # without --allow-unsigned the runtime's own refusal of an unsigned file, in one line
    assert "no metadata model_digest" in _refusal(compile_cli(model, out))


def test_output_onto_the_input_is_refused(tmp_path):
    model = tmp_path / "zhou.onnx"
    model.write_bytes(ZHOU.read_bytes())
    line = _refusal(compile_cli(model, model))
    assert "zhou.onnx" in line
    assert model.read_bytes() == ZHOU.read_bytes()


def test_a_name_that_is_no_c_identifier_is_refused(tmp_path):
    line = _refusal(compile_cli(ZHOU, tmp_path / "m.c", "--name", "2fast"))
    assert "--name '2fast': a C identifier is expected" in line
    line = _refusal(compile_cli(ZHOU, tmp_path / "2fast.c"))
    assert "the output's name gives '2fast'; --name: a C identifier is expected" in line
    assert not (tmp_path / "2fast.c").exists()
    # a leading underscore: `-o -` named the function __run, which C reserves, as an output named "_" would
    line = _refusal(compile_cli(ZHOU, tmp_path / "_"))
    assert "the output's name gives '_'; --name: a C identifier is expected" in line and "reserves" in line
    run = compile_cli(ZHOU, Path("-"))
    assert run.returncode == 2 and "'-' would be a file named '-'" in run.stderr and not Path("-").exists()


def test_the_function_is_named_after_the_output(tmp_path):
    out = tmp_path / "arm-zhou.c"
    r = compile_cli(ZHOU, out, "--json")
    assert r.returncode == 0, r.stderr
    import json

    report = json.loads(r.stdout)
    assert report["function"] == "arm_zhou_run" and report["steps"] == 3
    assert "int arm_zhou_run(const float in[7], float out[7])\n{" in out.read_text()


# -- pc_run's refusals -------------------------------------------------------------------------

def refusals(model: Path, tmp: Path, x: np.ndarray, *flags: str, t: np.ndarray | None = None,
             **allow) -> tuple[list[int], list[int]]:
    """(the compiled function's return code, pc_run's status) of each pose (at time t[i] for
    a model that takes time), one at a time; where both accept, the same bits."""
    from posecorr.controller.checks import PoseCorrError

    out = tmp / f"{model.stem.replace('-', '_')}.c"
    r = compile_cli(model, out, *flags)
    assert r.returncode == 0, r.stderr
    got, codes = run_compiled(build(out, out.stem, t is not None), x, t)
    c = Corrector(model, backend="c", max_batch=1, **allow)
    statuses = []
    for i in range(len(x)):
        try:
            want = c.correct(x[i], t=None if t is None else float(t[i])).astype(np.float32)
        except PoseCorrError as e:
            statuses.append(e.status)
            continue
        statuses.append(0)
        assert np.array_equal(got[i].view(np.uint32), want.view(np.uint32)), i
    return [int(k) for k in codes], statuses


def test_compiled_function_refuses_what_pc_run_refuses(tmp_path):
    """Positions outside the model's input_bounds (and on them), quaternions off unit by more
    than 1e-3 (and by less), NaN and infinity: the compiled function's code is pc_run's refusal
    (documented at the top of the file), with the bounds pc_run compares."""
    from posecorr.controller.checks import Status
    from posecorr.controller.onnx_meta import read_info

    lo, hi = (np.array(b, np.float32) for b in read_info(ZHOU)["input_bounds"])
    base = graphs.poses_in_box(ZHOU, 1, seed=11)[0]
    cases = {}
    for k in range(3):
        for side, v in (("below", np.nextafter(lo[k], np.float32(-1))), ("above", np.nextafter(hi[k], np.float32(1))),
                        ("on low", lo[k]), ("on high", hi[k])):
            cases[f"column {k} {side}"] = (k, v)
    x = []
    for k, v in cases.values():
        p = base.copy()
        p[k] = v
        x.append(p)
    for scale in (1.5, 0.0, 1.0011, 0.9989, 1.0009, 0.9991):
        p = base.copy()
        p[3:] = p[3:] / np.linalg.norm(p[3:]) * scale
        x.append(p)
    for bad in (np.nan, np.inf):
        p = base.copy()
        p[5] = bad
        x.append(p)
    p = base.copy()   # SteamVR's "no pose": a zero quaternion (5, before the box), at a position outside
    p[:3], p[3:] = hi + 1, 0
    x.append(p)
    # |q|^2 a few 1e-8 around the tolerance's ends and the float band's (PC_QUAT_NORM2_BAND),
    # where the double sum decides
    for target in (0.998001, 1.002001, 1 - 0.00199, 1 + 0.00199):
        for k in range(-40, 41, 8):
            p = base.copy()
            p[3:] = (p[3:] / np.linalg.norm(p[3:]) * np.sqrt(target * (1 + k * 1e-8))).astype(np.float32)
            x.append(p)
    codes, statuses = refusals(ZHOU, tmp_path, np.array(x, np.float32))
    code_of = {Status.OK: 0, Status.RANGE: 2, Status.NONFINITE: 4, Status.QUATERNION: 5}
    assert codes == [code_of[Status(s)] for s in statuses], list(zip(codes, statuses))
    # each kind of refusal and acceptance occurred (the cases are what they claim)
    assert set(codes) == {0, 2, 4, 5}
    assert codes[:12] == [2, 2, 0, 0] * 3
    assert codes[12:18] == [5, 5, 5, 5, 0, 0]
    assert codes[18:21] == [4, 4, 5]
    assert {0, 5} <= set(codes[21:])
    text = (tmp_path / f"{ZHOU.stem.replace('-', '_')}.c").read_text()
    for code in ("2  the input is outside", "3  the correction moves", "5  the input quaternion"):
        assert f" *   {code}" in text


def test_correction_beyond_reach_and_unbounded_models(tmp_path):
    """A model whose correction_reach its corrections exceed: pc_run refuses every pose
    (PC_ERR_RUNTIME), the compiled function returns 3. Without input_bounds and
    correction_reach, compiled with --allow-unbounded: any position passes, as in pc_run."""
    import onnx

    from posecorr.controller.checks import Status

    model = graphs.without_metadata(onnx.load(str(ZHOU)), "correction_reach")
    entry = model.metadata_props.add()
    entry.key, entry.value = "correction_reach", "[0.0001, 0.0001]"
    tight = tmp_path / "tight.onnx"
    tight.write_bytes(graphs.signed(model, aligned=True))
    x = graphs.poses_in_box(ZHOU, 20, seed=5)
    codes, statuses = refusals(tight, tmp_path, x)
    assert statuses == [Status.RUNTIME] * len(x) and codes == [3] * len(x)

    free = tmp_path / "free.onnx"
    free.write_bytes(graphs.signed(graphs.without_metadata(model, "input_bounds", "correction_reach")))
    far = x.copy()
    far[:, 0] += 5.0
    assert compile_cli(free, tmp_path / "refused.c").returncode != 0  # unbounded needs the flag
    codes, statuses = refusals(free, tmp_path, far, "--allow-unbounded", allow_unbounded=True)
    assert codes == statuses == [0] * len(x)
    text = (tmp_path / "free.c").read_text()
    assert "return 2;" not in text and "return 3;" not in text

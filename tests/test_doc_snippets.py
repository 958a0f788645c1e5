"""The code the README and the guides show runs as a user would paste it.

Every ```python block is executed with the names its page leaves to the reader bound to a
simulated session (`measured`, `reference`: (N, 7) poses; `pose`: one of them), in a scratch
folder holding the file the page names. Every ```c block is compiled against `posecorr.h`
and linked with libposecorr: statements go into a `main` with the pose's names declared, and
the program runs on a shipped model. A block that is an excerpt says why on the line before
its fence, `<!-- not run: REASON -->`, and is left out (the test lists those it leaves out).
"""
from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "runtime_c" / "tests"))
PAGES = sorted([ROOT / "README.md", ROOT / "runtime_c" / "README.md", *(ROOT / "docs").rglob("*.md")])
NOT_RUN = re.compile(r"<!--\s*not run:\s*(.+?)\s*-->")
SHIPPED = ROOT / "models" / "mlp-zhou-tansig-20x20x20x20-br.onnx"
# The file names the pages load; each is the shipped model, copied under that name.
MODEL_NAMES = ("model.onnx", "step2.onnx")


def snippets(language: str) -> list[tuple[str, str, str | None]]:
    """(page:line, code, reason it is not run or None) of every ```LANGUAGE block."""
    found = []
    for page in PAGES:
        lines = page.read_text(encoding="utf-8").splitlines()
        i = 0
        while i < len(lines):
            if lines[i].strip() != f"```{language}":
                i += 1
                continue
            reason = NOT_RUN.search(lines[i - 1]) if i else None
            start = i = i + 1
            while i < len(lines) and lines[i].strip() != "```":
                i += 1
            found.append((f"{page.relative_to(ROOT)}:{start}", "\n".join(lines[start:i]) + "\n",
                          reason.group(1) if reason else None))
    return found


def _ids(items):
    return [where for where, _, _ in items]


PYTHON = snippets("python")
C = snippets("c")


def test_the_pages_have_code_to_run_and_say_why_they_leave_any_out():
    assert sum(reason is None for *_, reason in PYTHON) >= 2
    assert sum(reason is None for *_, reason in C) >= 2
    left_out = [(where, reason) for where, _, reason in PYTHON + C if reason]
    for where, reason in left_out:
        assert len(reason.split()) >= 3, f"{where}: say why the block is not run"
    print("not run:", left_out)


@pytest.fixture(scope="module")
def session():
    from posecorr.simulate import simulate

    sim = simulate(3, seed=0)
    return sim.table.measured[:240], sim.table.reference[:240]


@pytest.fixture
def scratch(tmp_path, monkeypatch):
    for name in MODEL_NAMES:
        shutil.copy(SHIPPED, tmp_path / name)
    monkeypatch.chdir(tmp_path)
    return tmp_path


@pytest.mark.slow
@pytest.mark.parametrize("where,code,reason", PYTHON, ids=_ids(PYTHON))
def test_python_block_runs(where, code, reason, session, scratch):
    if reason:
        pytest.skip(reason)
    measured, reference = session
    names = {"measured": measured, "reference": reference, "pose": measured[0].copy(),
             "__name__": "__snippet__"}
    exec(compile(code, where, "exec"), names)
    # What the comments beside the code say it gives, checked where a block says it.
    if "corrector" in names:
        one, many = names["corrector"].correct(measured[0]), names["corrector"].correct(measured[:5])
        assert one.shape == (7,) and many.shape == (5, 7)
        np.testing.assert_allclose(many[0], one, rtol=0, atol=1e-6)
    if "model" in names and hasattr(names["model"], "score"):
        from posecorr.metrics import pose_metrics

        rmse = pose_metrics(reference, names["model"].predict(measured))["rmse_total"]
        assert names["model"].score(measured, reference) == pytest.approx(-rmse, rel=1e-9)
    if "spec" in names:
        said = re.search(r"spec\.file_name: (\S+)", code)
        assert said and names["spec"].file_name == said.group(1)


@pytest.fixture(scope="module")
def runtime():
    import graphs

    return graphs.build_test_runtime()


PROTOTYPE = re.compile(r"^\s*int (\w+)_run\(const float in\[7\], float out\[7\]\);")


def as_program(code: str, compiled: tuple[Path, str] | None) -> str:
    """The block as a C file: its #include lines at the top, the rest in a main that has the
    pose's names and reads the model named on the command line. A block that only declares
    `NAME_run` comes with `compiled`, (the file `posecorr compile --name NAME` wrote, NAME):
    the declaration follows that file, so one that differs from the definition does not
    compile, and main calls it."""
    if "int main(" in code:      # a whole program, compiled as written (the frame below
        return code             # added the <stdio.h> the runtime's first example lacked)
    lines = code.splitlines()
    top = [line for line in lines if line.startswith("#")]
    body = "\n".join(line for line in lines if not line.startswith("#"))
    for name in MODEL_NAMES:
        body = body.replace(f'"{name}"', "argv[1]")
    if compiled is not None:
        file, function = compiled
        top, body = [f'#include "{file}"', *top, body], f"    if ({function}_run(in, out)) return 3;"
    return "\n".join([
        "#include <stdio.h>", *top,
        "int main(int argc, char **argv) {",
        "    float x = 0.1f, y = -0.5f, z = 0.4f, qw = 1.0f, qx = 0.0f, qy = 0.0f, qz = 0.0f;",
        "    if (argc < 2) return 2;",
        "    float in[7] = {x, y, z, qw, qx, qy, qz}, out[7];" if compiled is not None else "",
        body,
        '    for (int i = 0; i < 7; i++) printf("%.9g\\n", out[i]);',
        "    return 0;",
        "}", ""])


@pytest.mark.parametrize("where,code,reason", C, ids=_ids(C))
def test_c_block_compiles_and_runs(where, code, reason, runtime, tmp_path):
    """Each block prints the corrected pose of (0.1, -0.5, 0.4, identity), which must be
    onnxruntime's for the shipped model within float32's rounding."""
    if reason:
        pytest.skip(reason)
    compiled = None
    prototype = PROTOTYPE.match(code)
    if prototype:
        compiled = (tmp_path / "compiled.c", prototype.group(1))
        subprocess.run([sys.executable, "-m", "posecorr.cli", "compile", str(SHIPPED), "-o",
                        str(compiled[0]), "--name", compiled[1]], check=True, capture_output=True)
    source = tmp_path / "snippet.c"
    source.write_text(as_program(code, compiled))
    exe = tmp_path / "snippet"
    whole = ["-Wextra", "-pedantic"] if "int main(" in code else []     # the frame's main is not the reader's
    built = subprocess.run([os.environ.get("CC", "cc"), "-std=c99", "-Wall", *whole, "-Werror",
                            "-Wno-unused-variable", f"-I{ROOT / 'runtime_c'}", str(source), "-o",
                            str(exe), f"-L{runtime}", "-lposecorr", f"-Wl,-rpath,{runtime}", "-lm"],
                           capture_output=True, text=True)
    assert built.returncode == 0, f"{where} does not compile:\n{source.read_text()}\n{built.stderr}"
    ran = subprocess.run([str(exe), str(SHIPPED)], capture_output=True, text=True, timeout=60)
    assert ran.returncode == 0, f"{where}: {ran.stdout}{ran.stderr}"
    from posecorr import Corrector

    pose = np.array([0.1, -0.5, 0.4, 1.0, 0.0, 0.0, 0.0], dtype=np.float32)
    want = Corrector(str(SHIPPED), backend="onnxruntime").correct(pose)
    np.testing.assert_allclose([float(v) for v in ran.stdout.split()], want, rtol=0, atol=2e-6)

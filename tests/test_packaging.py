"""The wheel holds the product only: built with `pip wheel` from a copy of the checkout, it
has every package of the source tree and no benchmark or model-building harness (those
live in bench/ and tools/), none of its modules reaches out of the installed package (into
`tests/data`, `runtime_c/`, or up the directory tree to a checkout), and installed in a
fresh environment its command line answers `--help` for every verb."""
from __future__ import annotations

import ast
import re
import shutil
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# What setuptools reads to build the wheel; build products of the checkout stay behind.
SOURCES = ("pyproject.toml", "setup.py", "README.md", "python", "train", "export", "runtime_c")
BUILD_LEFTOVERS = shutil.ignore_patterns("build", "build-*", "build_*", "_native", "__pycache__", "*.so",
                                         "*.egg-info", "*.pyc")
# Path components by which a module would read the checkout instead of its own package.
CHECKOUT_ONLY = {"tests", "runtime_c", "bench", "tools", "models"}

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    work = tmp_path_factory.mktemp("wheel")
    src = work / "src"
    src.mkdir()
    for name in SOURCES:
        path = ROOT / name
        if path.is_dir():
            shutil.copytree(path, src / name, ignore=BUILD_LEFTOVERS)
        else:
            shutil.copy2(path, src / name)
    out = work / "dist"
    run = subprocess.run([sys.executable, "-m", "pip", "wheel", str(src), "--no-deps", "--no-build-isolation",
                          "--no-index", "-q", "-w", str(out)], capture_output=True, text=True, cwd=work)
    assert run.returncode == 0, run.stderr[-3000:]
    (whl,) = out.glob("posecorr-*.whl")
    return whl


def wheel_modules(whl: Path) -> dict[str, str]:
    """{path in the wheel: source} of every Python module the wheel holds."""
    with zipfile.ZipFile(whl) as z:
        return {n: z.read(n).decode("utf-8") for n in z.namelist() if n.endswith(".py")}


def source_packages() -> set[str]:
    """Every package of the source tree, by its installed name (pyproject's package-dir)."""
    roots = {"posecorr": ROOT / "python" / "posecorr", "posecorr/train": ROOT / "train",
             "posecorr/export": ROOT / "export"}
    out = set()
    for prefix, root in roots.items():
        for init in root.rglob("__init__.py"):
            rel = init.parent.relative_to(root).as_posix()
            out.add(prefix if rel == "." else f"{prefix}/{rel}")
    return out


def is_harness(module: str) -> bool:
    """A benchmark or the shipped models' recipe, by the names they had in the package; the
    `bench` verb of the command line (posecorr/cli/bench.py) is the product."""
    folder, _, name = module.rpartition("/")
    return (name.startswith("bench_") or name == "benchmarks.py" or (name == "bench.py" and folder != "posecorr/cli")
            or module == "posecorr/export/models.py")


def docstring_nodes(tree: ast.AST) -> set[int]:
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and node.body:
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant):
                out.add(id(first.value))
    return out


def escapes(path: str, source: str) -> list[str]:
    """The ways a module at `path` (inside the wheel) reads outside the installed package:
    a checkout folder named in a string (docstrings aside), `Path(...).parents[k]` or a
    chain of `.parent` climbing above the top package folder."""
    depth = path.count("/")          # posecorr/controller/runtime.py: parents[1] is posecorr/
    tree = ast.parse(source, path)
    docs = docstring_nodes(tree)
    # the inner links of a `.parent.parent` chain: the chain is judged once, whole
    inner_links = {id(n.value) for n in ast.walk(tree) if isinstance(n, ast.Attribute) and n.attr == "parent"}
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in docs:
            parts = set(re.split(r"[/\\]", node.value))
            if parts & CHECKOUT_ONLY and len(parts) > 1:
                found.append(f"line {node.lineno}: path into the checkout {node.value!r}")
            elif node.value in ("tests", "runtime_c"):   # "bench" and "models" are also words of the CLI
                found.append(f"line {node.lineno}: checkout folder {node.value!r}")
        elif (isinstance(node, ast.Subscript) and isinstance(node.value, ast.Attribute)
              and node.value.attr == "parents" and isinstance(node.slice, ast.Constant)
              and node.slice.value >= depth):
            found.append(f"line {node.lineno}: parents[{node.slice.value}] leaves the package")
        elif isinstance(node, ast.Attribute) and node.attr == "parent" and id(node) not in inner_links:
            chain, inner = 0, node
            while isinstance(inner, ast.Attribute) and inner.attr == "parent":
                chain, inner = chain + 1, inner.value
            if chain > depth:
                found.append(f"line {node.lineno}: .parent x{chain} leaves the package")
    return found


def test_escapes_sees_a_module_climbing_to_the_checkout():
    climbing = ('"""Reads `tests/data` (a docstring may name it)."""\nfrom pathlib import Path\n'
                'ROOT = Path(__file__).resolve().parents[2]\nDATA = ROOT / "tests" / "data"\n'
                'UP = Path(__file__).parent.parent.parent\nW = "runtime_c/tools/zhou_weights.py"\n')
    found = escapes("posecorr/bench.py", climbing)
    assert len(found) == 4, found
    assert not escapes("posecorr/controller/runtime.py",
                       'from pathlib import Path\nNATIVE = Path(__file__).resolve().parents[1] / "_native"\n')


def test_is_harness_names_the_moved_modules():
    moved = ["posecorr/benchmarks.py", "posecorr/bench_apply.py", "posecorr/bench_targets.py",
             "posecorr/ingest/bench.py", "posecorr/train/bench_fit.py", "posecorr/train/bench_train.py",
             "posecorr/export/models.py"]
    assert all(is_harness(m) for m in moved)
    assert not any(is_harness(m) for m in ("posecorr/cli/bench.py", "posecorr/latency.py", "posecorr/train/lm.py"))


def test_wheel_holds_every_package_and_no_harness(wheel):
    with zipfile.ZipFile(wheel) as z:
        names = z.namelist()
    tops = {n.split("/")[0] for n in names}
    assert tops == {"posecorr", "posecorr-0.1.0.dist-info"}, tops
    packages = {n.rsplit("/", 1)[0] for n in names if n.endswith("/__init__.py")}
    assert packages == source_packages()
    modules = [n for n in names if n.endswith(".py")]
    harness = [n for n in modules if is_harness(n)]
    assert not harness, f"benchmark or model-building modules in the wheel: {harness}"
    for product in ("posecorr/latency.py", "posecorr/_native/libposecorr.so", "posecorr/_native/posecorr-bench",
                    "posecorr/_native/posecorr-plan", "posecorr/_native/formulas.h",
                    "posecorr/export/operators.txt"):
        assert product in names


def test_no_wheel_module_reads_the_checkout(wheel):
    found = {path: where for path, source in wheel_modules(wheel).items() if (where := escapes(path, source))}
    assert not found, found


def test_installed_wheel_answers_help_for_every_verb(wheel, tmp_path):
    """A fresh environment with the wheel installed (its dependencies come from this one's
    site-packages by a .pth file, which does not run this checkout's editable finder)."""
    env = tmp_path / "venv"
    subprocess.run([sys._base_executable, "-m", "venv", "--without-pip", str(env)], check=True)
    target = Path(subprocess.run([str(env / "bin" / "python"), "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"],
                                 capture_output=True, text=True, check=True).stdout.strip())
    # An import line with the folder as an ASCII literal: Python 3.11 reads .pth files in the
    # locale's encoding, not UTF-8 mode's, and a checkout under "/tmp/prüf ü" with a locale
    # the system lacks (C, ASCII) could not read the folder's name written plainly.
    (target / "posecorr_test_dependencies.pth").write_text(
        f"import sys; sys.path.append({ascii(sysconfig.get_path('purelib'))})\n", encoding="ascii")
    subprocess.run([sys.executable, "-m", "pip", "--python", str(env / "bin" / "python"), "install", "-q",
                    "--no-deps", "--no-index", str(wheel)], check=True, capture_output=True)
    where = subprocess.run([str(env / "bin" / "python"), "-c", "import posecorr; print(posecorr.__file__)"],
                           capture_output=True, text=True, check=True, cwd=tmp_path).stdout
    assert Path(where.strip()).is_relative_to(target)

    exe = str(env / "bin" / "posecorr")
    top = subprocess.run([exe, "--help"], capture_output=True, text=True, cwd=tmp_path)
    assert top.returncode == 0, top.stderr
    verbs = re.findall(r"^ {4}([a-z][a-z0-9_]*)(?: |$)", top.stdout, re.M)
    assert {"simulate", "ingest", "fit", "diagnose", "report", "sweep", "export", "demo", "info", "apply",
            "ros2", "bench", "compile"} <= set(verbs), top.stdout
    for verb in verbs:
        r = subprocess.run([exe, verb, "--help"], capture_output=True, text=True, cwd=tmp_path)
        assert r.returncode == 0 and r.stdout.startswith(f"usage: posecorr {verb}"), (verb, r.stderr)
    # compile from the wheel alone: the plan printer and formulas.h travel with libposecorr
    out = tmp_path / "zhou_fw.c"
    r = subprocess.run([exe, "compile", str(ROOT / "models" / "mlp-zhou-tansig-20x20x20x20-br.onnx"), "-o", str(out)],
                       capture_output=True, text=True, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert "int zhou_fw_run(const float in[7], float out[7])\n{" in out.read_text()

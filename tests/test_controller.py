"""The controller side (`posecorr.controller`) on numpy alone.

A subprocess installs an import hook that refuses torch, scipy, scikit-learn, onnx,
onnxruntime and matplotlib before anything else is imported, then imports the controller
subpackage, corrects poses through the C shim, applies a model to a table and reads a
model's info. Its results must equal those of the same calls in this (full) process, and
the corrected poses must agree with onnxruntime (the independent judge).
"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from posecorr.controller import Corrector, apply_file, read_info
from posecorr.data import write_table
from posecorr.simulate import simulate

MODELS = Path(__file__).resolve().parents[1] / "models"
SHIPPED = ("pmc-zhou.onnx", "mlp-zhou-tansig-20x20x20x20-br.onnx", "pmc-pos.onnx")
HEAVY = ("torch", "scipy", "sklearn", "onnx", "onnxruntime", "matplotlib")

BLOCKED = """
import importlib.abc, json, sys
HEAVY = {heavy!r}

class Refuse(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in HEAVY:
            raise ImportError(f"{{name}} is blocked: the controller side must not need it")
        return None

sys.meta_path.insert(0, Refuse())
import numpy as np
import posecorr.controller as controller

poses = np.load({poses!r})
out = {{}}
for name in {models!r}:
    with controller.Corrector({folder!r} + "/" + name) as corrector:
        np.save({folder_out!r} + "/" + name + ".npy", corrector.correct(poses))
        np.save({folder_out!r} + "/" + name + ".one.npy", corrector.correct(poses[0]))
    out[name] = controller.read_info({folder!r} + "/" + name)
out["apply"] = controller.apply_file({folder!r} + "/" + {models!r}[0], {table!r}, {applied!r})
try:
    import onnxruntime
except ImportError:
    out["blocked"] = True
out["heavy"] = sorted(m for m in HEAVY if m in sys.modules)
print(json.dumps(out, default=str))
"""


def test_controller_runs_with_the_heavy_packages_unimportable(tmp_path) -> None:
    table = simulate(3, seed=4).table.subset(np.arange(200))
    poses = table.measured
    np.save(tmp_path / "poses.npy", poses)
    write_table(table, tmp_path / "in.csv")
    script = BLOCKED.format(heavy=HEAVY, poses=str(tmp_path / "poses.npy"), models=SHIPPED,
                            folder=str(MODELS), folder_out=str(tmp_path), table=str(tmp_path / "in.csv"),
                            applied=str(tmp_path / "blocked.csv"))
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    blocked = json.loads(run.stdout)
    assert blocked["blocked"] is True and blocked["heavy"] == []

    import onnxruntime as ort

    for name in SHIPPED:
        with Corrector(MODELS / name) as corrector:
            normal = corrector.correct(poses)
        np.testing.assert_array_equal(np.load(tmp_path / f"{name}.npy"), normal)
        np.testing.assert_array_equal(np.load(tmp_path / f"{name}.one.npy"), normal[0])
        session = ort.InferenceSession(str(MODELS / name), providers=["CPUExecutionProvider"])
        judge = session.run(["corrected"], {"pose": poses.astype(np.float32)})[0]
        np.testing.assert_allclose(normal, judge, atol=2e-6)
        assert blocked[name] == json.loads(json.dumps(read_info(MODELS / name), default=str))
    normal_apply = apply_file(MODELS / SHIPPED[0], tmp_path / "in.csv", tmp_path / "normal.csv")
    assert {k: v for k, v in blocked["apply"].items() if k != "output"} == \
        {k: v for k, v in normal_apply.items() if k != "output"}
    assert (tmp_path / "blocked.csv").read_bytes() == (tmp_path / "normal.csv").read_bytes()


def test_the_blocking_hook_does_block() -> None:
    """The hook of the test above refuses what it names (else that test proves nothing)."""
    script = BLOCKED.split("import numpy")[0] + "import scipy.linalg\n"
    run = subprocess.run([sys.executable, "-c", script.format(heavy=HEAVY)], capture_output=True, text=True,
                         timeout=60)
    assert run.returncode != 0 and "scipy is blocked" in run.stderr



def test_controller_verbs_run_with_the_heavy_packages_unimportable(tmp_path) -> None:
    """The verbs the docs give a controller-side install (info, apply, bench, compile) run
    through the CLI with the heavy packages refused."""
    table = simulate(3, seed=4).table.subset(np.arange(50))
    write_table(table, tmp_path / "in.csv")
    model = str(MODELS / SHIPPED[0])
    verbs = [["info", model], ["apply", model, str(tmp_path / "in.csv"), "-o", str(tmp_path / "out.csv")],
             ["bench", model, "--n", "200", "--batch", "50"], ["compile", model, "-o", str(tmp_path / "m.c")]]
    hook = BLOCKED.split("import numpy")[0].format(heavy=HEAVY)
    for argv in verbs:
        script = hook + f"from posecorr.cli import main\nsys.exit(main({argv!r}))\n"
        run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
        assert run.returncode == 0, (argv[0], run.stderr)
    assert len((tmp_path / "out.csv").read_text().splitlines()) == 51
    assert "int m_run(const float in[7], float out[7]);" in (tmp_path / "m.c").read_text()

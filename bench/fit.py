"""Fit speed on the tables robot cells produce (issue 10, item 4), for `make bench`.

Each figure is the wall time of the `posecorr fit` command as a user runs it (a fresh
process: imports, fit, cross-validation, export with its parity check), the best of
`repeats` runs, with the machine's load average beside it (the machines are shared):

* `physics_loo_36`: `fit --effects station,mount --method none --cv loo` on a realistic
  session of 36 poses (goal: 5 s on a quiet 2-core machine);
* `auto_loo_36`: the same table with `--method auto --cv loo` (goal: 10 s, issue 23);
* `physics_exp3`: `fit --effects station,mount --method none` on simulated Experiment III,
  3375 poses (goal: 10 s);
* the two real sessions of tests/data/realdata with `--cv loo`, physics and auto.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from . import ROOT

GOALS_S = {"physics_loo_36": 5.0, "auto_loo_36": 10.0, "physics_exp3": 10.0}


def _timed(args: list[str], repeats: int) -> dict:
    best, load = float("inf"), []
    for _ in range(repeats):
        load.append(os.getloadavg()[0])
        start = time.perf_counter()
        run = subprocess.run([sys.executable, "-m", "posecorr.cli", *args], capture_output=True, text=True)
        elapsed = time.perf_counter() - start
        if run.returncode != 0:
            raise RuntimeError(f"posecorr {' '.join(args)} failed: {run.stderr.strip()}")
        best = min(best, elapsed)
    return {"command": "posecorr " + " ".join(args), "best_s": round(best, 3),
            "load_average_1min": [round(x, 2) for x in load]}


def run(path: str | None = None, repeats: int = 3) -> dict:
    from posecorr.data import write_table
    from posecorr.simulate import simulate, simulate_session

    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        session = work / "session36.csv"
        write_table(simulate_session(7, n=36, spread="full").table, session)
        exp3 = work / "exp3.csv"
        write_table(simulate(3, seed=0).table, exp3)
        out = str(work / "m.onnx")
        real = ROOT / "tests" / "data" / "realdata"
        physics = ["--effects", "station,mount", "--method", "none"]
        cases = {
            "physics_loo_36": [str(session), "-o", out, *physics, "--cv", "loo"],
            "auto_loo_36": [str(session), "-o", out, "--method", "auto", "--cv", "loo"],
            "physics_exp3": [str(exp3), "-o", out, *physics],
            "real_exp1_physics_loo": [str(real / "20201002_Exp1.csv"), "-o", out, *physics, "--cv", "loo"],
            "real_exp1_auto_loo": [str(real / "20201002_Exp1.csv"), "-o", out, "--method", "auto", "--cv", "loo"],
            "real_exp2_auto_loo": [str(real / "20200717_Exp2.csv"), "-o", out, "--method", "auto", "--cv", "loo"],
        }
        results = {}
        for name, args in cases.items():
            results[name] = _timed(["fit", *args, "--json"], repeats if name in GOALS_S else 1)
            if name in GOALS_S:
                results[name]["goal_s"] = GOALS_S[name]
                results[name]["met"] = results[name]["best_s"] <= GOALS_S[name]
            print(f"{name}: {results[name]['best_s']} s", file=sys.stderr)
    result = {"benchmark": "fit speed on robot-cell tables", "cpus": os.cpu_count(), "cases": results}
    if path:
        Path(path).write_text(json.dumps(result, indent=2))
    return result


if __name__ == "__main__":
    print(json.dumps(run(sys.argv[1] if len(sys.argv) > 1 else None), indent=2))

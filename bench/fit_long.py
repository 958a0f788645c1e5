"""`posecorr fit` on a 10^6-row table (issue 31, item 5): wall time and peak memory
(bench/results/fit_long.json).

A fit takes at most `FIT_ROWS_MAX` rows (python/posecorr/cli/fit.py): past them it is
refused once that many are read, before any fitting, with the ways to reduce the table.
Both routes run as their own process on the same generated table (bench/apply.py's, 10^6
Experiment III-like poses with references, ~285 MB): the refusal, and `--subsample
FIT_ROWS_MAX` (the whole table read, an even draw fitted and exported). The goal of the
issue is at most 2 GB and 2 minutes; the load average is recorded beside the figures (the
machines are shared).
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from .apply import _RUNNER, _peak_kib, write_table

ROWS = 1_000_000


def _measured(argv: list[str]) -> dict:
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", _RUNNER, json.dumps(argv)], capture_output=True, text=True)
    wall = time.perf_counter() - t0
    message = [line for line in proc.stderr.splitlines() if line.startswith("posecorr fit: error")]
    return {"command": "posecorr " + " ".join(argv[:1] + ["TABLE"] + argv[2:3] + ["OUT"] + argv[4:]),
            "exit": proc.returncode, "wall_s": round(wall, 2), "peak_rss_mb": round(_peak_kib(proc.stderr) / 1024, 1),
            "load_average_1min_before": round(load, 2), "refusal": message[0] if message else None}


def run(out_path: str | None = None, rows: int = ROWS) -> dict:
    from posecorr.cli.fit import FIT_ROWS_MAX

    with tempfile.TemporaryDirectory(prefix="posecorr-bench-fit-long-") as tmp:
        table, model = Path(tmp) / "table.csv", str(Path(tmp) / "m.onnx")
        write_table(table, rows)
        refused = _measured(["fit", str(table), "-o", model])
        drawn = _measured(["fit", str(table), "-o", model, "--subsample", str(FIT_ROWS_MAX)])
        if refused["exit"] != 2 or drawn["exit"] != 0:
            raise RuntimeError(f"unexpected exit: refused {refused['exit']}, --subsample {drawn['exit']}")
        result = {"rows": rows, "input_bytes": table.stat().st_size, "fit_rows_max": FIT_ROWS_MAX,
                  "refused": refused, "subsample": drawn, "cpu_count": os.cpu_count(),
                  "goal": {"wall_s": 120, "peak_rss_mb": 2048}}
    if out_path:
        Path(out_path).write_text(json.dumps(result, indent=2) + "\n")
    return result


if __name__ == "__main__":
    print(json.dumps(run(sys.argv[1] if len(sys.argv) > 1 else None), indent=2))

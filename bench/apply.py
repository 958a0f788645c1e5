"""`posecorr apply` on 10^6 rows: wall time, CPU time and peak memory (bench/results/apply.json).

The table (Experiment III-like poses with references, 15 columns, ~285 MB) is generated
in a temporary folder, then `posecorr apply` runs as its own process on the shipped zhou
MLP (the C back end), so its peak resident memory is its own. The reference, timed in the
same run on the same file, is the floor of any CSV tool in Python: `csv.reader` reading
every row and `csv.writer` writing it back, nothing parsed; the goal of issue 14 is
under 30 s and under 300 MB on a quiet machine, so the load average is recorded too.
"""
from __future__ import annotations

import csv
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROWS = 1_000_000
HEADER = ("id,meas_x,meas_y,meas_z,meas_qw,meas_qx,meas_qy,meas_qz,"
          "ref_x,ref_y,ref_z,ref_qw,ref_qx,ref_qy,ref_qz")


def write_table(path: Path, rows: int, seed: int = 0) -> None:
    """Poses in Experiment III's 0.2 m cube, any orientation, references 1 cm away."""
    rng = np.random.default_rng(seed)
    with open(path, "w", encoding="utf-8") as handle:
        handle.write(HEADER + "\n")
        for start in range(0, rows, 100_000):
            n = min(100_000, rows - start)
            p = np.array([0.0, -0.6, 0.5]) + rng.uniform(-0.1, 0.1, (n, 3))
            q = rng.normal(size=(n, 4))
            q /= np.linalg.norm(q, axis=1, keepdims=True)
            block = np.concatenate([p, q, p + rng.normal(scale=0.01, size=(n, 3)), q], axis=1)
            handle.write("".join(f"{start + i}," + ",".join(map(repr, row)) + "\n"
                                 for i, row in enumerate(block.tolist())))


# `posecorr apply` as the command line runs it, then its own peak resident memory (VmHWM of
# its address space: ru_maxrss would also count the parent's pages it was forked with).
_RUNNER = """
import json, sys
from posecorr.cli import main
code = main(json.loads(sys.argv[1]))
with open("/proc/self/status") as status:
    print(next(line for line in status if line.startswith("VmHWM")), file=sys.stderr)
sys.exit(code)
"""


def _peak_kib(stderr: str) -> float:
    line = next(line for line in stderr.splitlines() if line.startswith("VmHWM"))
    return float(line.split()[1])


def csv_floor(source: Path, target: Path) -> float:
    """Seconds to read every row with csv.reader and write it back with csv.writer."""
    t0 = time.perf_counter()
    with open(source, newline="", encoding="utf-8") as fin, open(target, "w", newline="", encoding="utf-8") as fout:
        csv.writer(fout).writerows(csv.reader(fin))
    return time.perf_counter() - t0


def run(out_path: str | None = None, rows: int = ROWS, model: str | None = None) -> dict:
    from . import ROOT, latency_model

    model_path = Path(model) if model else latency_model()
    with tempfile.TemporaryDirectory(prefix="posecorr-bench-apply-") as tmp:
        table = Path(tmp) / "table.csv"
        write_table(table, rows)
        load_before = os.getloadavg()
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        argv = ["apply", str(model_path), str(table), "-o", str(Path(tmp) / "out.csv"), "--json"]
        proc = subprocess.run([sys.executable, "-c", _RUNNER, json.dumps(argv)], capture_output=True, text=True)
        wall = time.perf_counter() - t0
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        if proc.returncode != 0:
            raise RuntimeError(f"posecorr apply failed: {proc.stderr.strip()}")
        payload = json.loads(proc.stdout)
        floor = csv_floor(table, Path(tmp) / "floor.csv")
        load_after = os.getloadavg()
        result = {
            "rows": rows, "model": str(model_path.relative_to(ROOT)) if model_path.is_relative_to(ROOT)
            else str(model_path), "input_bytes": table.stat().st_size,
            "output_bytes": (Path(tmp) / "out.csv").stat().st_size,
            "apply_wall_s": wall,
            "apply_cpu_s": (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime),
            "apply_peak_rss_mb": _peak_kib(proc.stderr) / 1024.0,
            "csv_floor_wall_s": floor, "apply_over_csv_floor": wall / floor,
            "load_average_before": load_before, "load_average_after": load_after,
            "cpu_count": os.cpu_count(), "rows_checked": payload["n"],
            "goal": {"wall_s": 30, "peak_rss_mb": 300},
        }
    if out_path:
        Path(out_path).write_text(json.dumps(result, indent=2) + "\n")
    return result


if __name__ == "__main__":
    print(json.dumps(run(sys.argv[1] if len(sys.argv) > 1 else None), indent=2))

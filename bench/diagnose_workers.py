"""The diagnosis with its folds fitted side by side (`diagnose --workers`): wall time of
`diagnose` on 100, 300 and 600 poses of the paper's Experiment II (every catalogue effect
present: the longest searches) in one process and in two, alternating in one run, with the
load average; and whether the two give the same result to the last bit
(bench/results/diagnose_workers.json).

The speed goal is a ratio taken in the same run: two processes against one. A fold's fit is
independent of the others', but the search between the cross-validations (score tests,
Jacobians of the held-out poses) stays in the parent, and five folds share two processes
three rounds deep, so two processes can gain at most 5/3 on the folds' part.
"""
from __future__ import annotations

import json
import os
import time

import numpy as np

SIZES = (100, 300, 600)
ROUNDS = 2


def _table(n: int):
    from posecorr.simulate import simulate

    table = simulate(2, seed=0).table
    return table.subset(np.sort(np.random.default_rng(0).permutation(table.n)[:n]))


def _timed(table, workers: int) -> tuple[float, str]:
    from posecorr.analysis.diagnose import diagnose

    start = time.perf_counter()
    result = diagnose(table, [], folds=5, workers=workers)
    return time.perf_counter() - start, json.dumps(result, sort_keys=True, default=str)


def run(out_path: str | None = None, sizes: tuple[int, ...] = SIZES, rounds: int = ROUNDS) -> dict:
    rows = []
    for n in sizes:
        table = _table(n)
        seconds: dict[int, list[float]] = {1: [], 2: []}
        texts: dict[int, str] = {}
        loads = [os.getloadavg()[0]]
        for _ in range(rounds):
            for workers in (1, 2):
                wall, texts[workers] = _timed(table, workers)
                seconds[workers].append(round(wall, 2))
                loads.append(os.getloadavg()[0])
        best = {w: min(s) for w, s in seconds.items()}
        rows.append({"poses": n, "seconds_1_process": seconds[1], "seconds_2_processes": seconds[2],
                     "speedup_best": round(best[1] / best[2], 3), "identical": texts[1] == texts[2],
                     "load_average_1min": [round(x, 2) for x in loads]})
    result = {"cores": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
              "rounds": rounds, "rows": rows}
    if out_path:
        with open(out_path, "w") as f:
            json.dump(result, f, indent=2)
            f.write("\n")
    return result

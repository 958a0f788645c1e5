"""`pc_run` on one pose of the shipped zhou MLP against an earlier revision's, in one process.

Both libraries are built from source (the revision's `runtime_c/` by `git archive`, the
checkout's as it is) with the release build's flags, merged into one object each with their
global symbols renamed (`old_pc_run`, `new_pc_run`, ...), and linked into one program that
checks the two give the same bits on 1,024 poses and then times them in alternating rounds
(10 x 1,024 poses each). A host's noise then lands on both alike: the figure is the ratio
new / old per round (median and tail), with the load average.

`--co-runner BYTES` runs a `memcpy` loop of that many bytes on the other core meanwhile: on a
virtual machine whose cores share a physical core with another thread, this brings on the
episodes in which a pose that needs more instructions slows most (CHANGELOG.md, 2026-11-25).

    python -m bench.previous [--rev c654a8e] [--rounds 800] [--co-runner 8000]
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from . import ROOT, latency_model

HARNESS = r"""
#define _POSIX_C_SOURCE 199309L
#include <posecorr.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <time.h>
pc_status old_pc_load_file(const char *, const pc_options *, pc_model **, pc_error *);
pc_status new_pc_load_file(const char *, const pc_options *, pc_model **, pc_error *);
pc_status old_pc_run(pc_model *, const float *, size_t, float *);
pc_status new_pc_run(pc_model *, const float *, size_t, float *);
static double now_ns(void)
{
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return t.tv_sec * 1e9 + t.tv_nsec;
}
int main(int argc, char **argv)
{
    enum { P = 1024, REPS = 10 };
    static float in[P * 7], o1[7], o2[7];
    const int rounds = atoi(argv[2]);
    unsigned long s = 12345;
    pc_model *mo, *mn;
    pc_error e;
    int r, i, k;
    if (old_pc_load_file(argv[1], NULL, &mo, &e) != PC_OK ||
        new_pc_load_file(argv[1], NULL, &mn, &e) != PC_OK) {
        fprintf(stderr, "load failed: %s\n", e.message);
        return 2;
    }
    for (i = 0; i < P; i++) { /* positions near the middle of the training box, any rotation */
        double q[4], n = 0;
        for (k = 0; k < 7; k++) {
            double u;
            s = s * 6364136223846793005UL + 1442695040888963407UL;
            u = (double)((s >> 11) & 0xfffffffffffffUL) / 4503599627370496.0;
            if (k < 3)
                in[i * 7 + k] = (float)((k == 1 ? -0.6 : k == 2 ? 0.5 : 0.0) + 0.2 * u - 0.1);
            else
                q[k - 3] = 2 * u - 1;
        }
        for (k = 0; k < 4; k++)
            n += q[k] * q[k];
        for (k = 0; k < 4; k++)
            in[i * 7 + 3 + k] = (float)(q[k] / sqrt(n));
    }
    for (i = 0; i < P; i++) {
        if (old_pc_run(mo, in + i * 7, 1, o1) != PC_OK || new_pc_run(mn, in + i * 7, 1, o2) != PC_OK) {
            fprintf(stderr, "pose %d refused\n", i);
            return 2;
        }
        for (k = 0; k < 7; k++)
            if (o1[k] != o2[k]) {
                fprintf(stderr, "pose %d column %d: %.9g against %.9g\n", i, k, o1[k], o2[k]);
                return 3;
            }
    }
    for (r = 0; r < rounds; r++) {
        double t0 = now_ns(), t1, t2;
        for (k = 0; k < REPS; k++)
            for (i = 0; i < P; i++)
                old_pc_run(mo, in + i * 7, 1, o1);
        t1 = now_ns();
        for (k = 0; k < REPS; k++)
            for (i = 0; i < P; i++)
                new_pc_run(mn, in + i * 7, 1, o2);
        t2 = now_ns();
        printf("%.2f %.2f\n", (t1 - t0) / (REPS * P), (t2 - t1) / (REPS * P));
    }
    return 0;
}
"""

CO_RUNNER = r"""
#include <stdlib.h>
#include <string.h>
int main(int argc, char **argv)
{
    const size_t n = (size_t)atol(argv[1]);
    char *a = malloc(n), *b = malloc(n);
    memset(a, 1, n);
    for (;;) {
        memcpy(b, a, n);
        __asm__ volatile("" ::: "memory");
    }
}
"""


def _run(cmd: list[str], **kw) -> str:
    return subprocess.run(cmd, check=True, capture_output=True, text=True, **kw).stdout


def merged_object(tree: Path, prefix: str, work: Path) -> Path:
    """The library's objects built from tree/runtime_c (release flags), as one object whose
    defined globals carry `prefix`."""
    build = work / f"{prefix}build"
    _run(["cmake", "-S", str(tree / "runtime_c"), "-B", str(build), "-DCMAKE_BUILD_TYPE=Release",
          "-DPC_BUILD_TESTS=OFF", f"-DPython3_EXECUTABLE={sys.executable}"])
    _run(["cmake", "--build", str(build), "--target", "posecorr_obj", "--parallel", "2"])
    objects = sorted(str(p) for p in (build / "CMakeFiles" / "posecorr_obj.dir").glob("*.o"))
    merged = work / f"{prefix}merged.o"
    _run(["ld", "-r", "-o", str(merged), *objects])
    names = [line.split()[2] for line in _run(["nm", "--defined-only", "-g", str(merged)]).splitlines()
             if len(line.split()) == 3]
    table = work / f"{prefix}symbols"
    table.write_text("".join(f"{n} {prefix}{n}\n" for n in names))
    out = work / f"{prefix}lib.o"
    _run(["objcopy", f"--redefine-syms={table}", str(merged), str(out)])
    return out


def run(out: str | None = None, rev: str = "c654a8e", rounds: int = 800,
        co_runner: int = 0) -> dict:
    model = latency_model()
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        old_tree = work / "old"
        old_tree.mkdir()
        archive = subprocess.run(["git", "-C", str(ROOT), "archive", rev, "runtime_c",
                                  "export/operators.txt"], check=True, capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", str(old_tree)], input=archive, check=True)
        old = merged_object(old_tree, "old_", work)
        new = merged_object(ROOT, "new_", work)
        (work / "ab.c").write_text(HARNESS)
        cc = shutil.which("cc") or "gcc"
        _run([cc, "-O2", "-I", str(ROOT / "runtime_c"), str(work / "ab.c"), str(old), str(new),
              "-lm", "-o", str(work / "ab")])
        helper = None
        if co_runner:
            (work / "co.c").write_text(CO_RUNNER)
            _run([cc, "-O2", str(work / "co.c"), "-o", str(work / "co")])
            helper = subprocess.Popen([str(work / "co"), str(co_runner)])
            time.sleep(0.3)
        load_before = os.getloadavg()
        try:
            done = subprocess.run([str(work / "ab"), str(model), str(rounds)], capture_output=True,
                                  text=True)
        finally:
            if helper:
                helper.kill()
                helper.wait()
        load_after = os.getloadavg()
    if done.returncode:
        raise SystemExit(f"the two libraries differ or failed on {model.name}: {done.stderr.strip()}")
    text = done.stdout
    times = np.array([[float(v) for v in line.split()] for line in text.splitlines()])
    ratio = times[:, 1] / times[:, 0]
    result = {
        "model": model.name,
        "previous_revision": rev,
        "rounds": rounds,
        "poses_per_round": 10 * 1024,
        "co_runner_memcpy_bytes": co_runner,
        "bit_identical_poses": 1024,
        "previous_median_ns": round(float(np.median(times[:, 0])), 1),
        "current_median_ns": round(float(np.median(times[:, 1])), 1),
        "ratio_current_over_previous": {f"p{q}": round(float(np.percentile(ratio, q)), 3)
                                        for q in (10, 50, 90, 99)},
        "load_average_before_after": [round(load_before[0], 2), round(load_after[0], 2)],
    }
    if out:
        Path(out).write_text(json.dumps(result, indent=2) + "\n")
    return result


def both(out: str) -> dict:
    """`make bench`: quiet, then with an 8 KB memcpy on the other core; one JSON file."""
    result = {"quiet": run(), "co_runner": run(co_runner=8000)}
    Path(out).write_text(json.dumps(result, indent=2) + "\n")
    return result


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.previous", description=__doc__.splitlines()[0])
    ap.add_argument("--rev", default="c654a8e", help="the earlier revision (git)")
    ap.add_argument("--rounds", type=int, default=800)
    ap.add_argument("--co-runner", type=int, default=0, metavar="BYTES")
    ap.add_argument("-o", "--output", help="JSON file (default: print only)")
    args = ap.parse_args(argv)
    print(json.dumps(run(args.output, args.rev, args.rounds, args.co_runner), indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())

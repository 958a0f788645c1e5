"""Every table-1 zhou tansig MLP, the 10-10 and 20-20 MLPs of quat (tansig), eaa (radbas) and
R (logsig), and networks of widths outside table 1, against the hand-written floor, by
instructions and by time.

For each of table 1's 16 architectures of zhou, and 10-10 and 20-20 of the other
representations with the paper's activation for each (the shipped files where there is one,
the others exported by the project's exporter after two epochs from a simulated Experiment III:
the weights do not change the work of a pose), `floor/gen_hand.py` writes a hand-written AVX2
function of the same network (same weights, activation formulas and summation order, the
representation's encode/decode, no FMA: pc_run's bits, `max_abs_diff`). Then:

* instructions a pose (valgrind's callgrind over 1,024 poses, `floor/floor.c MODEL pc|hand`)
  of `pc_run` built from the checkout and from an earlier revision (`--rev`, default
  a4423e5: before the layers were specialised by shape class), and of the hand function.
  A host shared with other work does not change these counts;
* time a pose, `pc_run` against the hand function in alternating rounds in one process
  (`floor/floor.c`, median of 41 rounds), `--runs` times, with the load average: the ratio
  is what the issue's figure quotes; on a busy host it is noise-bound;
* what each step of a pose runs (`Corrector.step_paths`).

    python -m bench.floor_all [--rev a4423e5] [--rev-outside d577528] [--runs 3] [-o bench/results/floor_all.json]
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

from . import RESULTS, ROOT, cpu

HERE = Path(__file__).resolve().parent / "floor"
# issue 33: pc_run within 1.2x of the hand-written floor for every table-1 architecture
GOAL_RATIO = 1.2
# issue 33: beside zhou, these architectures of the paper's other representations, each with
# its activation in the paper
OTHERS = {"quat": "tansig", "eaa": "radbas", "R": "logsig"}
OTHER_HIDDEN = ((10, 10), (20, 20))
# Networks of widths outside table 1 (no kernel of their K and N: the general layer, K and N
# read at run time), labelled "outside-...": one unit, odd widths, past 32 and past 64
# outputs, and the other activations; against the revision before such layers left the
# one-pose programs (`--rev-outside`), where their multiply-adds ran in the interpreter.
OUTSIDE = (("zhou", "tansig", (1,)), ("zhou", "tansig", (7, 7)), ("zhou", "tansig", (12, 12, 12)),
           ("zhou", "tansig", (33, 33)), ("zhou", "tansig", (48, 48)), ("zhou", "tansig", (70,)),
           ("quat", "tansig", (12, 12)), ("eaa", "radbas", (12, 12)), ("R", "logsig", (12, 12)))


def _run(cmd: list[str], **kw) -> str:
    return subprocess.run(cmd, check=True, capture_output=True, text=True, **kw).stdout


def build_library(tree: Path, build: Path) -> Path:
    """libposecorr.so built from tree/runtime_c with the release flags; its folder."""
    _run(["cmake", "-S", str(tree / "runtime_c"), "-B", str(build), "-DCMAKE_BUILD_TYPE=Release",
          "-DPC_BUILD_TESTS=OFF", f"-DPython3_EXECUTABLE={sys.executable}"])
    _run(["cmake", "--build", str(build), "--target", "posecorr", "--parallel", "2"])
    return build


def revision_tree(rev: str, work: Path) -> Path:
    tree = work / f"rev-{rev}"
    tree.mkdir()
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", rev, "runtime_c", "export/operators.txt"],
                             check=True, capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(tree)], input=archive, check=True)
    return tree


def _shipped(rep: str, activation: str, hidden: tuple[int, ...]) -> Path | None:
    name = f"mlp-{rep}-{activation}-{'x'.join(map(str, hidden))}-"
    return next((p for p in sorted((ROOT / "models").glob("mlp-*.onnx")) if p.stem.startswith(name)), None)


def export_models(work: Path) -> dict[str, Path]:
    """label -> an MLP: "10-10" for zhou tansig (every table-1 architecture), "quat-10-10"
    for the others (OTHERS, OTHER_HIDDEN); the shipped file where there is one, else
    tools/models.py's unshipped recipe."""
    from posecorr.train.spec import ARCHITECTURES
    from tools.models import unshipped_mlp

    wanted = [("zhou", "tansig", hidden, "-".join(map(str, hidden))) for hidden in ARCHITECTURES]
    wanted += [(rep, act, hidden, f"{rep}-" + "-".join(map(str, hidden)))
               for rep, act in OTHERS.items() for hidden in OTHER_HIDDEN]
    wanted += [(rep, act, hidden, f"outside-{rep}-" + "-".join(map(str, hidden)))
               for rep, act, hidden in OUTSIDE]
    return {label: _shipped(rep, act, hidden) or unshipped_mlp(rep, hidden, work / f"{label}.onnx", act, rows=200)
            for rep, act, hidden, label in wanted}


def instructions(exe: Path, model: Path, which: str) -> float:
    """Instructions a pose of run_pc or run_hand in floor.c (callgrind)."""
    out = exe.parent / f"callgrind.{exe.name}.{which}"
    subprocess.run(["valgrind", "--tool=callgrind", f"--callgrind-out-file={out}",
                    f"--toggle-collect=run_{which}", str(exe), str(model), which],
                   check=True, capture_output=True)
    for line in out.read_text().splitlines():
        if line.startswith("summary:") or line.startswith("totals:"):
            return round(int(line.split()[1]) / 1024.0, 1)
    raise SystemExit(f"no totals in {out}")


def one_model(model: Path, libs: dict[str, Path], work: Path, runs: int) -> dict:
    from posecorr.controller.runtime import Corrector

    cc = shutil.which("cc") or "gcc"
    d = work / model.stem
    d.mkdir()
    _run([sys.executable, str(HERE / "gen_hand.py"), str(model), str(d)])
    row: dict = {"model": model.name}
    valgrind = shutil.which("valgrind")
    for name, lib in libs.items():
        # -mavx2, not -march=native: valgrind decodes no AVX-512
        exe = d / f"count-{name}"
        _run([cc, "-O2", "-mavx2", f"-I{ROOT / 'runtime_c'}", f"-I{HERE}", str(HERE / "floor.c"),
              str(d / "hand_any.c"), f"-L{lib}", f"-Wl,-rpath,{lib}", "-lposecorr", "-lm", "-o", str(exe)])
        if valgrind:
            row[f"pc_run_instructions_{name}"] = instructions(exe, model, "pc")
            if name == "current":
                row["hand_instructions"] = instructions(exe, model, "hand")
    if valgrind:
        for name in libs:
            ratio = row[f"pc_run_instructions_{name}"] / row["hand_instructions"]
            row[f"instruction_ratio_{name}"] = round(ratio, 3)
    exe = d / "floor"
    lib = libs["current"]
    _run([cc, "-O2", "-march=native", f"-I{ROOT / 'runtime_c'}", f"-I{HERE}", str(HERE / "floor.c"),
          str(d / "hand_any.c"), f"-L{lib}", f"-Wl,-rpath,{lib}", "-lposecorr", "-lm", "-o", str(exe)])
    row["time_runs"] = []
    for _ in range(runs):
        load = os.getloadavg()[0]
        text = _run([str(exe), str(model)]).split()
        # "pc_run X ns, hand Y ns, max|diff| D, ratio R"
        row["time_runs"].append({"pc_run_ns": float(text[1]), "hand_ns": float(text[4]),
                                 "ratio": float(text[-1]), "load_average": round(load, 2)})
        # the largest difference of the outputs on 1,024 poses: 0 when the function is the
        # same network computed the same way (a wrong one shows here)
        row["max_abs_diff"] = float(text[7].rstrip(","))
    # the run of median ratio, as the issue quotes it (median of the runs, its load average)
    row["median_run"] = sorted(row["time_runs"], key=lambda r: r["ratio"])[len(row["time_runs"]) // 2]
    row["within_goal"] = "yes" if row["median_run"]["ratio"] <= GOAL_RATIO else "no"
    paths = Corrector(model, library=str(lib / "libposecorr.so")).step_paths()
    row["step_paths"] = [f"{p}: {why}" for p, why in paths]
    return row


def run(out: str | None = None, rev: str = "a4423e5", runs: int = 3,
        rev_outside: str = "d577528") -> dict:
    from tqdm import tqdm

    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        current = build_library(ROOT, work / "build-current")
        libs = {"current": current, "previous": build_library(revision_tree(rev, work), work / "build-previous")}
        libs_outside = {"current": current,
                        "previous": build_library(revision_tree(rev_outside, work), work / "build-outside")}
        models = export_models(work)
        rows = {label: one_model(path, libs_outside if label.startswith("outside-") else libs, work, runs)
                for label, path in tqdm(models.items(), desc="floor", unit="network")}
    def met(group: str) -> str:
        some = [row for label, row in rows.items()
                if group == ("outside" if label.startswith("outside-") else
                             "others" if label.split("-")[0] in OTHERS else "zhou")]
        return f"{sum(row['within_goal'] == 'yes' for row in some)} of {len(some)}"
    result = {"cpu": cpu(), "previous_revision": rev, "previous_revision_outside": rev_outside, "goal_ratio": GOAL_RATIO,
              "within_goal": met("zhou"), "within_goal_others": met("others"),
              "within_goal_outside": met("outside"),
              "unit_instructions": "per pose (callgrind, 1,024 poses)",
              "unit_time": "ns per pose, median of 41 rounds (floor.c)", "networks": rows}
    if out:
        from posecorr.safeio import atomic_output

        with atomic_output(out) as f:
            f.write(json.dumps(result, indent=2) + "\n")
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.floor_all", description=__doc__.splitlines()[0])
    parser.add_argument("--rev", default="a4423e5", help="earlier revision for the 'previous' counts")
    parser.add_argument("--rev-outside", default="d577528",
                        help="earlier revision for the 'previous' counts of the outside-table-1 networks")
    parser.add_argument("--runs", type=int, default=3, help="timed runs per network")
    parser.add_argument("-o", "--out", default=str(RESULTS / "floor_all.json"))
    args = parser.parse_args(argv)
    print(json.dumps(run(args.out, args.rev, args.runs, args.rev_outside), indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())

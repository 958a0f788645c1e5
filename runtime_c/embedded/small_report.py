"""What `make embedded` prints for the small boards (small.c and compiled.c under QEMU with
-icount shift=0): per board, RAM (.data, .bss with the static arena, the arena the model
keeps, stack peak of the reserved stack), flash (the firmware's text and read-only data, the
model), instructions per pose of each implementation and their ratios (a compiled function's
also to the other boards' implementations of its model), and the match with the x86 runtime.

    python small_report.py --size arm-none-eabi-size --json OUT.json \\
        --board 16 small16.log small16.elf MODEL.onnx [--board 32 ...]

With --networks FOLDER NAME ..., the networks table instead (Makefile: networks): per
network, pc_run on the 32 KB board and, where the model loads there, on the 16 KB one (both
at program_ops 512: the whole programs run compiled), and the
compiled, hand-written and emlearn functions each on a 2 KB board, their instructions a
pose, RAM, and ratios to the hand-written function and to emlearn (the goal:
<= FLOOR_RATIO and <= 1); --json writes the table.

Exit status 1 when a board's firmware did not finish, called malloc, or a pc_run, compiled
or hand-written output differs from the x86 runtime (posecorr.Corrector, backend "c") in any
bit (the hand-written function is the same arithmetic), or emlearn's (its own summation
order and libm's tanhf) by more than TOLERANCE.
"""
from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np

TOLERANCE = 1e-5
OUT = re.compile(r"^out (\w+) (\d+)((?: [0-9a-f]{8}){7})$")
KV = re.compile(r"(\w+)=(\d+)")


def parse(text: str) -> dict:
    poses: dict[str, dict[int, np.ndarray]] = {}
    counts: dict[str, int] = {}
    figures: dict[str, int] = {}
    for line in text.splitlines():
        if m := OUT.match(line):
            bits = np.array([int(h, 16) for h in m.group(3).split()], dtype=np.uint32)
            poses.setdefault(m.group(1), {})[int(m.group(2))] = bits.view(np.float32)
        elif line.startswith("count "):
            counts[line.split()[1]] = int(KV.search(line).group(2))
        elif line.startswith(("load ok", "mallocs=", "calibration")):
            figures.update({k: int(v) for k, v in KV.findall(line)})
    arrays = {k: np.stack([v[i] for i in sorted(v)]) for k, v in poses.items()}
    return {"poses": arrays, "instructions_per_pose": counts, "figures": figures}


def sections(elf: Path, size_tool: str) -> dict[str, int]:
    out = subprocess.run([size_tool, "-A", str(elf)], check=True, capture_output=True,
                         text=True).stdout
    rows = (ln.split() for ln in out.splitlines())
    return {r[0]: int(r[1]) for r in rows if len(r) == 3 and r[0].startswith(".")}


# The implementations a firmware may run: those that must give the x86 runtime's bits
# (every one is compared with it), and those also compared with pc_run on the target.
EXACT = ("pc_run", "compiled", "reference")
CLOSE = ("reference", "emlearn")
# The goal for a build on the M4: instructions a pose within 1.3x the hand-written
# function's, and at or below emlearn's.
FLOOR_RATIO = 1.3


def _match(run: dict, x86: np.ndarray) -> dict:
    x = run["poses"]["input"]
    match: dict = {"poses": int(len(x))}
    for impl in run["poses"]:
        if impl != "input":
            got = run["poses"][impl]
            match[f"{impl}_identical_poses"] = int(np.sum(np.all(got.view(np.uint32) == x86.view(np.uint32), axis=1)))
            match[f"{impl}_max_abs_diff"] = float(np.max(np.abs(got.astype(np.float64) - x86)))
    for impl in CLOSE:
        if impl in run["poses"] and "pc_run" in run["poses"]:
            match[f"{impl}_max_abs_diff_to_pc_run"] = float(
                np.max(np.abs(run["poses"][impl].astype(np.float64) - run["poses"]["pc_run"])))
    return match


def board_report(kb: int, log: Path, elf: Path, model: Path, size_tool: str) -> dict:
    from posecorr import Corrector

    run = parse(log.read_text())
    sec = sections(elf, size_tool)
    x = run["poses"]["input"]
    x86 = Corrector(model, backend="c").correct(x.astype(np.float64)).astype(np.float32)
    f = run["figures"]
    ram = {".data": sec.get(".data", 0), ".bss": sec.get(".bss", 0),
           "arena_reserved": f.get("arena_reserved", 0), "arena_used": f.get("arena_used", 0),
           "stack_reserved": f.get("stack_reserved", 0), "stack_peak": f.get("stack_peak", 0)}
    ram["total"] = ram[".data"] + ram[".bss"] + ram["stack_reserved"]
    counts = run["instructions_per_pose"]
    main_impl = next((k for k in EXACT if k in counts), next(iter(counts)))
    ratios = {f"{main_impl}/{k}": round(counts[main_impl] / v, 3) for k, v in counts.items() if k != main_impl}
    return {"board_ram_kb": kb, "model": model.name, "model_bytes": model.stat().st_size,
            "flash": {"text": sec.get(".text", 0), "rodata (model included)": sec.get(".rodata", 0)},
            "ram": ram, "steps": f.get("steps"), "program_ops": f.get("program_ops"),
            "mallocs": f.get("mallocs"), "instructions_per_pose": counts, "ratios": ratios,
            "instructions_per_systick_tick": f.get("instructions_per_tick_x1000", 0) / 1000,
            "match": _match(run, x86)}


def compare_across_boards(reports: list[dict]) -> None:
    """A compiled function's instruction ratios to the other boards' implementations of
    the same model (each counted on its own board, under the same QEMU clock)."""
    for r in reports:
        if "compiled" not in r["instructions_per_pose"]:
            continue
        mine = r["instructions_per_pose"]["compiled"]
        for other in reports:
            if other is not r and other["model"] == r["model"]:
                for impl, v in other["instructions_per_pose"].items():
                    r["ratios"][f"compiled/{impl} ({other['board_ram_kb']} KB board)"] = round(mine / v, 3)


def print_board(r: dict) -> None:
    kb, ram, m, c = r["board_ram_kb"], r["ram"], r["match"], r["instructions_per_pose"]
    if "pc_run" in c:
        print(f"\n{kb} KB board (linker script: RAM {kb} KB, stack included), {r['model']}, "
              f"max_batch 1, program_ops {r['program_ops']}, {r['steps']} steps per pose:")
        print(f"  RAM: .data {ram['.data']} B + .bss {ram['.bss']} B (static arena "
              f"{ram['arena_reserved']} B, the model keeps {ram['arena_used']} B) + stack "
              f"{ram['stack_reserved']} B (peak {ram['stack_peak']} B) = {ram['total']} B "
              f"of {kb * 1024}; malloc calls during load and run: {r['mallocs']}")
        print(f"  flash: text {r['flash']['text']} B, read-only data "
              f"{r['flash']['rodata (model included)']} B (the model {r['model_bytes']} B, read in place)")
    else:
        print(f"\n{kb} KB board (linker script: RAM {kb} KB, stack included), {r['model']} "
              "compiled to C by `posecorr compile`, no runtime:")
        print(f"  RAM: .data {ram['.data']} B + .bss {ram['.bss']} B + stack "
              f"{ram['stack_reserved']} B (peak {ram['stack_peak']} B) = {ram['total']} B "
              f"of {kb * 1024}; malloc calls: {r['mallocs']}")
        print(f"  flash: text {r['flash']['text']} B, read-only data "
              f"{r['flash']['rodata (model included)']} B (the weights)")
    print("  instructions per pose (qemu -icount shift=0, SysTick at "
          f"{r['instructions_per_systick_tick']:g} instructions per tick): "
          + ", ".join(f"{k} {v}" for k, v in c.items())
          + ("; " + ", ".join(f"{k} {v}" for k, v in r["ratios"].items()) if r["ratios"] else ""))
    exact = "; ".join(f"{k} bit-identical on {m[k + '_identical_poses']}/{m['poses']} poses "
                      f"(max |diff| {m[k + '_max_abs_diff']:.2g})" for k in EXACT if k + "_identical_poses" in m)
    extra = "".join(f"; {k.removesuffix('_max_abs_diff_to_pc_run')} vs pc_run max |diff| {v:.2g}"
                    for k, v in m.items() if k.endswith("_to_pc_run"))
    print(f"  match with x86 pc_run: {exact}{extra}")


def board_ok(r: dict) -> bool:
    m = r["match"]
    return (r["mallocs"] == 0 and r["ram"]["total"] <= r["board_ram_kb"] * 1024
            and all(m[f"{k}_identical_poses"] == m["poses"] for k in EXACT if f"{k}_identical_poses" in m)
            and m.get("reference_max_abs_diff_to_pc_run", 0.0) <= TOLERANCE
            and m.get("emlearn_max_abs_diff", 0.0) <= TOLERANCE)


# ---- the networks table: each network's builds (Makefile: networks) --------------------

# build (its log and elf in the network's folder) -> (implementation in the log, key in the
# row, board RAM in KB); pc_run runs on the 32 KB board, and on the 16 KB one where the model
# loads there (Makefile: PC16_NETWORKS)
NETWORK_BUILDS = {"pc32": ("pc_run", "pc_run", 32), "pc16": ("pc_run", "pc_run_16kb", 16),
                  "compiled2": ("compiled", "compiled", 2),
                  "reference2": ("reference", "reference", 2), "emlearn2": ("emlearn", "emlearn", 2)}
# the builds held to the goal, as the table prints them
FLOOR_BUILDS = {"pc_run": "pc_run 32 KB", "pc_run_16kb": "pc_run 16 KB", "compiled": "compiled"}


def network_row(folder: Path, size_tool: str) -> tuple[dict, list[dict]]:
    """One network's row (instructions and RAM of each build, the goal's ratios) and the
    board reports it comes from."""
    import onnx

    model = folder / "model.onnx"
    meta = {p.key: p.value for p in onnx.load(str(model), load_external_data=False).metadata_props}
    boards, row = [], {"network": folder.name, "representation": meta.get("representation"),
                       "architecture": meta.get("architecture"),
                       "parameters": int(meta.get("n_parameters", 0))}
    for build, (impl, key, kb) in NETWORK_BUILDS.items():
        if not (folder / f"{build}.log").exists() and build == "pc16":
            continue
        b = board_report(kb, folder / f"{build}.log", folder / f"{build}.elf", model, size_tool)
        ram = b["ram"]
        row[key] = {"board_ram_kb": kb, "instructions_per_pose": b["instructions_per_pose"][impl],
                    "ram_used": ram[".data"] + ram[".bss"] + ram["stack_peak"],
                    "ram_reserved": ram["total"], "arena_used": ram["arena_used"],
                    "identical_poses": b["match"][f"{impl}_identical_poses"],
                    "max_abs_diff_to_x86": b["match"][f"{impl}_max_abs_diff"]}
        if impl == "pc_run":
            row[key].update({"program_ops": b["program_ops"], "steps": b["steps"],
                             "arena_reserved": ram["arena_reserved"],
                             "flash_text": b["flash"]["text"]})
        boards.append(b)
    hand, eml = row["reference"]["instructions_per_pose"], row["emlearn"]["instructions_per_pose"]
    for key in FLOOR_BUILDS:
        if key in row:
            mine = row[key]["instructions_per_pose"]
            row[key].update({"over_hand": round(mine / hand, 3), "over_emlearn": round(mine / eml, 3),
                             "meets_floor": mine <= FLOOR_RATIO * hand and mine <= eml})
    return row, boards


def print_networks(rows: dict[str, dict]) -> None:
    print("\nM4 instructions a pose (qemu -icount shift=0) / RAM used (.data + .bss + stack peak), "
          "each build on its own board; ratio to the hand-written function, <= 1.3 and "
          "<= emlearn is the goal:")
    print(f"  {'network':<20}{'pc_run 32 KB':>18}{'pc_run 16 KB':>18}{'compiled 2 KB':>18}"
          f"{'hand 2 KB':>18}{'emlearn 2 KB':>18}   "
          + "  ".join(f"{label + '/hand':>15}" for label in FLOOR_BUILDS.values()))
    for name, r in rows.items():
        cells = "".join((f"{r[i]['instructions_per_pose']:>6} / {r[i]['ram_used']:>5} B" if i in r
                         else "does not load").rjust(18)
                        for i in ("pc_run", "pc_run_16kb", "compiled", "reference", "emlearn"))
        verdict = "".join((f"{r[i]['over_hand']:>11.2f} {'ok' if r[i]['meets_floor'] else 'no':<3}"
                           if i in r else f"{'-':>11}    ") + "  " for i in FLOOR_BUILDS)
        print(f"  {r['representation'] + ' ' + r['architecture']:<20}{cells}   {verdict.rstrip()}")
    print("  bits against x86 pc_run: " + "; ".join(
        f"{r['representation']} {r['architecture']}: "
        + ", ".join(f"{i} {r[i]['identical_poses']}/16" for i in ("pc_run", "pc_run_16kb", "compiled", "reference")
                    if i in r)
        + f", emlearn max |diff| {r['emlearn']['max_abs_diff_to_x86']:.2g}" for r in rows.values()))


def networks_main(args) -> int:
    rows, ok = {}, True
    for name in args.names:
        row, boards = network_row(args.networks / name, args.size)
        rows[name] = row
        ok &= all(board_ok(b) for b in boards)
    print_networks(rows)
    if args.json:
        from posecorr.safeio import write_text

        write_text(args.json, json.dumps({"command": "make embedded", "networks": rows}, indent=2) + "\n")
    return 0 if ok else 1


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="arm-none-eabi-size")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--board", nargs=4, action="append",
                    metavar=("KB", "LOG", "ELF", "MODEL"))
    ap.add_argument("--networks", type=Path, help="the networks' folder (then NAME ...)")
    ap.add_argument("names", nargs="*")
    args = ap.parse_args(argv)
    if args.networks:
        return networks_main(args)
    if not args.board:
        ap.error("--board or --networks is required")
    reports = [board_report(int(kb), Path(log), Path(elf), Path(model), args.size)
               for kb, log, elf, model in args.board]
    compare_across_boards(reports)
    for r in reports:
        print_board(r)
    ok = all(board_ok(r) for r in reports)
    if args.json:
        args.json.write_text(json.dumps(reports, indent=2) + "\n")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())

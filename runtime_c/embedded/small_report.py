"""What `make embedded` prints for the small boards (small.c under QEMU with -icount shift=0):
per board, RAM (.data, .bss with the static arena, the arena the model keeps, stack peak of
the reserved stack), flash (the firmware's text and read-only data, the model), instructions
per pose of each implementation and their ratios, and the match with the x86 runtime.

    python small_report.py --size arm-none-eabi-size --json OUT.json \\
        --board 16 small16.log small16.elf MODEL.onnx [--board 32 ...]

Exit status 1 when a board's firmware did not finish, called malloc, or a pc_run output
differs from the x86 runtime (posecorr.Corrector, backend "c") in any bit; the hand-written
function must match pc_run within TOLERANCE (it is the same arithmetic, so it matches
exactly), and emlearn's difference (its own summation order and libm's tanhf) is reported.
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


def board_report(kb: int, log: Path, elf: Path, model: Path, size_tool: str) -> dict:
    from posecorr import Corrector

    run = parse(log.read_text())
    sec = sections(elf, size_tool)
    x = run["poses"]["input"]
    x86 = Corrector(model, backend="c").correct(x.astype(np.float64)).astype(np.float32)
    got = run["poses"]["pc_run"]
    match = {"pc_run_identical_poses": int(np.sum(np.all(got.view(np.uint32) == x86.view(np.uint32), axis=1))),
             "poses": int(len(x)),
             "pc_run_max_abs_diff": float(np.max(np.abs(got.astype(np.float64) - x86)))}
    for impl in ("reference", "emlearn"):
        if impl in run["poses"]:
            match[f"{impl}_max_abs_diff_to_pc_run"] = float(
                np.max(np.abs(run["poses"][impl].astype(np.float64) - got)))
    f = run["figures"]
    ram = {".data": sec.get(".data", 0), ".bss": sec.get(".bss", 0),
           "arena_reserved": f.get("arena_reserved", 0), "arena_used": f.get("arena_used", 0),
           "stack_reserved": f.get("stack_reserved", 0), "stack_peak": f.get("stack_peak", 0)}
    ram["total"] = ram[".data"] + ram[".bss"] + ram["stack_reserved"]
    counts = run["instructions_per_pose"]
    ratios = {f"pc_run/{k}": round(counts["pc_run"] / v, 3) for k, v in counts.items() if k != "pc_run"}
    return {"board_ram_kb": kb, "model": model.name, "model_bytes": model.stat().st_size,
            "flash": {"text": sec.get(".text", 0), "rodata (model included)": sec.get(".rodata", 0)},
            "ram": ram, "steps": f.get("steps"), "program_ops": f.get("program_ops"),
            "mallocs": f.get("mallocs"), "instructions_per_pose": counts, "ratios": ratios,
            "instructions_per_systick_tick": f.get("instructions_per_tick_x1000", 0) / 1000,
            "match": match}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="arm-none-eabi-size")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--board", nargs=4, action="append", required=True,
                    metavar=("KB", "LOG", "ELF", "MODEL"))
    args = ap.parse_args(argv)
    reports, ok = [], True
    for kb, log, elf, model in args.board:
        r = board_report(int(kb), Path(log), Path(elf), Path(model), args.size)
        reports.append(r)
        ram, m, c = r["ram"], r["match"], r["instructions_per_pose"]
        print(f"\n{kb} KB board (linker script: RAM {kb} KB, stack included), {r['model']}, "
              f"max_batch 1, program_ops {r['program_ops']}, {r['steps']} steps per pose:")
        print(f"  RAM: .data {ram['.data']} B + .bss {ram['.bss']} B (static arena "
              f"{ram['arena_reserved']} B, the model keeps {ram['arena_used']} B) + stack "
              f"{ram['stack_reserved']} B (peak {ram['stack_peak']} B) = {ram['total']} B "
              f"of {int(kb) * 1024}; malloc calls during load and run: {r['mallocs']}")
        print(f"  flash: text {r['flash']['text']} B, read-only data "
              f"{r['flash']['rodata (model included)']} B (the model {r['model_bytes']} B, read in place)")
        print("  instructions per pose (qemu -icount shift=0, SysTick at "
              f"{r['instructions_per_systick_tick']:g} instructions per tick): "
              + ", ".join(f"{k} {v}" for k, v in c.items())
              + ("; " + ", ".join(f"{k} {v}" for k, v in r["ratios"].items()) if r["ratios"] else ""))
        extra = "".join(f"; {k.removesuffix('_max_abs_diff_to_pc_run')} vs pc_run max |diff| {v:.2g}"
                        for k, v in m.items() if k.endswith("_to_pc_run"))
        print(f"  match with x86: pc_run bit-identical on {m['pc_run_identical_poses']}/{m['poses']} "
              f"poses (max |diff| {m['pc_run_max_abs_diff']:.2g}){extra}")
        ok &= (r["mallocs"] == 0 and m["pc_run_identical_poses"] == m["poses"]
               and m.get("reference_max_abs_diff_to_pc_run", 0.0) <= TOLERANCE
               and ram["total"] <= int(kb) * 1024)
    if args.json:
        args.json.write_text(json.dumps(reports, indent=2) + "\n")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())

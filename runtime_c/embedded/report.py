"""What `make embedded` prints: the QEMU run compared with the x86 runtime, and the
firmware's flash and RAM by origin (runtime, model, firmware, C library) from the map file.

    python report.py --log qemu.log --model MODEL.onnx --elf firmware.elf --map firmware.map

Exit status 1 when the firmware did not finish cleanly or an output differs from the x86
runtime (posecorr.Corrector, backend "c") by more than TOLERANCE.
"""
from __future__ import annotations

import argparse
import re
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

TOLERANCE = 1e-5
POSE_WIDTH = 7

# Output sections by where they live on a microcontroller. .data is in both: its initial
# values are stored in flash and copied to RAM at reset.
FLASH_CODE = (".isr_vector", ".text", ".ARM.extab", ".ARM.exidx", ".preinit_array",
              ".init_array", ".fini_array")
FLASH_RODATA = (".rodata",)
RAM_DATA = (".data",)
RAM_BSS = (".bss",)
RAM_ARENA = (".arena",)  # the caller's buffer of pc_load_into
SECTIONS = FLASH_CODE + FLASH_RODATA + RAM_DATA + RAM_BSS + RAM_ARENA

# Origin of an input section, by the file the map names (first match wins).
ORIGINS = (
    ("runtime", re.compile(r"libposecorr\.a\(")),
    ("model", re.compile(r"model_data\.o$")),
    ("firmware", re.compile(r"(main|startup)\.o$")),
    ("C library", re.compile(r"lib(c|m|g|gcc|nosys)(_nano)?\.a\(|crt\w*\.o$")),
)
COLUMNS = ("runtime", "model", "firmware", "C library", "alignment")


# ---- QEMU output --------------------------------------------------------------------

POSE_LINE = re.compile(r"^pose (\d+) in((?: [0-9a-f]{8}){7}) out((?: [0-9a-f]{8}){7})$")
KEY_VALUE = re.compile(r"(\w+)=(\d+)")


@dataclass
class FirmwareRun:
    inputs: np.ndarray
    outputs: np.ndarray
    figures: dict[str, int]
    lines: list[str] = field(repr=False)

    @property
    def api(self) -> str:
        """The load entry point the firmware used."""
        return next((ln.split()[1] for ln in self.lines if ln.startswith("api: ")), "")

    @property
    def truncated_message(self) -> str:
        """The status name and message of the firmware's load of half the model."""
        return next((ln.split(": ", 1)[1] for ln in self.lines if ln.startswith("truncated: ")), "")

    @property
    def finished(self) -> bool:
        n = len(self.inputs)
        return (f"done: {n}/{n} poses ok" in self.lines
                and "batch: identical to single-pose runs" in self.lines)


def hex_floats(text: str) -> np.ndarray:
    return np.array([int(h, 16) for h in text.split()], dtype=np.uint32).view(np.float32)


def parse_log(text: str) -> FirmwareRun:
    lines = text.splitlines()
    ins, outs, figures = [], [], {}
    for line in lines:
        m = POSE_LINE.match(line)
        if m:
            ins.append(hex_floats(m.group(2)))
            outs.append(hex_floats(m.group(3)))
        elif line.startswith(("api:", "load: ok", "heap:", "memory:", "arena:")):
            figures.update({k: int(v) for k, v in KEY_VALUE.findall(line)})
    shape = (len(ins), POSE_WIDTH)
    return FirmwareRun(np.array(ins, np.float32).reshape(shape),
                       np.array(outs, np.float32).reshape(shape), figures, lines)


# ---- map file -----------------------------------------------------------------------

INPUT_ONE_LINE = re.compile(r"^ (\S+)\s+0x([0-9a-f]+)\s+0x([0-9a-f]+)\s*(.*)$")
INPUT_CONTINUED = re.compile(r"^\s+0x([0-9a-f]+)\s+0x([0-9a-f]+)\s+(\S.*)$")
OUTPUT_SECTION = re.compile(r"^(\.\S+)(?:\s+0x([0-9a-f]+)\s+0x([0-9a-f]+))?")


def origin(path: str, name: str) -> str:
    if name == "*fill*":
        return "alignment"
    for label, pattern in ORIGINS:
        if pattern.search(path):
            return label
    return "other"


def map_sizes(text: str) -> dict[str, dict[str, int]]:
    """{output section: {origin: bytes}} of the allocated sections of a GNU ld map.

    Each input section owns the bytes from its address to the next one's (the last to the
    end of its output section): the sizes the map prints for merged string sections are
    those before merging, the addresses are where the bytes really are.
    """
    body = text.split("Linker script and memory map", 1)[1]
    starts: dict[str, list[tuple[int, str]]] = {}
    ends: dict[str, int] = {}
    current = None
    pending = None  # an input section whose address and size are on the next line
    for line in body.splitlines():
        if not line.strip():
            continue
        if not line.startswith(" "):
            m = OUTPUT_SECTION.match(line)
            current = m.group(1) if m and m.group(1) in SECTIONS and m.group(2) else None
            if current:
                ends[current] = int(m.group(2), 16) + int(m.group(3), 16)
            pending = None
            continue
        if current is None:
            continue
        m = INPUT_ONE_LINE.match(line)
        if m and not m.group(1).startswith("0x"):
            name, addr, size, path = m.group(1), int(m.group(2), 16), int(m.group(3), 16), m.group(4)
        elif pending and (c := INPUT_CONTINUED.match(line)):
            name, addr, size, path = pending, int(c.group(1), 16), int(c.group(2), 16), c.group(3)
        else:
            stripped = line.strip()
            pending = stripped if re.fullmatch(r"\.\S+|COMMON", stripped) else None
            continue
        pending = None
        if size:
            starts.setdefault(current, []).append((addr, origin(path.strip(), name)))
    sizes: dict[str, dict[str, int]] = {}
    for section, entries in starts.items():
        entries.sort(key=lambda e: e[0])
        bounds = [a for a, _ in entries[1:]] + [ends[section]]
        bucket = sizes.setdefault(section, {})
        for (addr, key), stop in zip(entries, bounds):
            bucket[key] = bucket.get(key, 0) + stop - addr
    return sizes


def elf_sizes(elf: Path, size_tool: str) -> dict[str, int]:
    """Section sizes as `arm-none-eabi-size -A` reports them."""
    out = subprocess.run([size_tool, "-A", str(elf)], check=True, capture_output=True,
                         text=True).stdout
    rows = (ln.split() for ln in out.splitlines())
    return {r[0]: int(r[1]) for r in rows if len(r) == 3 and r[0].startswith(".")}


def group(sizes: dict[str, dict[str, int]], names: tuple[str, ...]) -> dict[str, int]:
    total: dict[str, int] = {}
    for name in names:
        for key, value in sizes.get(name, {}).items():
            total[key] = total.get(key, 0) + value
    return total


# ---- report -------------------------------------------------------------------------

def x86_truncated_message(model: Path) -> str:
    """The x86 runtime's message for the first half of the model (what the firmware loads
    as its error case), without the shim's "path: " prefix."""
    import tempfile

    from posecorr import Corrector, PoseCorrError

    data = model.read_bytes()
    with tempfile.TemporaryDirectory() as tmp:
        half = Path(tmp) / "half.onnx"
        half.write_bytes(data[:len(data) // 2])
        try:
            Corrector(half, backend="c")
        except PoseCorrError as e:
            return str(e).removeprefix(f"{half}: ")
    return "(loaded without error)"


def compare(run: FirmwareRun, model: Path) -> tuple[float, int]:
    from posecorr import Corrector

    x86 = Corrector(model, backend="c").correct(run.inputs.astype(np.float64))
    x86 = x86.astype(np.float32)
    diff = float(np.max(np.abs(run.outputs.astype(np.float64) - x86)))
    identical = int(np.sum(np.all(run.outputs.view(np.uint32) == x86.view(np.uint32), axis=1)))
    return diff, identical


def size_table(sizes: dict[str, dict[str, int]]) -> list[str]:
    rows = [("flash: code (text)", group(sizes, FLASH_CODE)),
            ("flash: read-only data (rodata)", group(sizes, FLASH_RODATA)),
            ("flash: .data initial values", group(sizes, RAM_DATA)),
            ("RAM: .data", group(sizes, RAM_DATA)),
            ("RAM: .bss", group(sizes, RAM_BSS))]
    if group(sizes, RAM_ARENA):
        rows.append(("RAM: .arena (pc_load_into)", group(sizes, RAM_ARENA)))
    flash: dict[str, int] = {}
    for _, row in rows[:3]:
        for key, value in row.items():
            flash[key] = flash.get(key, 0) + value
    rows.insert(3, ("flash total", flash))
    columns = COLUMNS + (("other",) if any("other" in r[1] for r in rows) else ())
    head = f"{'bytes':32}" + "".join(f"{c:>11}" for c in columns) + f"{'total':>10}"
    out = [head]
    for label, row in rows:
        out.append(f"{label:32}" + "".join(f"{row.get(c, 0):>11}" for c in columns)
                   + f"{sum(row.values()):>10}")
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--log", type=Path, required=True)
    ap.add_argument("--model", type=Path, required=True)
    ap.add_argument("--elf", type=Path, required=True)
    ap.add_argument("--map", type=Path, required=True)
    ap.add_argument("--size", default="arm-none-eabi-size")
    args = ap.parse_args(argv)

    run = parse_log(args.log.read_text())
    ok = run.finished and len(run.inputs) > 0
    print(f"QEMU mps2-an386 (Cortex-M4F) against x86 libposecorr, {args.model.name}:")
    if not ok:
        print("  the firmware did not finish cleanly; its output:")
        print("\n".join("    " + ln for ln in run.lines))
        return 1
    diff, identical = compare(run, args.model)
    print(f"  {len(run.inputs)} poses, max |QEMU - x86| = {diff:.3g} (tolerance {TOLERANCE:g}); "
          f"bit-identical poses: {identical}/{len(run.inputs)}")
    print("  single-pose and batch runs on the target: identical")
    target = run.truncated_message
    host = x86_truncated_message(args.model)
    print(f"  half the model refused: target '{target}'")
    print(f"  {'same message as' if target.endswith(host) else 'DIFFERENT message from'} "
          f"x86: '{host}'")
    for i in (0, len(run.inputs) - 1):
        print(f"  pose {i}: in  " + " ".join(f"{v:+.6f}" for v in run.inputs[i]))
        print(f"  {' ' * len(str(i))}       out " + " ".join(f"{v:+.6f}" for v in run.outputs[i]))

    sizes = map_sizes(args.map.read_text())
    elf = elf_sizes(args.elf, args.size)
    mismatch = [s for s in SECTIONS if s in elf and sum(sizes.get(s, {}).values()) != elf[s]]
    print(f"\nfirmware.elf by origin (map file; sections sum to `{Path(args.size).name} -A`: "
          f"{'yes' if not mismatch else 'NO: ' + ', '.join(mismatch)}):")
    print("\n".join("  " + ln for ln in size_table(sizes)))
    f = run.figures
    data_bss = sum(group(sizes, RAM_DATA + RAM_BSS).values())
    shape = f"{f['nodes']} nodes, {f['steps']} steps, max_batch {f['max_batch']}"
    if run.api == "pc_load_into":
        print(f"\nRAM (pc_load_into, no malloc for the model): .data + .bss {data_bss} B; caller "
              f"arena {f['arena_reserved']} B reserved, pc_required_bytes {f['required_bytes']} B "
              f"(model arena {f['arena_bytes']} B + load-time scratch); malloc calls during the load: "
              f"{f['load_allocations']}; stack peak {f['stack_peak']} B")
        print(f"  RAM in use: {data_bss + f['required_bytes'] + f['stack_peak']} B "
              f"(.data + .bss + required arena + stack; {shape}); heap peak {f['heap_peak']} B "
              f"is stdio and pc_required_bytes itself, after the run")
    else:
        print(f"\nRAM (pc_load_memory): .data + .bss {data_bss} B; heap: the model's arena "
              f"{f['arena_bytes']} B ({f['model_in_use']} B of malloc, {f['load_allocations']} malloc "
              f"calls during the load), heap peak "
              f"{f['heap_peak']} B (during load: arena + load-time scratch + stdio buffer); "
              f"stack peak {f['stack_peak']} B")
        print(f"  RAM in use: {data_bss + f['heap_peak'] + f['stack_peak']} B at the peak of load, "
              f"{data_bss + f['model_in_use'] + f['stack_peak']} B for the loaded model "
              f"(.data + .bss + arena + stack; {shape})")
    within = diff <= TOLERANCE and not mismatch
    return 0 if within else 1


if __name__ == "__main__":
    sys.exit(main())

"""Writes runtime_c/programs_compiled.c: the one-pose programs of the given models as C.

    python runtime_c/tools/compile_programs.py --shapes PRINT_SHAPES MODEL... [-o FILE] [--check]

PRINT_SHAPES is tools/print_shapes.c linked with a library built with PC_PRINT_SHAPES (the
CMake target posecorr-print-shapes); it prints the shape of every program the loader builds
(program.c: per operation its code, term count, stored flag and where each operand comes
from). Each distinct shape becomes one function that performs the interpreter's operations
on the same entries in the same order, keeping the values it computed itself in registers
and storing only the results the shape marks as stored. The loader runs such a function in
place of the interpreter when a program's shape equals it byte for byte.

--check: exit 1 when FILE lacks a shape of these models (the test suite's freshness check).
"""
from __future__ import annotations

import argparse
import re
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
RUNTIME = HERE.parent


def sop_codes(header: Path = RUNTIME / "kernels.h") -> dict[int, str]:
    """The PC_SOP_* enumerators of kernels.h, by value."""
    text = header.read_text()
    body = re.search(r"enum \{\s*(PC_SOP_NONE = 0,.*?)\};", text, re.S).group(1)
    names = re.findall(r"\b(PC_SOP_[A-Z0-9_]+)\b", re.sub(r"/\*.*?\*/", "", body, flags=re.S))
    return dict(enumerate(names))


class Shape:
    """One program shape, parsed from its bytes."""

    def __init__(self, data: bytes, codes: dict[int, str]):
        self.data = data
        self.ops = []  # (name, n_terms, stored, [operand back-references; 0 external])
        at = 0
        while at < len(data):
            name = codes[data[at]]
            n_terms, stored = data[at + 1], data[at + 2]
            at += 3
            refs = []
            for _ in range(operand_count(name, n_terms)):
                back = data[at]
                at += 1
                if back == 255:
                    back = data[at] | data[at + 1] << 8
                    at += 2
                refs.append(back)
            self.ops.append((name, n_terms, bool(stored), refs))

    def fnv1a(self) -> int:
        h = 0xCBF29CE484222325
        for byte in self.data:
            h = ((h ^ byte) * 0x100000001B3) & 0xFFFFFFFFFFFFFFFF
        return h


BINARY = {"PC_SOP_ADD", "PC_SOP_SUB", "PC_SOP_MUL", "PC_SOP_DIV", "PC_SOP_MAX", "PC_SOP_MIN"}
COMPARE = {"PC_SOP_EQ": "==", "PC_SOP_GT": ">", "PC_SOP_GE": ">=", "PC_SOP_LT": "<",
           "PC_SOP_LE": "<="}
BOOL_RESULT = set(COMPARE) | {"PC_SOP_COPY1"}


def operand_count(name: str, n_terms: int) -> int:
    if name == "PC_SOP_DOT":
        return 3 + 2 * n_terms
    if name == "PC_SOP_WHERE":
        return 3
    if name in BINARY or name in COMPARE:
        return 2
    return 1


# Operations worth a branch: a select whose sides need one of these computes only the side
# it takes (the graph computes both; the selected values, so the bits, are the same).
COSTLY = {"PC_SOP_DIV", "PC_SOP_SQRT", "PC_SOP_EXP", "PC_SOP_SIN", "PC_SOP_COS", "PC_SOP_TAN",
          "PC_SOP_ATAN", "PC_SOP_TANH", "PC_SOP_SIGMOID"}


def _lazy_selects(shape: Shape) -> dict[int, tuple[list[int], list[set[int]]]]:
    """The selects to run as branches, by their last member: WHERE operations of one computed
    condition, read only after the last of them, with the operations only one side needs
    (its cone: not stored, every use on that side), when a cone holds a costly operation."""
    n = len(shape.ops)
    users: list[list[tuple[int, int]]] = [[] for _ in range(n)]
    for pos, (_, _, _, refs) in enumerate(shape.ops):
        for slot, back in enumerate(refs):
            if back:
                users[pos - back].append((pos, slot))
    groups: dict[int, list[int]] = {}
    for pos, (name, _, _, refs) in enumerate(shape.ops):
        if name == "PC_SOP_WHERE" and refs[2]:
            groups.setdefault(pos - refs[2], []).append(pos)
    lazy = {}
    for members in groups.values():
        last, inside = members[-1], set(members)
        if any(u <= last for m in members for u, _ in users[m] if u not in inside):
            continue
        cones: list[set[int]] = []
        for slot in (0, 1):
            cone: set[int] = set()
            for pos in range(last - 1, -1, -1):
                if pos in inside or shape.ops[pos][2] or not users[pos]:
                    continue
                if all((u in inside and s == slot) or u in cone for u, s in users[pos]):
                    cone.add(pos)
            cones.append(cone)
        if any(shape.ops[p][0] in COSTLY for cone in cones for p in cone):
            lazy[last] = (members, cones)
    return lazy


def function(shape: Shape, fn_name: str) -> str:
    """C for one shape. Entry numbering as program.c emits it: a header entry where the
    code changes, one entry per operation, one per DOT term."""
    head = [f"PC_HOT static pc_status {fn_name}(const pc_step *s)", "{",
            "    char *const base = (char *)s->io[0];",
            "    const pc_scalar_op16 *const e = ((const pc_scalar_program16 *)s->prm)->ops;"]
    entry, last = 0, None
    kinds, first_entry = [], []  # per position: "f" float or "b" bool; its entry

    def read(pos: int, back: int, kind: str, k: int, field: str) -> str:
        if back:
            return f"{kinds[pos - back]}{pos - back}"
        return f"PC_X{kind.upper()}({k}, {field})"

    for name, n_terms, _, _ in shape.ops:
        if name != last:
            entry += 1  # the group's header
            last = name
        first_entry.append(entry)
        entry += 1 + (n_terms if name == "PC_SOP_DOT" else 0)
        kinds.append("b" if name in BOOL_RESULT else "f")

    def store(pos: int, pad: str) -> list[str]:
        if not shape.ops[pos][2]:
            return []
        return [f"{pad}PC_STORE{kinds[pos].upper()}({first_entry[pos]}, {kinds[pos]}{pos});"]

    def op_lines(pos: int, pad: str) -> list[str]:
        name, n_terms, _, refs = shape.ops[pos]
        k, kind, var = first_entry[pos], kinds[pos], f"{kinds[pos]}{pos}"
        lines = []
        if name in BINARY:
            a, b = read(pos, refs[0], "f", k, "a"), read(pos, refs[1], "f", k, "b")
            expr = f"pc_sop_float({name}, {a}, {b})"
        elif name in COMPARE:
            a, b = read(pos, refs[0], "f", k, "a"), read(pos, refs[1], "f", k, "b")
            expr = f"{a} {COMPARE[name]} {b}"
        elif name == "PC_SOP_WHERE":
            a, b = read(pos, refs[0], "f", k, "a"), read(pos, refs[1], "f", k, "b")
            c = read(pos, refs[2], "b", k, "c")
            expr = f"{c} ? {a} : {b}"
        elif name == "PC_SOP_COPY":
            expr = read(pos, refs[0], "f", k, "a")
        elif name == "PC_SOP_COPY1":
            expr = read(pos, refs[0], "b", k, "a")
        elif name == "PC_SOP_DOT":
            a, b = read(pos, refs[0], "f", k, "a"), read(pos, refs[1], "f", k, "b")
            c = read(pos, refs[2], "f", k, "c")
            lines.append(f"{pad}float {var} = {c};")
            lines.append(f"{pad}{var} += {a} * {b};")
            for t in range(1, n_terms + 1):
                ta = read(pos, refs[1 + 2 * t], "f", k + t, "a")
                tb = read(pos, refs[2 + 2 * t], "f", k + t, "b")
                lines.append(f"{pad}{var} += {ta} * {tb};")
            expr = None
        else:  # unary
            expr = f"pc_sop_float({name}, {read(pos, refs[0], 'f', k, 'a')}, 0.0f)"
        if expr is not None:
            ctype = "uint8_t" if kind == "b" else "float"
            lines.append(f"{pad}const {ctype} {var} = {expr};")
        return lines + store(pos, pad)

    lazy = _lazy_selects(shape)

    def emit(positions: set[int], pad: str) -> list[str]:
        mine = {last: g for last, g in lazy.items() if set(g[0]) <= positions}
        owned = {p for members, cones in mine.values() for p in (*members, *cones[0], *cones[1])}
        nested = {p for members, cones in mine.values() for p in (*cones[0], *cones[1])}
        lines = []
        for pos in sorted(positions):
            if pos not in owned:
                lines += op_lines(pos, pad)
            elif pos in mine and pos not in nested:
                members, cones = mine[pos]
                cond = f"b{pos - shape.ops[pos][3][2]}"
                lines += [f"{pad}float {', '.join(f'f{m}' for m in members)};", f"{pad}if ({cond}) {{"]
                for slot, cone in enumerate(cones):
                    if slot:
                        lines.append(f"{pad}}} else {{")
                    lines += emit(cone, pad + "    ")
                    lines += [f"{pad}    f{m} = {read(m, shape.ops[m][3][slot], 'f', first_entry[m], 'ab'[slot])};"
                              for m in members]
                lines.append(f"{pad}}}")
                for m in members:
                    lines += store(m, pad)
        return lines

    return "\n".join(head + emit(set(range(len(shape.ops))), "    ") + ["    return PC_OK;", "}"])


def generate(shapes: list[bytes], codes: dict[int, str]) -> str:
    parsed = [Shape(data, codes) for data in shapes]
    parsed.sort(key=lambda s: (len(s.data), s.data))
    out = ["/* Generated by tools/compile_programs.py from the shipped models' one-pose programs"
           " (make programs);",
           " * do not edit. Each function is the interpreter's program of one shape, with the",
           " * values it computes kept in registers (kernels.h, pc_compiled_program). */",
           '#include "kernels.h"', "", "#include <stdint.h>", "",
           "#define PC_XF(k, f) (*(const float *)(base + e[k].f))",
           "#define PC_XB(k, f) (*(const uint8_t *)(base + e[k].f))",
           "#define PC_STOREF(k, v) (*(float *)(base + e[k].o) = (v))",
           "#define PC_STOREB(k, v) (*(uint8_t *)(base + e[k].o) = (v))", ""]
    table = []
    for shape in parsed:
        h = shape.fnv1a()
        name = f"pc_program_{h:016x}"
        out.append(f"static const uint8_t {name}_shape[{len(shape.data)}] = {{")
        row = [f"{b}," for b in shape.data]
        for i in range(0, len(row), 24):
            out.append("    " + " ".join(row[i:i + 24]))
        out.append("};")
        out.append(function(shape, name))
        out.append("")
        table.append(f"    {{{len(shape.data)}u, 0x{h:016x}ull, {name}_shape, {name}}},")
    out.append(f"const pc_compiled_program pc_compiled_programs[{max(len(table), 1)}] = {{")
    out += table or ["    {0u, 0ull, NULL, NULL},"]
    out.append("};")
    out.append(f"const size_t pc_n_compiled_programs = {len(table)};")
    return "\n".join(out) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--shapes", required=True, help="the print_shapes program")
    ap.add_argument("models", nargs="+")
    ap.add_argument("-o", "--output", default=str(RUNTIME / "programs_compiled.c"))
    ap.add_argument("--check", action="store_true")
    args = ap.parse_args(argv)
    run = subprocess.run([args.shapes, *args.models], capture_output=True, text=True)
    if run.returncode:
        sys.stderr.write(run.stderr)
        return 2
    shapes = sorted({bytes.fromhex(line.split()[1]) for line in run.stdout.splitlines()
                     if line.startswith("shape ")})
    text = generate(shapes, sop_codes())
    path = Path(args.output)
    if args.check:
        have = path.read_text() if path.exists() else ""
        missing = [s for s in shapes if f"pc_program_{Shape(s, sop_codes()).fnv1a():016x}_shape" not in have]
        if missing:
            print(f"{path} lacks {len(missing)} of these models' {len(shapes)} program shapes: run make programs",
                  file=sys.stderr)
            return 1
        print(f"{path}: holds all {len(shapes)} program shapes of these models")
        return 0
    path.write_text(text)
    print(f"{path}: {len(shapes)} program shapes")
    return 0


if __name__ == "__main__":
    sys.exit(main())

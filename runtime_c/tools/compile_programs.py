"""Writes runtime_c/programs_compiled.c: the one-pose programs of the given models as C.

    python runtime_c/tools/compile_programs.py --shapes PRINT_SHAPES MODEL... [-o FILE] [--check]

PRINT_SHAPES is tools/print_shapes.c linked with a library built with PC_PRINT_SHAPES (the
CMake target posecorr-print-shapes); it prints the shape of every program the loader builds
(program.c: per operation its code, term count, stored flag and where each operand comes
from). Each distinct shape becomes one function that performs the interpreter's operations
in the same order, keeping the values it computed itself in registers; its parameters
(the loader writes them in place of the interpreter's entries) are only the offsets of
its arena operands and of the results the shape marks as stored, then its constants; a select whose sides need a costly operation runs
as a branch (_lazy_selects). The loader runs such a function in place of the interpreter
when a program's shape equals it byte for byte.

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
        self.ops = []  # (name, n_terms, stored, [back-references; 0 arena; -1 - j constant j])
        self.n_k = 0
        self.zeros: set[int] = set()  # the constants that are a sum's starting zero
        at = 0
        while at < len(data):
            name = codes[data[at]]
            n_terms, stored = data[at + 1], data[at + 2]
            at += 3
            refs = []
            for _ in range(operand_count(name, n_terms)):
                back = data[at]
                at += 1
                if back in (253, 254):
                    if back == 253:
                        self.zeros.add(self.n_k)
                    back = -1 - self.n_k
                    self.n_k += 1
                elif back == 255:
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
            if back > 0:
                users[pos - back].append((pos, slot))
    groups: dict[int, list[int]] = {}
    for pos, (name, _, _, refs) in enumerate(shape.ops):
        if name == "PC_SOP_WHERE" and refs[2] > 0:
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


class _Writer:
    """The C of one shape's operations. Offset numbering as program.c writes them
    (pc_compiled_params): per operation in order, its arena operands, then its result
    when stored."""

    def __init__(self, shape: Shape):
        self.shape, self.kinds = shape, []  # kind "f" float or "b" bool
        self.x: dict[tuple[int, int], int] = {}  # (position, operand slot) -> offset index
        self.x_store: dict[int, int] = {}  # position -> offset index of its stored result
        for pos, (name, _, stored, refs) in enumerate(shape.ops):
            for slot, back in enumerate(refs):
                if back == 0:
                    self.x[pos, slot] = len(self.x) + len(self.x_store)
            if stored:
                self.x_store[pos] = len(self.x) + len(self.x_store)
            self.kinds.append("b" if name in BOOL_RESULT else "f")
        self.n_x = len(self.x) + len(self.x_store)
        self.lazy = _lazy_selects(shape)

    def read(self, pos: int, slot: int, kind: str) -> str:
        back = self.shape.ops[pos][3][slot]
        if back > 0:
            return f"{self.kinds[pos - back]}{pos - back}"
        if back < 0:
            return f"PC_K{kind.upper()}({-1 - back})"
        return f"PC_X{kind.upper()}({self.x[pos, slot]})"

    def store(self, pos: int, pad: str) -> list[str]:
        if not self.shape.ops[pos][2]:
            return []
        kind = self.kinds[pos]
        return [f"{pad}PC_STORE{kind.upper()}({self.x_store[pos]}, {kind}{pos});"]

    def op(self, pos: int, pad: str) -> list[str]:
        name, n_terms, _, _ = self.shape.ops[pos]
        kind, var, lines = self.kinds[pos], f"{self.kinds[pos]}{pos}", []
        if name in BINARY:
            expr = f"pc_sop_float({name}, {self.read(pos, 0, 'f')}, {self.read(pos, 1, 'f')})"
        elif name in COMPARE:
            expr = f"{self.read(pos, 0, 'f')} {COMPARE[name]} {self.read(pos, 1, 'f')}"
        elif name == "PC_SOP_WHERE":
            expr = f"{self.read(pos, 2, 'b')} ? {self.read(pos, 0, 'f')} : {self.read(pos, 1, 'f')}"
        elif name in ("PC_SOP_COPY", "PC_SOP_COPY1"):
            expr = self.read(pos, 0, kind)
        elif name == "PC_SOP_DOT":
            refs = self.shape.ops[pos][3]
            first = f"{self.read(pos, 0, 'f')} * {self.read(pos, 1, 'f')}"
            if refs[2] < 0 and -1 - refs[2] in self.shape.zeros and refs[0] == refs[1] > 0:
                lines.append(f"{pad}float {var} = {first}; /* a square: 0 + it is it */")
            else:
                lines.append(f"{pad}float {var} = {self.read(pos, 2, 'f')};")
                lines.append(f"{pad}{var} += {first};")
            for t in range(1, n_terms + 1):
                lines.append(f"{pad}{var} += {self.read(pos, 1 + 2 * t, 'f')} * "
                             f"{self.read(pos, 2 + 2 * t, 'f')};")
            expr = None
        else:  # unary
            expr = f"pc_sop_float({name}, {self.read(pos, 0, 'f')}, 0.0f)"
        if expr is not None:
            lines.append(f"{pad}const {'uint8_t' if kind == 'b' else 'float'} {var} = {expr};")
        return lines + self.store(pos, pad)

    def select(self, last: int, pad: str) -> list[str]:
        """A lazy select (_lazy_selects) as an if: each side computes its own cone."""
        members, cones = self.lazy[last]
        lines = [f"{pad}float {', '.join(f'f{m}' for m in members)};",
                 f"{pad}if ({self.read(last, 2, 'b')}) {{"]
        for slot, cone in enumerate(cones):
            if slot:
                lines.append(f"{pad}}} else {{")
            lines += self.emit(cone, pad + "    ")
            lines += [f"{pad}    f{m} = {self.read(m, slot, 'f')};" for m in members]
        lines.append(f"{pad}}}")
        return lines + [line for m in members for line in self.store(m, pad)]

    def emit(self, positions: set[int], pad: str) -> list[str]:
        """The operations at these positions in order, the lazy selects among them as ifs."""
        mine = {last: g for last, g in self.lazy.items() if set(g[0]) <= positions}
        cone = {p for _, cones in mine.values() for p in (*cones[0], *cones[1])}
        owned = cone | {p for members, _ in mine.values() for p in members}
        lines = []
        for pos in sorted(positions):
            if pos not in owned:
                lines += self.op(pos, pad)
            elif pos in mine and pos not in cone:
                lines += self.select(pos, pad)
        return lines


def function(shape: Shape, fn_name: str) -> str:
    """C for one shape: the interpreter's operations in the same order (but for lazy
    selects), the values it computes in registers, the arena read and written at the
    offsets its parameters list."""
    w = _Writer(shape)
    head = [f"PC_HOT static pc_status {fn_name}(const pc_step *s)", "{"]
    if w.n_x:
        head += ["    char *const base = (char *)s->io[0];",
                 "    const int16_t *const x = (const int16_t *)s->prm;"]
    body = w.emit(set(range(len(shape.ops))), "    ")
    if shape.n_k:  # the constants follow the offsets, their count rounded up to even
        head.append(f"    const float *const k = (const float *)(const void *)"
                    f"((const int16_t *)s->prm + {(w.n_x + 1) // 2 * 2});")
    return "\n".join(head + body + ["    return PC_OK;", "}"])


def generate(shapes: list[bytes], codes: dict[int, str]) -> str:
    parsed = [Shape(data, codes) for data in shapes]
    parsed.sort(key=lambda s: (len(s.data), s.data))
    out = ["/* Generated by tools/compile_programs.py from the shipped models' one-pose programs"
           " (make programs);",
           " * do not edit. Each function is the interpreter's program of one shape, with the",
           " * values it computes kept in registers (kernels.h, pc_compiled_program). */",
           '#include "kernels.h"', "", "#include <stdint.h>", "",
           "#define PC_XF(j) (*(const float *)(base + x[j]))",
           "#define PC_XB(j) (*(const uint8_t *)(base + x[j]))",
           "#define PC_KF(j) (k[j])",
           "#define PC_KB(j) (*(const uint8_t *)&k[j])",
           "#define PC_STOREF(j, v) (*(float *)(base + x[j]) = (v))",
           "#define PC_STOREB(j, v) (*(uint8_t *)(base + x[j]) = (v))", ""]
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

"""A model's one-pose function as C source: what `posecorr compile` writes.

libposecorr loads the model (the posecorr-plan tool beside it, max_batch 1) and prints the
plan pc_run runs for one pose: its one-pose programs (element operations on byte offsets of
the activations, constants from a pool) and its dense layers (act(A B + C) with the weights).
`plan()` reads that; `source()` writes it as C99: each element operation as one statement on
a local variable, in the program's order; each dense layer as a loop that sums, per output,
its bias and then x[k] W[k][n] for k ascending (libposecorr's order), the weights as
`static const float` arrays by columns (each output reads its weights in a row). The
element formulas (tanh, sigmoid, ONNX's Max and Min, ...) are libposecorr's:
runtime_c/formulas.h is copied into the file as it is, and the expression of each
operation is the one the runtime was compiled from (posecorr-plan prints it). So the
function computes what pc_run computes, bit for bit (tests/test_compile.py).
"""
from __future__ import annotations

import re
import subprocess
import textwrap
from functools import partial
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .native_tools import NATIVE

POSE_WIDTH = 7
# pc_act (kernels.h): the activation a dense layer applies, as an expression of `acc`.
ACTIVATIONS = {0: ("none", "acc"), 1: ("tanh", "pc_tanh_inline(acc)"),
               2: ("sigmoid", "pc_sigmoid(acc)"), 3: ("relu", "PC_RELU_EXPR(acc)"),
               4: ("clip", "pc_clip(acc, lo, hi)"), 5: ("radbas", "pc_radbas(acc)")}
COMPARE = {"PC_SOP_EQ": "==", "PC_SOP_GT": ">", "PC_SOP_GE": ">=", "PC_SOP_LT": "<",
           "PC_SOP_LE": "<="}


class Unsupported(ValueError):
    """The model's plan has a step this compiler does not write as C."""


# ---- the plan, as posecorr-plan prints it ------------------------------------------------

@dataclass
class Operand:
    """A layer's operand: activations from byte offset `at`, or constant values."""

    at: int | None = None
    values: np.ndarray | None = None


@dataclass
class Layer:
    k: int
    n: int
    act: int
    lo: float
    hi: float
    alpha: float
    beta: float
    a: Operand
    b: Operand
    c: Operand | None
    o: int


@dataclass
class Program:
    """A one-pose program, or a node's kernel (`kernel`) whose work has the same form."""

    ops: list[tuple] = field(default_factory=list)  # (code, a, b, c, o, [(a, b) terms])
    pool: dict[int, int] = field(default_factory=dict)  # offset -> 32-bit word
    kernel: str | None = None


@dataclass
class Dense:
    layers: list[Layer] = field(default_factory=list)


@dataclass
class Checks:
    """pc_run's input and reach checks on this model, their numbers as pc_run compares them
    (an unbounded model's: infinite bounds, reach_pos2 infinite, reach_cos2 0)."""

    lo: np.ndarray
    hi: np.ndarray
    reach_pos2: float
    reach_cos2: float
    span: tuple[float, float] | None


@dataclass
class Plan:
    codes: dict[int, tuple[str, str]]  # code -> (name, expression in a and b)
    input: int
    time: int | None
    output: int
    steps: list
    checks: Checks | None = None


def _floats(text: str) -> np.ndarray:
    return np.array([int(w, 16) for w in text.split(",")], dtype=np.uint32).view(np.float32)


def _operand(text: str) -> Operand | None:
    if text == "-":
        return None
    if text.startswith("a:"):
        return Operand(at=int(text[2:]))
    return Operand(values=_floats(text[2:]))


def _bits_float(word: str) -> float:
    return float(np.array([int(word, 16)], dtype=np.uint32).view(np.float32)[0])


def _layer(words: list[str]) -> Layer:
    _, k, n, act, lo, hi, alpha, beta, a, b, c, o = words[1:]
    return Layer(int(k), int(n), int(act), _bits_float(lo), _bits_float(hi), _bits_float(alpha),
                 _bits_float(beta), _operand(a), _operand(b), _operand(c), int(o[2:]))


def _checks(words: list[str]) -> Checks:
    f = dict(w.split("=") for w in words[1:])
    span = None if f["span"] == "-" else tuple(float(v) for v in _floats(f["span"]))
    return Checks(_floats(f["lo"]), _floats(f["hi"]), _bits_float(f["reach_pos2"]),
                  _bits_float(f["reach_cos2"]), span)


def parse(text: str) -> Plan:
    """The Plan of posecorr-plan's output; Unsupported names a step it cannot translate."""
    codes: dict[int, tuple[str, str]] = {}
    steps: list = []
    head: dict[str, str] = {}
    checks = None
    for line in text.splitlines():
        words = line.split()
        kind = words[0]
        if kind == "sop":
            codes[int(words[1])] = (words[2], " ".join(words[3:]))
        elif kind == "checks":
            checks = _checks(words)
        elif kind == "plan":
            head = dict(w.split("=") for w in words[1:])
        elif kind == "step":
            if words[2] == "kernel":
                raise Unsupported(f"step {words[1]} of its one-pose plan runs {' '.join(words[3:])}, which "
                                  "has no C form here (one-pose programs, dense layers, element arithmetic and "
                                  "copies have)")
            steps.append(Dense() if words[2] == "dense" else
                         Program(kernel=" ".join(words[3:]) if words[2] == "elements" else None))
        elif kind == "op":
            code, a, b, c, o = map(int, words[1:])
            steps[-1].ops.append((code, a, b, c, o, []))
        elif kind == "term":
            steps[-1].ops[-1][5].append((int(words[1]), int(words[2])))
        elif kind == "pool":
            lo = int(words[1])
            steps[-1].pool = {lo + 4 * i: int(w, 16) for i, w in enumerate(words[2:])}
        elif kind == "layer":
            steps[-1].layers.append(_layer(words))
    if checks is None:
        raise ValueError("posecorr-plan printed no checks line (a posecorr-plan older than this package)")
    return Plan(codes, int(head["in"]), None if head["t"] == "-" else int(head["t"]),
                int(head["out"]), steps, checks)


def plan(model: Path, *, allow_unbounded: bool = False, allow_unsigned: bool = False) -> Plan:
    """The one-pose plan libposecorr loads `model` into. ValueError with the runtime's
    message when it refuses the file, Unsupported when a step has no C form."""
    tool = NATIVE / "posecorr-plan"
    args = [str(tool), str(model)] + ["--allow-unbounded"] * allow_unbounded + \
        ["--allow-unsigned"] * allow_unsigned
    run = subprocess.run(args, capture_output=True, text=True)
    if run.returncode:
        raise ValueError(run.stderr.strip() or f"{tool} failed ({run.returncode})")
    return parse(run.stdout)


# ---- C -------------------------------------------------------------------------------------

def literal(x: float) -> str:
    """A float32 constant as C: the shortest decimal that reads back as the same float."""
    if np.isnan(x):
        return "NAN"
    if np.isinf(x):
        return "INFINITY" if x > 0 else "(-INFINITY)"
    text = repr(np.float32(x)).removeprefix("np.float32(").removesuffix(")")
    if not re.search(r"[.e]", text):
        text += ".0"
    return f"({text}f)" if text.startswith("-") else f"{text}f"


class _Body:
    """The run function's statements: element operations on local variables, stores to the
    activations m[] that a dense layer reads, and the layers' calls."""

    def __init__(self, plan: Plan):
        self.codes = plan.codes
        self.lines: list[str] = []
        self.value: dict[int, str] = {j * 4 + plan.input: f"in[{j}]" for j in range(POSE_WIDTH)}
        if plan.time is not None:
            self.value[plan.time] = "t"
        self.boolean: dict[int, str] = {}
        self.in_memory: set[int] = set()
        self.n_vars = 0
        self.m_floats = 0
        self.weights: list[str] = []
        self.n_layers = 0
        self.activations: set[int] = set()

    # -- element operations
    def read(self, off: int, pool: dict[int, int]) -> str:
        if off < 0:
            return literal(float(np.array([pool[off]], np.uint32).view(np.float32)[0]))
        if off in self.value:
            return self.value[off]
        if off % 4:
            raise Unsupported(f"a float read at byte offset {off}, not a multiple of 4")
        self.m_floats = max(self.m_floats, off // 4 + 1)
        return f"m[{off // 4}]"

    def read_bool(self, off: int, pool: dict[int, int]) -> str:
        if off < 0:
            return str(pool[off - off % 4] >> (8 * (off % 4)) & 0xFF)
        if off not in self.boolean:
            raise Unsupported(f"a boolean read at offset {off} that no operation wrote")
        return self.boolean[off]

    def define(self, prefix: str, ctype: str, expr: str) -> str:
        var = f"{prefix}{self.n_vars}"
        self.n_vars += 1
        self.lines.append(f"    const {ctype} {var} = {expr};")
        return var

    def operation(self, op: tuple, pool: dict[int, int]) -> None:
        code, a, b, c, o, terms = op
        name, expr = self.codes[code]
        f = partial(self.read, pool=pool)
        if name == "PC_SOP_COPY1":
            self.boolean[o] = self.read_bool(a, pool)
            return
        if name in COMPARE:
            self.boolean[o] = self.define("b", "int", f"{f(a)} {COMPARE[name]} {f(b)}")
            return
        if name == "PC_SOP_COPY":
            var = f(a)
        elif name == "PC_SOP_WHERE":
            var = self.define("v", "float", f"{self.read_bool(c, pool)} ? {f(a)} : {f(b)}")
        elif name == "PC_SOP_DOT":
            var = f"v{self.n_vars}"
            self.n_vars += 1
            self.lines.append(f"    float {var} = {f(c)};")
            for ta, tb in [(a, b)] + terms:
                self.lines.append(f"    {var} += {f(ta)} * {f(tb)};")
        elif expr:  # the runtime's expression in a and b, on these operands
            operands = {"a": f(a), "b": f(b) if re.search(r"\bb\b", expr) else ""}
            var = self.define("v", "float", re.sub(r"\b[ab]\b", lambda w: operands[w.group()], expr))
        else:
            raise Unsupported(f"element operation {name} has no C form here")
        self.value[o] = var
        self.in_memory.discard(o)

    def program(self, step: Program, k: int) -> None:
        what = f"{step.kernel}, as its" if step.kernel else "one-pose program of"
        self.lines.append(f"    /* step {k}: {what} {len(step.ops)} element operations */")
        for op in step.ops:
            self.operation(op, step.pool)

    # -- dense layers
    def store(self, at: int, count: int) -> None:
        """The values at [at, at + 4 count) into m[], where a layer reads them."""
        for off in range(at, at + 4 * count, 4):
            if off in self.value and off not in self.in_memory:
                self.lines.append(f"    m[{off // 4}] = {self.value[off]};")
                self.in_memory.add(off)
        self.m_floats = max(self.m_floats, at // 4 + count)

    def operand(self, x: Operand, count: int, label: str, what: str) -> str:
        if x.at is not None:
            if x.at % 4:
                raise Unsupported(f"a layer operand at byte offset {x.at}")
            self.store(x.at, count)
            return f"m + {x.at // 4}" if x.at else "m"
        name = f"{label}{self.n_layers}"
        rows = [", ".join(literal(v) for v in x.values[i:i + 6]) for i in range(0, len(x.values), 6)]
        self.weights.append(f"/* layer {self.n_layers}: {what} */\n"
                            f"static const float {name}[{len(x.values)}] = {{\n    "
                            + ",\n    ".join(rows) + "\n};")
        return name

    def layer(self, g: Layer) -> None:
        if g.alpha != 1.0:
            raise Unsupported("a Gemm with alpha other than 1")
        if g.c is not None and g.c.at is not None and g.beta != 1.0:
            raise Unsupported("a Gemm whose C is computed, with beta other than 1")
        if g.c is None:
            g.c = Operand(values=np.zeros(g.n, np.float32))
        elif g.c.values is not None:
            g.c.values = (np.float32(g.beta) * g.c.values).astype(np.float32)
        reads = [(x.at, count) for x, count in ((g.a, g.k), (g.b, g.k * g.n), (g.c, g.n)) if x.at is not None]
        if any(at < g.o + 4 * g.n and g.o < at + 4 * count for at, count in reads):
            raise Unsupported("a dense layer whose output overlaps its input")
        a = self.operand(g.a, g.k, "x", f"its input, {g.k} values")
        if g.b.values is None:
            raise Unsupported("a dense layer whose weights are computed (a MatMul of two activations)")
        # by columns: output n reads its K weights in a row, the order it sums them in
        g.b.values = g.b.values.reshape(g.k, g.n).T.ravel()
        w = self.operand(g.b, g.k * g.n, "w", f"W ({g.k} x {g.n}) by columns: {g.n} rows of {g.k}")
        bias = self.operand(g.c, g.n, "b", f"the bias, {g.n} values")
        self.n_layers += 1
        self.activations.add(g.act)
        act = ACTIVATIONS[g.act][0]
        extra = f", {literal(g.lo)}, {literal(g.hi)}" if g.act == 4 else ""
        self.lines.append(f"    dense_{act}({a}, {g.k}, {w}, {bias}, {g.n}{extra}, "
                          f"{'m + ' + str(g.o // 4) if g.o else 'm'});")
        for off in range(g.o, g.o + 4 * g.n, 4):
            self.value.pop(off, None)
            self.in_memory.add(off)
        self.m_floats = max(self.m_floats, g.o // 4 + g.n)

    def dense(self, step: Dense, k: int) -> None:
        sizes = "-".join(str(x) for x in [step.layers[0].k] + [g.n for g in step.layers])
        self.lines.append(f"    /* step {k}: dense layers {sizes} */")
        for g in step.layers:
            if g.act not in ACTIVATIONS:
                raise Unsupported(f"a dense layer with activation {g.act}")
            self.layer(g)


def _without_unused(lines: list[str]) -> list[str]:
    """Drops definitions nothing reads (a program computes results that only its own
    stores to the arena used, and copies into m[] are written where read)."""
    kept = list(lines)
    while True:
        text = "\n".join(kept)
        unused = {name for name in re.findall(r"const \w+ ([vb]\d+) =", text)
                  if len(re.findall(rf"\b{name}\b", text)) == 1}
        if not unused:
            return kept
        kept = [ln for ln in kept if not any(re.search(rf"const \w+ {n} =", ln) for n in unused)]


def _dense_function(act: int) -> str:
    name, expr = ACTIVATIONS[act]
    clip = ", float lo, float hi" if act == 4 else ""
    return (f"static void dense_{name}(const float *x, int K, const float *wt, const float *b, int N{clip},\n"
            f"                       float *y)\n"
            "{\n    int n, k;\n    for (n = 0; n < N; n++) {\n        float acc = b[n];\n"
            "        for (k = 0; k < K; k++)\n            acc += x[k] * wt[n * K + k];\n"
            f"        y[n] = {expr};\n    }}\n}}")


def formulas_header() -> str:
    """runtime_c/formulas.h, which the package build places beside libposecorr."""
    path = NATIVE / "formulas.h"
    if not path.is_file():
        raise FileNotFoundError(f"{path} is missing; reinstall posecorr (pip install .)")
    return path.read_text()


def source(p: Plan, name: str, origin: str, digest: str | None = None) -> str:
    """The C file of plan `p`: `int NAME_run(const float in[7], [float t,] float out[7])`."""
    body = _Body(p)
    for k, step in enumerate(p.steps):
        (body.program if isinstance(step, Program) else body.dense)(step, k)
    outs = [body.read(p.output + 4 * j, {}) for j in range(POSE_WIDTH)]
    time = "float t, " if p.time is not None else ""
    lines = _without_unused(body.lines + [f"    o[{j}] = {x};" for j, x in enumerate(outs)])
    memory = [f"    float m[{body.m_floats}]; /* the activations the dense layers read and write */"] \
        if body.m_floats else []
    header = _header(name, origin, digest, p.time is not None)
    run = ([f"int {name}_run(const float in[{POSE_WIDTH}], {time}float out[{POSE_WIDTH}])", "{",
            f"    float o[{POSE_WIDTH}];", "    int j;"] + memory
           + _input_checks(p.checks, p.time is not None) + lines + _output_checks(p.checks)
           + [f"    for (j = 0; j < {POSE_WIDTH}; j++)", "        out[j] = o[j];", "    return 0;", "}"])
    parts = [header, "/* ---- libposecorr's element formulas (runtime_c/formulas.h, as it is) ---- */",
             formulas_header().strip(), "/* ---- the weights ---- */", *body.weights,
             "/* ---- the dense layer: y = act(x W + b), W [K][N] given by columns (wt[n K + k] =\n"
             " * W[k][n]); per output, the bias then x[k] W[k][n] for k ascending (libposecorr's\n"
             " * order) ---- */",
             *(_dense_function(a) for a in sorted(body.activations)),
             "/* ---- the one-pose function ---- */", "\n".join(run)]
    return "\n\n".join(parts) + "\n"


# The function's return codes: pc_run's refusals (runtime_c/run.c), each its own number.
STATUS = {0: "corrected: out holds the corrected pose",
          1: "an output is not finite (pc_run: PC_ERR_RUNTIME)",
          2: "the input is outside the range the model was fitted on: a position outside its "
             "input_bounds, or a time outside its time_bounds (PC_ERR_RANGE)",
          3: "the correction moves the pose beyond the model's correction_reach (PC_ERR_RUNTIME)",
          4: "an input value (or the time) is not finite (PC_ERR_NONFINITE)",
          5: "the input quaternion is not unit: |q|^2 outside [0.998001, 1.002001] (PC_ERR_QUATERNION)",
          6: "the output quaternion is not unit: |q|^2 not within 0.001 of 1 (PC_ERR_RUNTIME)"}


def _input_checks(c: Checks, takes_time: bool) -> list[str]:
    """pc_run's input checks (run.c, pc_check_input), in its order: the time, then the pose's
    values, its quaternion and its position against input_bounds. An unbounded model (loaded
    with --allow-unbounded) has infinite bounds: every finite value passes, so none is written."""
    lines = ["    /* pc_run's input checks, in its order (the return codes: top of the file) */"]
    if takes_time:
        lines += ["    if (!isfinite(t))", "        return 4;"]
        if c.span:
            lines += [f"    if (!(t >= {literal(c.span[0])} && t <= {literal(c.span[1])}))", "        return 2;"]
    lines += [f"    for (j = 0; j < {POSE_WIDTH}; j++)", "        if (!isfinite(in[j]))", "            return 4;"]
    # |q|^2 in double only where the float sum cannot decide, as pc_run (a Cortex-M4 sums
    # doubles in software)
    lines += ["    if (!pc_unit_input_banded(((in[3] * in[3] + in[4] * in[4]) + in[5] * in[5]) + in[6] * in[6],",
              "                              in + 3))", "        return 5;"]
    bounded = [k for k in range(3) if np.isfinite(c.lo[k]) or np.isfinite(c.hi[k])]
    if bounded:
        tests = [f"!(in[{k}] >= {literal(c.lo[k])} && in[{k}] <= {literal(c.hi[k])})" for k in bounded]
        lines += ["    if (" + " ||\n        ".join(tests) + ")", "        return 2;"]
    return lines


def _output_checks(c: Checks) -> list[str]:
    """pc_run's output checks (run.c, pc_check_output): finite, a unit quaternion, within reach."""
    lines = ["    /* pc_run's output checks, in its order */",
             f"    for (j = 0; j < {POSE_WIDTH}; j++)", "        if (!isfinite(o[j]))", "            return 1;",
             "    {", "        const pc_move v = pc_move_of(in, o);",
             "        if (!pc_unit_output(&v))", "            return 6;"]
    if np.isfinite(c.reach_pos2) or c.reach_cos2 != 0.0:
        lines += [f"        if (!pc_within_reach(&v, {literal(c.reach_pos2)}, {literal(c.reach_cos2)}))",
                  "            return 3;"]
    return lines + ["    }"]


def _status_lines() -> str:
    return "\n".join(textwrap.fill(text, 92, initial_indent=f" *   {k}  ", subsequent_indent=" *      ")
                     for k, text in STATUS.items())


# The words of the first line by which `posecorr compile` knows the files it wrote.
BANNER = "compiled by `posecorr compile`"


def _header(name: str, origin: str, digest: str | None, takes_time: bool) -> str:
    time = "float t, " if takes_time else ""
    return f"""/* {origin} {BANNER}: its one-pose function in C99.
 *
 *     int {name}_run(const float in[7], {time}float out[7]);
 *
 * in: one pose as the model's input "pose" (x, y, z, qw, qx, qy, qz; a unit quaternion){
    ', t: its time (s since the session start, the input "t")' if takes_time else ''};
 * out: the corrected pose as its output "corrected". The same operations in the same
 * order as libposecorr's pc_run on this model, so the same bits (built without
 * -ffast-math, with float arithmetic evaluated as float, FLT_EVAL_METHOD 0 as on x86-64 and
 * ARM: on s390x add -fexcess-precision=fast, on x87 -msse2 -mfpmath=sse; contraction into
 * fused multiply-adds is switched off below), and pc_run's
 * checks with the numbers pc_run compares (the model's input bounds and correction reach:
 * none when it has none and was compiled with --allow-unbounded). Returns, as pc_run
 * refuses (out is written on 0 only):
{_status_lines()}
 * Needs <math.h> only; no heap, no global state: the activations live on the stack.
 * model_digest: {digest or '(none)'}
 */
#if defined(__clang__)
#pragma STDC FP_CONTRACT OFF
#elif defined(__GNUC__)
#pragma GCC optimize("fp-contract=off")
#endif

#include <math.h>

int {name}_run(const float in[7], {time}float out[7]);"""

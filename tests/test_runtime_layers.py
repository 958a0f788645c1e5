"""runtime_c is cut in one-way layers (runtime_c/README.md): no include cycle between its
headers, no link cycle between its objects (who defines what the other uses, from `nm`),
every file in the layer table, no include of a higher layer, and no dead code silenced
with a cast to void."""
from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "runtime_c"
sys.path.insert(0, str(SRC / "tests"))

import graphs  # noqa: E402

# The layers, lowest first: a file may include or call files of its own layer or below.
LAYERS = [
    ("base", ["posecorr.h", "base.h", "status.c", "scratch.h", "scratch.c", "crc32c.c"]),
    ("protobuf wire format", ["pb.h", "pb.c"]),
    ("records of the load", ["ir.h", "ir.c"]),
    ("ONNX decoding", ["onnx.h", "onnx.c"]),
    ("kernels", ["kernels.h", "formulas.h", "kernels.c", "dense.c", "programs_compiled.c"]),
    ("operators", ["op.h", "op.c", "op_elementwise.c", "op_shape.c", "op_dense.c",
                   "op_reduce.c", "op_table.c"]),
    ("graph scan", ["graph.h", "graph.c"]),
    ("model and pc_run", ["model.h", "run.c"]),
    ("planner", ["place.h", "place.c", "program.h", "program.c", "plan.h", "plan.c"]),
    ("loading and public accessors", ["load.h", "api.c"]),
]
RANK = {f: i for i, (_, files) in enumerate(LAYERS) for f in files}
INCLUDE = re.compile(r'^\s*#\s*include\s+"([^"]+)"', re.M)


def library_files() -> list[Path]:
    return sorted([*SRC.glob("*.c"), *SRC.glob("*.h")])


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """A cycle of graph as a list of nodes (first == last), or None."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(n: str) -> list[str] | None:
        state[n] = 1
        stack.append(n)
        for m in sorted(graph.get(n, ())):
            if state.get(m) == 1:
                return stack[stack.index(m):] + [m]
            if m not in state and (c := visit(m)):
                return c
        stack.pop()
        state[n] = 2
        return None

    for n in sorted(graph):
        if n not in state and (c := visit(n)):
            return c
    return None


def test_find_cycle_sees_a_cycle():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": set()}) is None


def include_graph() -> dict[str, set[str]]:
    return {p.name: set(INCLUDE.findall(p.read_text())) for p in library_files()}


def test_every_file_has_a_layer():
    missing = [p.name for p in library_files() if p.name not in RANK]
    assert not missing, f"add {missing} to LAYERS here and to runtime_c/README.md"


def test_no_include_cycle():
    graph = include_graph()
    assert find_cycle(graph) is None, f"include cycle: {' -> '.join(find_cycle(graph))}"


def test_includes_point_down():
    up = [(f, h) for f, hs in include_graph().items() for h in hs
          if h in RANK and RANK[h] > RANK[f]]
    assert not up, f"files including a higher layer: {up}"


def test_header_comments_number_their_layer_as_the_table_does():
    """Each internal header opens with "Layer N, ...": N is its rank in LAYERS (lowest 0),
    the order runtime_c/README.md draws."""
    numbered = {}
    for p in sorted(SRC.glob("*.h")):
        first = re.match(r"/\* Layer (\d+),", p.read_text())
        if first:
            numbered[p.name] = int(first.group(1))
    assert set(numbered) == set(RANK) & {p.name for p in SRC.glob("*.h")} - {"posecorr.h"}
    wrong = {name: (n, RANK[name]) for name, n in numbered.items() if n != RANK[name]}
    assert not wrong, f"header comment's layer number vs LAYERS: {wrong}"


@pytest.fixture(scope="module")
def objects() -> dict[str, Path]:
    if shutil.which("nm") is None:
        pytest.skip("nm (binutils) not installed")
    build = graphs.build_test_runtime()
    objs = {p.name[:-2]: p for p in (build / "CMakeFiles" / "posecorr_obj.dir").glob("*.c.o")}
    assert objs, "no objects in the build"
    return objs


def symbols(obj: Path) -> tuple[set[str], set[str]]:
    out = subprocess.run(["nm", str(obj)], capture_output=True, text=True, check=True).stdout
    defined, undefined = set(), set()
    for line in out.splitlines():
        parts = line.split()
        if len(parts) == 2 and parts[0] == "U":
            undefined.add(parts[1])
        elif len(parts) == 3 and parts[1] in "TDRBCV":
            defined.add(parts[2])
    return defined, undefined


def test_no_link_cycle(objects):
    table = {name: symbols(p) for name, p in objects.items()}
    owner = {s: name for name, (defined, _) in table.items() for s in defined}
    graph = {name: {owner[s] for s in undefined if s in owner and owner[s] != name}
             for name, (_, undefined) in table.items()}
    edges = sum(len(v) for v in graph.values())
    print(f"{len(graph)} objects, {edges} object -> object symbol dependencies")
    assert edges > len(graph) // 2, "the symbol graph is implausibly sparse"
    assert find_cycle(graph) is None, f"link cycle: {' -> '.join(find_cycle(graph))}"
    up = [(a, b) for a, bs in graph.items() for b in bs if RANK[b] > RANK[a]]
    assert not up, f"objects calling a higher layer: {up}"


def test_no_void_casts_silencing_dead_code():
    cast = re.compile(r"\(void\)\s*[A-Za-z_&*(]")
    hits = [f"{p.name}:{i}" for p in library_files()
            for i, line in enumerate(p.read_text().splitlines(), 1) if cast.search(line)]
    assert not hits, f"(void) casts in the library: {hits}"


# pc_vformat's subset (status.c): the library formats its messages itself, because the C
# library of a microcontroller (newlib-nano) lacks %zu and %ll.
CONVERSION = re.compile(r"%(\.(?:\*|\d+))?(z|ll|l)?([diuxsc%])")
ANY_CONVERSION = re.compile(r"%[-+ #0-9.*]*(?:hh|h|ll|l|z|j|t|L)?[a-zA-Z%]")
STRING = re.compile(r'"((?:[^"\\\n]|\\.)*)"')


def test_messages_use_the_library_formatter():
    """No printf-family call in the library, and every conversion in its string literals
    is one pc_vformat implements (tests/unit_tests.c compares it with snprintf)."""
    calls = re.compile(r"\b(?:v?s?n?printf|fprintf|puts)\s*\(")
    printf_calls, unknown = [], []
    for p in library_files():
        for i, line in enumerate(p.read_text().splitlines(), 1):
            if calls.search(line) and not line.lstrip().startswith(("*", "/*")):
                printf_calls.append(f"{p.name}:{i}")
            for literal in STRING.findall(line):
                for conv in ANY_CONVERSION.findall(literal):
                    if not CONVERSION.fullmatch(conv):
                        unknown.append(f"{p.name}:{i}: {conv}")
    assert not printf_calls, f"printf-family calls in the library (use pc_format): {printf_calls}"
    assert not unknown, f"conversions pc_vformat does not implement: {unknown}"


def test_message_checker_sees_unsupported_conversions():
    assert not CONVERSION.fullmatch(ANY_CONVERSION.findall('"%5.2f"')[0])
    assert [bool(CONVERSION.fullmatch(c)) for c in ANY_CONVERSION.findall('"%zu %.*s %lld %08x"')] \
        == [True, True, True, False]

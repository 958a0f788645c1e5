"""No function longer than 60 lines unless a comment says why it stays whole (issue 34 item 7).

The size is emlearn's and scikit-learn's: a longer function is split into named phases. A
function may stay longer when a comment in it, or in the comment block right above it,
contains "stays whole" and says why (a hot loop that a call would slow, one table that
reads best in one place). A function's length runs from its def (or C header) line to the
last line of its body; decorators are not counted.

Python: every .py under python/, train/, export/, tools/, bench/ and runtime_c/tools/, read
with `ast`.
C: the top-level functions of runtime_c/*.c, found by matching braces once comments,
strings and preprocessor lines are blanked. runtime_c/programs_compiled.c is left out: it is
written by runtime_c/tools/compile_programs.py, one straight-line function per one-pose
program of the shipped models, as long as the program, never edited by hand; its generator is held to
the rule instead."""
from __future__ import annotations

import ast
import io
import re
import tokenize
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LIMIT = 60
MARK = "stays whole"
PYTHON_DIRS = ("python", "train", "export", "tools", "bench", "runtime_c/tools")
C_GENERATED = {"programs_compiled.c"}


def _comment_lines_py(text: str) -> dict[int, str]:
    return {tok.start[0]: tok.string for tok in tokenize.generate_tokens(io.StringIO(text).readline)
            if tok.type == tokenize.COMMENT}


def _excused(lines: list[str], comments: dict[int, str], first: int, last: int, is_comment) -> bool:
    """Whether a comment in lines first..last (1-based), or in the comment block right above
    `first`, contains MARK."""
    above = first - 1
    while above >= 1 and is_comment(lines[above - 1]):
        above -= 1
    return any(MARK in comments.get(n, "") for n in range(above + 1, last + 1))


def long_python_functions(path: Path) -> list[tuple[int, str, int]]:
    """(line, name, length) of each function in a Python file over LIMIT lines without its
    comment."""
    text = path.read_text(encoding="utf-8")
    lines = text.splitlines()
    comments = _comment_lines_py(text)
    out = []
    for node in ast.walk(ast.parse(text, filename=str(path))):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            length = node.end_lineno - node.lineno + 1
            first = min([node.lineno] + [d.lineno for d in node.decorator_list])
            if length > LIMIT and not _excused(lines, comments, first, node.end_lineno,
                                               lambda s: s.lstrip().startswith("#")):
                out.append((node.lineno, node.name, length))
    return out


def _blank_c(text: str) -> tuple[str, dict[int, str]]:
    """The C text with comments, string and character literals and preprocessor lines
    (with their continuations) blanked, line breaks kept; and each line's comment text."""
    out, comments = [], {}
    i, n, line, at_line_start = 0, len(text), 1, True
    while i < n:
        c = text[i]
        if at_line_start and text[i:].lstrip(" \t").startswith("#"):
            j = i
            while True:     # the directive runs to an unescaped line end
                k = text.find("\n", j)
                k = n if k < 0 else k
                if k > 0 and text[k - 1] == "\\" and k < n:
                    j = k + 1
                    continue
                break
        elif text.startswith("/*", i):
            k = text.find("*/", i + 2)
            k = n if k < 0 else k + 2
        elif text.startswith("//", i):
            k = text.find("\n", i)
            k = n if k < 0 else k
        elif c in "\"'":
            k = i + 1
            while k < n and text[k] != c:
                k += 2 if text[k] == "\\" else 1
            k = min(k + 1, n)
        else:
            out.append(c)
            at_line_start = c == "\n" or (at_line_start and c in " \t")
            line += c == "\n"
            i += 1
            continue
        piece = text[i:k]
        if piece.startswith(("/*", "//")):
            for offset, part in enumerate(piece.split("\n")):
                comments[line + offset] = comments.get(line + offset, "") + part
        out.append(re.sub(r"[^\n]", " ", piece))
        line += piece.count("\n")
        at_line_start = piece.endswith("\n")
        i = k
    return "".join(out), comments


def long_c_functions(path: Path) -> list[tuple[int, str, int]]:
    """(line, name, length) of each top-level function in a C file over LIMIT lines without
    its comment. A top-level brace opens a function when the text since the previous
    top-level statement ends with a closing parenthesis (not `= {`, not `struct x {`)."""
    text = path.read_text(encoding="utf-8")
    raw_lines = text.splitlines()
    blank, comments = _blank_c(text)
    out, depth, stmt_start, header = [], 0, 0, ""
    for pos, ch in enumerate(blank):
        if ch == "{":
            if depth == 0:
                header = blank[stmt_start:pos]
            depth += 1
        elif ch == "}":
            depth -= 1
            if depth == 0:
                name = re.search(r"(\w+)\s*\([^()]*(?:\([^()]*\)[^()]*)*\)\s*$", header)
                if name and "=" not in header:
                    # The header starts after the last blank line before the name (a blanked
                    # comment, or an invocation of a macro that defines functions, comes before).
                    start = stmt_start + max(header.rfind("\n\n", 0, name.start()) + 2,
                                             len(header) - len(header.lstrip()))
                    first = blank.count("\n", 0, start) + 1
                    while not raw_lines[first - 1].strip():
                        first += 1
                    last = blank.count("\n", 0, pos) + 1
                    if last - first + 1 > LIMIT and not _excused(
                            raw_lines, comments, first, last,
                            lambda s: s.lstrip().startswith(("/*", "*", "//"))):
                        out.append((first, name.group(1), last - first + 1))
                stmt_start = pos + 1
        elif ch == ";" and depth == 0:
            stmt_start = pos + 1
    return out


def _python_files() -> list[Path]:
    return sorted(p for d in PYTHON_DIRS for p in (ROOT / d).rglob("*.py")
                  if not {".venv", "__pycache__", "build"} & set(p.relative_to(ROOT).parts))


def _c_files() -> list[Path]:
    return sorted(p for p in (ROOT / "runtime_c").glob("*.c") if p.name not in C_GENERATED)


def _report(found: list[tuple[Path, int, str, int]]) -> str:
    return "\n".join(f"{p.relative_to(ROOT)}:{line}:{name}: {length} lines (over {LIMIT}, no "
                     f"'{MARK}' comment saying why)" for p, line, name, length in found)


def test_no_python_function_over_60_lines_without_its_comment():
    files = _python_files()
    assert len(files) > 50, "the scan found too few Python files: the folders moved?"
    found = [(p, *f) for p in files for f in long_python_functions(p)]
    assert not found, _report(found)


def test_no_c_function_over_60_lines_without_its_comment():
    files = _c_files()
    assert len(files) > 10, "the scan found too few C files: runtime_c moved?"
    found = [(p, *f) for p in files for f in long_c_functions(p)]
    assert not found, _report(found)


def test_the_checker_measures_and_excuses(tmp_path):
    """The checkers find a long function, name its line, and let it pass with its comment:
    counted against functions written here with known lengths."""
    body = "".join(f"    x{i} = {i}\n" for i in range(60))
    long_py = tmp_path / "long.py"
    long_py.write_text("import os\n\n\n@staticmethod\ndef long():\n" + body + "\n\ndef short():\n    pass\n")
    assert long_python_functions(long_py) == [(5, "long", 61)]
    long_py.write_text("def long():\n" + body[:-len("    x59 = 59\n")])   # 60 lines: allowed
    assert long_python_functions(long_py) == []
    long_py.write_text("# the table stays whole: one place to read it\ndef long():\n" + body)
    assert long_python_functions(long_py) == []
    long_py.write_text("def long():\n    # it stays whole: a call per pose costs more than it\n" + body)
    assert long_python_functions(long_py) == []

    c_body = "".join(f"    x += {i}; /* {{ */\n" for i in range(58))
    long_c = tmp_path / "long.c"
    header = ("#define M(a) \\\n    { a }\nstatic const int t[] = {1, 2};\n"
              "struct s { int a; };\n")
    fn = "static int\nlong_fn(int x, const char *s)\n{\n" + c_body + "    return x;\n}\n"
    long_c.write_text(header + fn + "int short_fn(void) { return '{'; }\n")
    assert long_c_functions(long_c) == [(5, "long_fn", 63)]
    long_c.write_text(header + "/* long_fn stays whole: its loop is the hot path\n * of every pose. */\n"
                      + fn)
    assert long_c_functions(long_c) == []

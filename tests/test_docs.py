"""Every file the repository's docs and comments name is a file of the repository.

The tracked text files are read (Markdown, build files and text whole; Python for its
comments and docstrings; C for its comments), every token that looks like a file name
(`docs/design.md`, `kernels.c`, `tools/models.py`) is resolved against the repository, and
any reference to a folder outside it (`../shared`) is refused."""
from __future__ import annotations

import io
import re
import shutil
import subprocess
import tokenize
from pathlib import Path, PurePosixPath

import pytest

ROOT = Path(__file__).resolve().parents[1]
SELF = Path(__file__).resolve().relative_to(ROOT).as_posix()
# Sources and docs; outputs a command writes (.csv, .json, .html, .onnx) are named in usage
# lines without being files of the repository, so they are not checked.
EXTENSIONS = ("md", "py", "c", "h", "txt", "toml", "sh", "ld", "mk", "yml", "yaml")
# A file name: path characters ending in a name character, a dot and a known extension, not
# followed by more name characters (`x.c.o` is no reference to `x.c`); not after `$` (a shell
# variable's folder) or `<` (a system header).
REFERENCE = re.compile(r"(?<![\w./$<-])((?:\.\.?/)*[\w][\w.-]*(?:/[\w.-]+)*\.(?:%s))(?![\w.-]*\w)"
                       % "|".join(EXTENSIONS))
OUTSIDE = re.compile(r"\.\./shared\b|/work/shared\b")
URL = re.compile(r"[a-z][a-z0-9+.-]*://\S+")
WHOLE_TEXT = {".md", ".txt", ".toml", ".cmake", ".mk", ".sh", ".ld", ".yml", ".yaml", ".in"}
WHOLE_NAMES = {"Makefile", "CMakeLists.txt"}
# Names that are not meant as files of the repository.
NOT_REPOSITORY_FILES = {
    "F.py", "OUT.c", "OUT.h",      # placeholders in usage lines
    "Python.h", "eml_net.h",       # headers of CPython and emlearn
    "stdatomic.h",                 # C11's, looked for by runtime_c/CMakeLists.txt
    "model_data.c", "poses.h",     # written by the firmware build (runtime_c/embedded/Makefile)
    "mlp_weights.h",
    "zhou_compiled.c",             # ... by `posecorr compile` there (the guide's example)
    "metadata.yaml",               # the index file of a ROS 2 bag folder
    "proposed.py", "bend.py",      # the effect files `diagnose --propose` writes in the loop's examples
    "reference/cli.md", "../reference/cli.md",   # the site's page written at build time (tools/docs_site.py)
}


def tracked_files() -> list[str]:
    if shutil.which("git") is None or not (ROOT / ".git").exists():
        pytest.skip("not a git checkout: the tracked files are unknown")
    out = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True).stdout
    return [p for p in out.decode("utf-8").split("\0") if p]


def python_prose(source: str) -> str:
    """The comments and docstrings (strings standing as a statement) of a Python source."""
    parts, previous = [], tokenize.NEWLINE
    try:
        for tok in tokenize.generate_tokens(io.StringIO(source).readline):
            if tok.type == tokenize.COMMENT:
                parts.append(tok.string)
            elif tok.type == tokenize.STRING and previous in (tokenize.NEWLINE, tokenize.INDENT, tokenize.DEDENT):
                parts.append(tok.string)
            if tok.type not in (tokenize.COMMENT, tokenize.NL):
                previous = tok.type
    except (SyntaxError, tokenize.TokenError):
        return ""
    return "\n".join(parts)


C_COMMENT = re.compile(r"/\*.*?\*/|//[^\n]*", re.S)
C_STRING = re.compile(r'"(?:[^"\\\n]|\\.)*"')


def c_prose(source: str) -> str:
    """The comments of a C source (string literals removed first: "//" may sit in one)."""
    return "\n".join(C_COMMENT.findall(C_STRING.sub('""', source)))


def prose(path: str, text: str) -> str | None:
    p = PurePosixPath(path)
    if p.suffix == ".py":
        return python_prose(text)
    if p.suffix in (".c", ".h"):
        return c_prose(text)
    if p.suffix in WHOLE_TEXT or p.name in WHOLE_NAMES:
        return text
    return None


def resolves(ref: str, where: str, files: set[str], names: set[str]) -> bool:
    """`ref` named in file `where` is a file of the repository: relative to the file's
    folder or any folder above it up to the root, or (a bare name, or a path written from
    some folder of the tree) the end of a tracked path."""
    folder = PurePosixPath(where).parent
    for base in (folder, *folder.parents):
        candidate = (base / ref).as_posix()
        parts: list[str] = []
        for part in candidate.split("/"):
            if part == "..":
                if not parts:
                    break
                parts.pop()
            elif part not in ("", "."):
                parts.append(part)
        else:
            if "/".join(parts) in files:
                return True
    clean = ref.lstrip("./")
    if "/" not in clean:
        return clean in names
    return any(f == clean or f.endswith("/" + clean) for f in files)


def references(files: list[str]) -> tuple[list[str], list[str]]:
    """(missing, outside): "file: name" of names that are no tracked file, and "file:line:
    text" of lines naming a folder outside the repository."""
    tracked = set(files)
    names = {PurePosixPath(f).name for f in files}
    missing, outside = [], []
    for path in files:
        if prose(path, "") is None or path == SELF:   # this file names them to find them
            continue
        try:
            text = (ROOT / path).read_text(encoding="utf-8")
        except (UnicodeDecodeError, FileNotFoundError):
            continue
        for line_no, line in enumerate(text.splitlines(), 1):
            if OUTSIDE.search(line):
                outside.append(f"{path}:{line_no}: {line.strip()}")
        body = prose(path, text)
        if not body:
            continue
        for ref in sorted(set(REFERENCE.findall(URL.sub(" ", body)))):
            if ref in NOT_REPOSITORY_FILES or resolves(ref, path, tracked, names):
                continue
            missing.append(f"{path}: {ref}")
    return missing, outside


def test_no_reference_to_a_missing_file():
    missing, outside = references(tracked_files())
    assert not outside, "references outside the repository:\n" + "\n".join(outside)
    assert not missing, "references to files the repository does not hold:\n" + "\n".join(missing)


def test_reference_check_sees_missing_and_outside_files():
    files = ["README.md", "runtime_c/kernels.h", "runtime_c/kernels.c", "runtime_c/tools/zhou_weights.py",
             "python/posecorr/data.py", "docs/design.md"]
    text = {
        "README.md": "See docs/design.md and `kernels.c`; DESIGN.md is gone; https://x.org/a.md is a URL.",
        "runtime_c/kernels.h": '/* layout chosen in ops.c; weights from tools/zhou_weights.py */\n'
                               'static const char *s = "not_a_comment.c";\n',
        "python/posecorr/data.py": '"""The table (docs/design.md, "Data"); see ../shared/DESIGN.md."""\n'
                                   'PATH = "tmp/made_at_run_time.py"  # old.py was removed\n',
    }
    tracked = set(files)
    names = {PurePosixPath(f).name for f in files}
    found = {}
    for path, body in text.items():
        refs = set(REFERENCE.findall(URL.sub(" ", prose(path, body))))
        found[path] = sorted(r for r in refs if not resolves(r, path, tracked, names))
    assert found == {"README.md": ["DESIGN.md"], "runtime_c/kernels.h": ["ops.c"],
                     "python/posecorr/data.py": ["../shared/DESIGN.md", "old.py"]}
    assert OUTSIDE.search(text["python/posecorr/data.py"])

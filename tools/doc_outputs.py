"""The outputs the guides show are what their commands print today.

A guide shows a command's output in a ```text block: a line `$ COMMAND` (posecorr on PATH,
run from the repository's root), then lines of what it printed, often a few of many (a
`...` line marks a cut, but any line may be left out). This harness runs a page's commands
in order in a scratch folder holding copies of `examples/`, `tests/data/` and `models/` (a `fit` appends
a ledger beside its data: the checkout is never written), and checks that every shown line
is a line of the real output, in order.

Lines are compared in their words and numbers: the words exactly, a whole number (a rank,
a count) exactly, a decimal to one unit in the last digit the page prints
(a figure that sits on a rounding step may print either way on another CPU), so a figure
the code no longer gives fails. Figures that vary with the CPU by design (`VOLATILE`, each
with its reason) are held to their order of magnitude. A block that cannot run here says
why in an HTML comment on the line before its fence, `<!-- outputs not checked: REASON -->`,
and is reported as such.

    python -m tools.doc_outputs [PAGE ...]     # every page of docs/ with commands, by default

tests/test_doc_outputs.py runs it on every page.
"""
from __future__ import annotations

import argparse
import math
import os
import re
import shutil
import subprocess
import sys
import tempfile
from contextlib import nullcontext
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DOCS = ROOT / "docs"
# What the commands read, copied into the scratch folder under the same names.
INPUTS = ("examples", "tests/data", "models")
NOT_CHECKED = re.compile(r"<!--\s*outputs not checked:\s*(.+?)\s*-->")
NUMBER = re.compile(r"[-+]?(?:\d+\.\d*|\.\d+|\d+)(?:[eE][-+]?\d+)?")
# Figures that depend on the CPU's kernels, not on posecorr: checked to their order of magnitude.
VOLATILE = {
    re.compile(r"\d+ bytes, parity \S+ m / \S+ rad"):
        "float32 rounding of onnxruntime's kernels, which it picks for the CPU at run time; the "
        "file's size moves with the digits of the figures its metadata records",
}
TIMEOUT_S = 600


@dataclass
class Command:
    line: int            # the `$` line's number on the page (1-based)
    text: str
    shown: list[tuple[int, str]] = field(default_factory=list)   # (line number, text)


@dataclass
class Block:
    line: int
    commands: list[Command]
    not_checked: str | None    # the reason the page gives, or None


def blocks(page: Path) -> list[Block]:
    """The page's ```text blocks that hold at least one `$ ` command."""
    found, lines = [], page.read_text(encoding="utf-8").splitlines()
    i = 0
    while i < len(lines):
        if lines[i].strip() != "```text":
            i += 1
            continue
        start, commands, i = i + 1, [], i + 1
        while i < len(lines) and lines[i].strip() != "```":
            text = lines[i]
            if text.startswith("$ "):
                command = text[2:]
                while command.endswith("\\") and i + 1 < len(lines):
                    i += 1
                    command = command[:-1] + " " + lines[i].strip()
                commands.append(Command(i + 1, command))
            elif commands and text.strip() and text.strip() != "...":
                commands[-1].shown.append((i + 1, text))
            i += 1
        if commands:
            before = lines[start - 2] if start >= 2 else ""
            reason = NOT_CHECKED.search(before)
            found.append(Block(start, commands, reason.group(1) if reason else None))
        i += 1
    return found


def _allowance(printed: str) -> float:
    """One unit in the last digit `printed` shows; none for a whole number (a rank, a count)."""
    mantissa, _, exponent = printed.lower().lstrip("+-").partition("e")
    if "." not in mantissa and not exponent:
        return 0.0
    decimals = len(mantissa.partition(".")[2])
    return 10.0 ** (int(exponent or 0) - decimals)


def _volatile_spans(text: str) -> list[tuple[int, int]]:
    return [m.span() for pattern in VOLATILE for m in pattern.finditer(text)]


def numbers_agree(shown: str, real: str, volatile: bool = False) -> bool:
    a, b = float(shown), float(real)
    if volatile:
        return a == b or (a > 0 and b > 0 and abs(math.log10(a / b)) <= 1.0)
    return abs(a - b) <= _allowance(shown) * (1 + 1e-9)


def lines_agree(shown: str, real: str) -> bool:
    """The same words, and numbers that agree (`numbers_agree`), whitespace aside."""
    shown_numbers, real_numbers = list(NUMBER.finditer(shown)), list(NUMBER.finditer(real))
    if len(shown_numbers) != len(real_numbers):
        return False
    if " ".join(NUMBER.split(shown)).split() != " ".join(NUMBER.split(real)).split():
        return False
    loose = _volatile_spans(shown)
    return all(numbers_agree(s.group(), r.group(), any(lo <= s.start() < hi for lo, hi in loose))
               for s, r in zip(shown_numbers, real_numbers))


def _shown_path(page: Path) -> Path:
    """A page as the reader names it: from the repository's root, or whole if outside it."""
    return page.relative_to(ROOT) if page.is_relative_to(ROOT) else page


@dataclass
class Mismatch:
    page: Path
    line: int
    command: str
    shown: str
    nearest: str     # the real line most like it, for the reader

    def __str__(self) -> str:
        return (f"{_shown_path(self.page)}:{self.line}: not in the output of `{self.command}`\n"
                f"  page: {self.shown.strip()}\n  real: {self.nearest.strip()}")


def _nearest(shown: str, real: list[str]) -> str:
    from difflib import SequenceMatcher

    return max(real, key=lambda line: SequenceMatcher(None, shown.split(), line.split()).ratio(), default="")


def compare(page: Path, command: Command, output: str) -> list[Mismatch]:
    """Each shown line must match a real line after the one the previous shown line matched."""
    real = output.splitlines()
    at, missing = 0, []
    for number, shown in command.shown:
        hit = next((k for k in range(at, len(real)) if lines_agree(shown, real[k])), None)
        if hit is None:
            missing.append(Mismatch(page, number, command.text, shown, _nearest(shown, real)))
        else:
            at = hit + 1
    return missing


def scratch_folder(where: Path) -> Path:
    for name in INPUTS:
        shutil.copytree(ROOT / name, where / name)
    return where


def run(command: str, cwd: Path) -> str:
    """The command's stdout and stderr, interleaved as a terminal shows them."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1",
           "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"}
    done = subprocess.run(["bash", "-o", "pipefail", "-c", command], cwd=cwd, env=env, stdout=subprocess.PIPE,
                          stderr=subprocess.STDOUT, text=True, timeout=TIMEOUT_S)
    if done.returncode != 0:
        raise RuntimeError(f"`{command}` exited with {done.returncode}:\n{done.stdout[-2000:]}")
    return done.stdout


@dataclass
class PageResult:
    page: Path
    commands: int = 0
    mismatches: list[Mismatch] = field(default_factory=list)
    not_checked: list[tuple[int, str]] = field(default_factory=list)   # (block line, reason)


def check(page: Path, scratch: Path | None = None) -> PageResult:
    """Run the page's commands in order (one scratch folder for the page) and compare."""
    result = PageResult(page)
    with (nullcontext(str(scratch)) if scratch else tempfile.TemporaryDirectory(prefix="doc-outputs-")) as tmp:
        cwd = scratch_folder(Path(tmp))
        for block in blocks(page):
            if block.not_checked is not None:
                result.not_checked.append((block.line, block.not_checked))
                continue
            for command in block.commands:
                result.commands += 1
                result.mismatches += compare(page, command, run(command.text, cwd))
    return result


def pages_with_commands() -> list[Path]:
    return sorted(page for page in DOCS.rglob("*.md") if blocks(page))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tools.doc_outputs", description=__doc__.split("\n\n")[0])
    parser.add_argument("pages", nargs="*", type=Path, help="Markdown pages (default: every page with commands)")
    args = parser.parse_args(argv)
    failed = 0
    for page in [p.resolve() for p in args.pages] or pages_with_commands():
        result = check(page)
        for line, reason in result.not_checked:
            print(f"{_shown_path(page)}:{line}: not checked: {reason}")
        for mismatch in result.mismatches:
            print(mismatch)
        print(f"{_shown_path(page)}: {result.commands} commands, "
              f"{len(result.mismatches)} shown lines not in their output")
        failed += bool(result.mismatches)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())

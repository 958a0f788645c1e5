"""The C header's constants for the tests, read from runtime_c/posecorr.h itself: a test
spells a load flag or a status by its name, never by its number, so a change of the header
is a change of the tests."""
from __future__ import annotations

import re
from pathlib import Path

HEADER = (Path(__file__).resolve().parents[1] / "runtime_c" / "posecorr.h").read_text()


def _enum(start: str, end: str) -> dict[str, int]:
    """{name: value} of the enum between `start` and `end`: explicit values (`1u << 3`, `7`)
    or the count from the previous one, as C counts."""
    first = HEADER.index(start)
    body = HEADER[first:HEADER.index(end, first)]
    body = re.sub(r"/\*.*?\*/", "", body, flags=re.S)
    out, value = {}, -1
    for name, given in re.findall(r"\b(PC_[A-Z0-9_]+)\s*(?:=\s*([^,\n]+))?\s*,?", body):
        if given:
            shift = re.fullmatch(r"(\d+)u?\s*<<\s*(\d+)", given.strip())
            value = int(shift[1]) << int(shift[2]) if shift else int(given.strip().rstrip("u"), 0)
        else:
            value += 1
        out[name] = value
    return out


STATUS = _enum("typedef enum pc_status {", "} pc_status;")
LOAD = _enum("/* pc_options.flags */\nenum {", "};")
DEFINES = {name: int(value) for name, value in re.findall(r"#define (PC_[A-Z0-9_]+) (\d+)\b", HEADER)}

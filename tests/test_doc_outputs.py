"""The guides' command outputs are what the commands print (tools/doc_outputs.py): each page's
`$ posecorr ...` lines are run in order and every line the page shows must be in the output."""
from __future__ import annotations

from pathlib import Path

import pytest

from tools import doc_outputs
from tools.doc_outputs import blocks, check, lines_agree, pages_with_commands

PAGES = pages_with_commands()


def test_the_guides_with_commands_are_found():
    names = {page.name for page in PAGES}
    assert {"loop.md", "sessions.md", "ingest.md"} <= names


@pytest.mark.parametrize("page", PAGES, ids=[page.name for page in PAGES])
@pytest.mark.cpu_floats
def test_shown_outputs_are_real(page: Path):
    result = check(page)
    assert not result.mismatches, "\n".join(map(str, result.mismatches))
    # a page is either run or says why it cannot be
    assert result.commands or result.not_checked


def test_a_figure_the_code_no_longer_gives_fails():
    shown = "2       sweep_harmonics    form       8   0.1379  1.893e-11          0.0073         0.0053       no"
    real = "2       sweep_harmonics    form       8   0.1369  1.893e-11          0.0073         0.0053       no"
    assert not lines_agree(shown, real)
    assert lines_agree(real, real.replace("  ", " "))          # whitespace aside
    assert lines_agree("rmse 0.7907 mm", "rmse 0.7908 mm")      # one unit in the last decimal
    assert not lines_agree("rmse 0.7907 mm", "rmse 0.7909 mm")
    assert not lines_agree("4  sweep", "5  sweep")                # a rank is a count: exactly
    assert not lines_agree("18304 bytes", "18305 bytes")
    assert lines_agree("p = 5.337e-23", "p = 5.338e-23")
    assert not lines_agree("p = 1.9e-11", "p = 1.9e-12")
    assert not lines_agree("model: physics", "model: physics+pmc-zhou")
    assert not lines_agree("0.5 0.5", "0.5")


def test_cpu_dependent_figures_are_held_to_their_order_of_magnitude():
    line = "-> m.onnx (151 nodes, 18304 bytes, parity {} m / 5.0e-07 rad)"
    assert lines_agree(line.format("1.7e-07"), line.format("3.1e-07"))
    assert not lines_agree(line.format("1.7e-07"), line.format("2.0e-05"))
    assert lines_agree(line.format("1.7e-07").replace("18304", "18288"), line.format("1.7e-07"))
    assert not lines_agree(line.format("1.7e-07").replace("151", "152"), line.format("1.7e-07"))


def test_a_page_is_run_in_order_and_its_cuts_and_reasons_kept(tmp_path: Path):
    page = tmp_path / "page.md"
    page.write_text(
        "Text.\n\n```text\n$ printf 'a 1.50\\nb 2\\nc 3.25\\n' > out.txt && cat out.txt\na 1.50\n...\nc 3.25\n"
        "$ cat out.txt\nb 2\nc 3.28\n```\n\n"
        "<!-- outputs not checked: it takes hours -->\n```text\n$ false\nnothing\n```\n\n"
        "```text\nno command here\n```\n", encoding="utf-8")
    found = blocks(page)
    assert [len(b.commands) for b in found] == [2, 1]
    assert found[1].not_checked == "it takes hours"
    result = check(page)
    assert result.commands == 2 and result.not_checked == [(14, "it takes hours")]
    assert [(m.line, m.shown) for m in result.mismatches] == [(10, "c 3.28")]
    assert "c 3.25" in result.mismatches[0].nearest


def test_a_shown_line_out_of_order_fails(tmp_path: Path):
    page = tmp_path / "page.md"
    page.write_text("```text\n$ printf 'first\\nsecond\\n'\nsecond\nfirst\n```\n", encoding="utf-8")
    assert [m.shown for m in check(page).mismatches] == ["first"]


def test_a_failing_command_stops_the_check(tmp_path: Path):
    page = tmp_path / "page.md"
    page.write_text("```text\n$ posecorr fit missing.csv\n```\n", encoding="utf-8")
    with pytest.raises(RuntimeError, match="exited with 2"):
        check(page)


def test_the_checkout_is_not_written(tmp_path: Path):
    # `fit` appends a ledger beside its data: the commands run on copies of the inputs
    data = Path("tests/data/realdata/20200717_Exp2.csv")
    ledger = Path(f"{data}.ledger.jsonl")
    assert not (doc_outputs.ROOT / ledger).exists()
    page = tmp_path / "page.md"
    page.write_text(f"```text\n$ posecorr fit {data} --effects station,mount --method none -o m.onnx\n```\n",
                    encoding="utf-8")
    scratch = tmp_path / "scratch"
    scratch.mkdir()
    assert check(page, scratch=scratch).commands == 1
    assert (scratch / ledger).is_file() and (scratch / "m.onnx").is_file()
    assert not (doc_outputs.ROOT / ledger).exists()

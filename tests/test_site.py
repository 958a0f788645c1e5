"""The documentation site: the README fits on a screen, the site builds with `mkdocs build
--strict` (no broken link or anchor) without reaching the network, its command-line reference
is the parser's, its figures are bench/results' and every `posecorr` command the README and
the guides show is one the real parser accepts."""
from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("mkdocs")
pytest.importorskip("mkdocstrings")

from posecorr.cli import build_parser  # noqa: E402
from tools.docs_site import FigureError, cli_reference, fill_figures, load_results  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
PAGES = sorted([ROOT / "README.md", *(ROOT / "docs").rglob("*.md")])
FENCE = re.compile(r"^```(\w*)[^\n]*\n(.*?)^```", re.M | re.S)
SHELL_BLOCKS = {"", "sh", "bash", "shell", "console", "text"}
SEPARATORS = {"&&", "||", "|", ";"}
REDIRECTS = re.compile(r"^\d*[<>]")
# A command, not a program's output line ("posecorr ros2: loaded ..."): a word after posecorr.
COMMAND = re.compile(r"posecorr [\w-]+(\s|$)")
# Proxies that lead nowhere: a build that fetched anything (fonts, a plugin's assets) fails.
NO_NETWORK = {"HTTP_PROXY": "http://127.0.0.1:9", "HTTPS_PROXY": "http://127.0.0.1:9",
              "ALL_PROXY": "http://127.0.0.1:9", "NO_PROXY": "", "NO_MKDOCS_2_WARNING": "1"}


def shown_commands(text: str) -> list[tuple[int, list[str]]]:
    """(line, argv after `posecorr`) of every `posecorr VERB ...` or `$ posecorr VERB ...` in
    the text's shell and text code blocks; continuation lines joined, comments, redirections
    and what follows `&&`, `|` or `;` cut off (a `posecorr` command after them is one more)."""
    found = []
    for block in FENCE.finditer(text):
        if block.group(1) not in SHELL_BLOCKS:
            continue
        first = text.count("\n", 0, block.start(2)) + 1
        lines = block.group(2).split("\n")
        i = 0
        while i < len(lines):
            start, line = i, lines[i]
            while line.rstrip().endswith("\\") and i + 1 < len(lines):
                i += 1
                line = line.rstrip()[:-1] + " " + lines[i]
            i += 1
            line = line.strip().removeprefix("$ ")
            if not COMMAND.match(line):
                continue
            segment: list[str] = []
            redirected = False
            for token in shlex.split(line, comments=True) + [";"]:
                if token in SEPARATORS:
                    if segment[:1] == ["posecorr"]:
                        found.append((first + start, segment[1:]))
                    segment, redirected = [], False
                elif REDIRECTS.match(token) or redirected:
                    redirected = True
                else:
                    segment.append(token)
    return found


def parser_refusal(argv: list[str]) -> str | None:
    """None when the real parser accepts `posecorr ARGV`, else its message."""
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            build_parser().parse_args(argv)
        except SystemExit as exc:
            return err.getvalue().strip() or f"exit {exc.code}"
    return None


def test_readme_fits_on_a_screen():
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    assert len(text.splitlines()) <= 250
    assert "make demo" in text and "make test" in text
    picture = re.search(r"!\[[^\]]*\]\(([^)]+)\)", text)
    assert picture and (ROOT / picture.group(1)).is_file()


def test_every_shown_command_is_accepted_by_the_parser():
    bad, seen = [], 0
    for page in PAGES:
        for line, argv in shown_commands(page.read_text(encoding="utf-8")):
            seen += 1
            refusal = parser_refusal(argv)
            if refusal:
                bad.append(f"{page.relative_to(ROOT)}:{line}: posecorr {shlex.join(argv)}: {refusal}")
    assert not bad, "commands the parser refuses:\n" + "\n".join(bad)
    assert seen >= 20, f"only {seen} posecorr commands found in the docs"


def test_command_check_sees_a_wrong_verb_option_or_value():
    text = ("```sh\n$ posecorr fit d.csv -o m.onnx --effects station && posecorr info m.onnx | head\n"
            "posecorr fitt d.csv -o m.onnx\n"
            "posecorr fit d.csv \\\n    -o m.onnx --method bogus   # a comment\n"
            "posecorr apply m.onnx d.csv -o out.csv --no-such-option 2>/dev/null\n```\n"
            "```python\nposecorr fitt is not a shell line here\n```\n")
    commands = shown_commands(text)
    assert [argv[0] for _, argv in commands] == ["fit", "info", "fitt", "fit", "apply"]
    assert [line for line, _ in commands] == [2, 2, 3, 4, 6]
    assert commands[3][1][-2:] == ["--method", "bogus"]
    refused = [parser_refusal(argv) for _, argv in commands]
    assert refused[0] is None and refused[1] is None
    assert "invalid choice: 'fitt'" in refused[2]
    assert "bogus" in refused[3]
    assert "--no-such-option" in refused[4]


def _options(parser: argparse.ArgumentParser) -> dict[str, set[str]]:
    """{verb: its option strings}, walked from the parser."""
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return {verb: {s for a in p._actions for s in a.option_strings if s not in ("-h", "--help")}
            for verb, p in sub.choices.items()}


def test_cli_reference_is_the_parsers():
    page = cli_reference()
    options = _options(build_parser())
    assert len(options) >= 12
    sections = re.split(r"^## posecorr ", page, flags=re.M)[1:]
    assert [s.split("\n", 1)[0] for s in sections] == list(options)
    for section in sections:
        verb = section.split("\n", 1)[0]
        listed = set(re.findall(r"`(--?[\w-]+)`", section))
        assert options[verb] <= listed, (verb, options[verb] - listed)
    # A parser with an option the real one lacks shows it: the page is written from the parser.
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    sub.choices["fit"].add_argument("--made-up-here", help="only in this test (default %(default)s)", default=7)
    assert "`--made-up-here` | `MADE_UP_HERE` | `7` | only in this test (default 7) |" in cli_reference(parser)


def test_figures_come_from_bench_results():
    results = load_results()
    latency = json.loads((ROOT / "bench" / "results" / "latency.json").read_text())
    text = "C {{ latency: single_pose_median_us/c }} us, {{ ros2: ros2/1/run }}, {{ latency: batch %,d }}"
    assert fill_figures(text, results) == (f"C {latency['single_pose_median_us']['c']:.3g} us, "
                                          f"{json.loads((ROOT / 'bench/results/ros2.json').read_text())['ros2'][1]['run']}, "
                                          f"{latency['batch']:,d}")
    for wrong in ("{{ latency: single_pose_median_us/d }}", "{{ nowhere: x }}", "{{ latency: counts }}",
                  "{{ latency single_pose_median_us.c }}"):
        with pytest.raises(FigureError):
            fill_figures(wrong, results, "page.md")


def test_site_config_reaches_no_network():
    import yaml

    class Loader(yaml.SafeLoader):
        pass

    Loader.add_multi_constructor("", lambda loader, suffix, node: None)  # mkdocs' !ENV etc.
    config = yaml.load((ROOT / "mkdocs.yml").read_text(), Loader=Loader)
    assert config["theme"]["font"] is False             # no Google Fonts in the pages
    plugins = {next(iter(p)) if isinstance(p, dict) else p for p in config["plugins"]}
    assert not plugins & {"privacy", "social", "optimize", "blog", "git-revision-date-localized"}, plugins


@pytest.mark.slow
def test_site_builds_strict_without_network(tmp_path):
    out = tmp_path / "site"
    env = {**os.environ, **NO_NETWORK}
    run = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-q", "-d", str(out)],
                         cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    assert "fonts.googleapis" not in (out / "index.html").read_text(encoding="utf-8")   # system fonts
    cli = (out / "reference" / "cli.html").read_text(encoding="utf-8")
    for verb, options in _options(build_parser()).items():
        assert f'id="posecorr-{verb}"' in cli, verb
        assert all(o in cli for o in options), verb
    api = (out / "reference" / "api.html").read_text(encoding="utf-8")
    assert "CorrectionPipeline" in api and "test_recipe" in api     # from the docstrings
    latency = json.loads((ROOT / "bench" / "results" / "latency.json").read_text())
    runtime = (out / "guides" / "runtime-c.html").read_text(encoding="utf-8")
    assert f"{latency['single_pose_median_us']['c']:.3g}" in runtime
    for page in out.rglob("*.html"):
        assert not re.search(r"\{\{\s*\w+\s*:", page.read_text(encoding="utf-8")), page

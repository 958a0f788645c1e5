"""The generated parts of the documentation site (`make docs`, mkdocs.yml's `hooks`).

- The command-line reference, `reference/cli.md`, is written from the real parser
  (`posecorr.cli.build_parser`): every verb, its usage, its options with their defaults,
  choices and help. Nothing of it is typed by hand.
- The Python API reference reads the docstrings (mkdocstrings) from `build/docs-api/`: the
  package laid out as installed (pyproject.toml's `package-dir`: `posecorr.train` lives in
  train/, `posecorr.export` in export/), in symbolic links to the sources.
- Figures of speed and accuracy come from `bench/results/*.json`: a page writes
  `{{ latency: single_pose_median_us/c }}` (a file's stem, then a path of keys into it, list
  items by number) or `{{ latency: batch_ns_per_pose/c %.0f }}` (a format spec after `%`)
  and the build puts the stored value there. A name the JSON does not hold stops the build
  with the page, the placeholder and what is missing.

mkdocs calls `on_config`, `on_files` and `on_page_markdown`; the functions they call are
plain Python, and tests/test_site.py calls them directly.
"""
from __future__ import annotations

import argparse
import json
import re
import shutil
import tomllib
from pathlib import Path
from typing import Any

from mkdocs.plugins import event_priority

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "bench" / "results"
CLI_PAGE = "reference/cli.md"
API_SOURCES = ROOT / "build" / "docs-api"
PLACEHOLDER = re.compile(r"\{\{\s*(\w+)\s*:\s*([\w/-]+)\s*(?:%(\S+)\s*)?\}\}")
USAGE_WIDTH = 88


class FigureError(ValueError):
    """A placeholder that names no stored figure."""


# --- the command-line reference ----------------------------------------------------------

def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def _help(action: argparse.Action, prog: str) -> str:
    """The option's help with argparse's %(default)s-style fields filled in."""
    if not action.help or action.help == argparse.SUPPRESS:
        return ""
    fields = {k: v for k, v in vars(action).items() if v is not argparse.SUPPRESS}
    fields["prog"] = prog
    if fields.get("choices") is not None:
        fields["choices"] = ", ".join(map(str, fields["choices"]))
    return action.help % fields


def _cell(text: Any) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ")


def _argument(action: argparse.Action) -> str:
    if action.nargs == 0:
        return ""
    if action.choices is not None:
        return " / ".join(f"`{c}`" for c in action.choices)
    name = action.metavar or (action.dest.upper() if action.option_strings else action.dest)
    return f"`{name}`" + (" ..." if action.nargs in ("+", "*") else "")


def _default(action: argparse.Action) -> str:
    if action.nargs == 0 or action.default in (None, argparse.SUPPRESS) or action.required:
        return ""
    if isinstance(action.default, (list, tuple)):
        return ", ".join(f"`{v}`" for v in action.default)
    return f"`{action.default}`"


def verb_section(name: str, sub: argparse.ArgumentParser) -> list[str]:
    sub.formatter_class = lambda prog: argparse.HelpFormatter(prog, width=USAGE_WIDTH)
    usage = sub.format_usage().strip().removeprefix("usage: ")
    lines = [f"## posecorr {name}", "", sub.description or "", "", "```text", usage, "```", "",
             "| option | argument | default | what |", "|---|---|---|---|"]
    for action in sub._actions:
        if isinstance(action, argparse._HelpAction):
            continue
        flags = ", ".join(f"`{s}`" for s in action.option_strings) or f"`{action.dest}` (positional)"
        if action.required and action.option_strings:
            flags += " (required)"
        what = _cell(_help(action, sub.prog))
        lines.append(f"| {flags} | {_argument(action)} | {_default(action)} | {what} |")
    return lines + [""]


def cli_reference(parser: argparse.ArgumentParser | None = None) -> str:
    """The markdown of the command-line reference, from `parser` (default: posecorr's)."""
    if parser is None:
        from posecorr.cli import build_parser

        parser = build_parser()
    verbs = _subparsers(parser)
    lines = ["# Command-line reference", "",
             "Written at build time from the parser of `posecorr` (`posecorr.cli.build_parser`, "
             "`tools/docs_site.py`): what is below is what `posecorr VERB --help` accepts.", "",
             "| verb | what it does |", "|---|---|"]
    lines += [f"| [`{name}`](#posecorr-{name}) | {_cell(sub.description)} |" for name, sub in verbs.items()]
    lines.append("")
    for name, sub in verbs.items():
        lines += verb_section(name, sub)
    return "\n".join(lines)


# --- figures from bench/results -------------------------------------------------------

def load_results(folder: Path = RESULTS) -> dict[str, Any]:
    return {p.stem: json.loads(p.read_text(encoding="utf-8")) for p in sorted(folder.glob("*.json"))}


def figure(results: dict[str, Any], stem: str, path: str) -> Any:
    if stem not in results:
        raise FigureError(f"no bench/results/{stem}.json (there are: {', '.join(sorted(results))})")
    value: Any = results[stem]
    walked = []
    for key in path.split("/"):
        walked.append(key)
        if isinstance(value, list) and key.isdigit() and int(key) < len(value):
            value = value[int(key)]
        elif isinstance(value, dict) and key in value:
            value = value[key]
        else:
            raise FigureError(f"bench/results/{stem}.json has no {'/'.join(walked)}")
    if isinstance(value, (dict, list)):
        raise FigureError(f"bench/results/{stem}.json: {path} is not a single figure")
    return value


def render(value: Any, spec: str | None) -> str:
    if spec:
        return format(value, spec)
    if isinstance(value, bool) or value is None:
        return {True: "yes", False: "no", None: "-"}[value]
    if isinstance(value, int):
        return f"{value:,}"
    if isinstance(value, float):
        return f"{value:.3g}"
    return str(value)


def fill_figures(markdown: str, results: dict[str, Any], where: str = "") -> str:
    """`markdown` with every placeholder replaced by its stored figure."""
    def one(match: re.Match[str]) -> str:
        stem, path, spec = match.groups()
        try:
            return render(figure(results, stem, path), spec)
        except (FigureError, ValueError) as exc:
            raise FigureError(f"{where}: {match.group(0)}: {exc}") from None

    filled = PLACEHOLDER.sub(one, markdown)
    left = re.search(r"\{\{.*?\}\}", filled)
    if left:
        raise FigureError(f"{where}: {left.group(0)}: not a placeholder ({{{{ STEM: KEY/KEY %FORMAT }}}})")
    return filled


# --- the package as installed, for the API reference -----------------------------------

def stage_package(out: Path = API_SOURCES) -> Path:
    """`out`/posecorr laid out as the installed package, in links to the checkout's sources."""
    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
    mapping = pyproject["tool"]["setuptools"]["package-dir"]
    shutil.rmtree(out, ignore_errors=True)
    for package, source in sorted(mapping.items()):       # the root package before its subpackages
        target = out.joinpath(*package.split("."))
        if "." in package:
            target.symlink_to(ROOT / source, target_is_directory=True)
            continue
        target.mkdir(parents=True)
        for entry in (ROOT / source).iterdir():
            if entry.name != "__pycache__":
                (target / entry.name).symlink_to(entry)
    return out


# --- mkdocs hooks ------------------------------------------------------------------------

@event_priority(100)      # before mkdocstrings, which reads its paths in its own on_config
def on_config(config: Any) -> Any:
    stage_package()
    return config


def on_files(files: Any, config: Any) -> Any:
    from mkdocs.structure.files import File

    files.append(File.generated(config, CLI_PAGE, content=cli_reference()))
    return files


def on_page_markdown(markdown: str, page: Any, config: Any, files: Any) -> str:
    from mkdocs.exceptions import PluginError

    try:
        return fill_figures(markdown, load_results(), f"docs/{page.file.src_uri}")
    except FigureError as exc:
        raise PluginError(str(exc)) from None

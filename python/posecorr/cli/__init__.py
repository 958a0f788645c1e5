"""The `posecorr` command line: one entry point, one verb per job, `--json` everywhere.

Each verb is a module of this package that declares itself as a `Verb` (its arguments beside
the code that reads them, what it writes, what it needs); the dispatcher finds every module
but the helpers (`HELPERS`) and refuses one that is no verb. A new verb is one new file. Verbs import what they need when they run, so the controller-side verbs
(`apply`, `info`, `bench`) work on an install with numpy only. Every anticipated failure
(bad table, bad model file, bad option, bad output path, a missing optional package) ends
with a one-line message naming the file and exit code 2, never a traceback; SIGTERM and
Ctrl-C end a verb cleanly (exit 143 / 130), and every file is written atomically (`safeio`).
"""
from __future__ import annotations

import argparse
import importlib
import os
import pkgutil
import sys
import warnings
from typing import Any

from .. import __version__
from ..textui import did_you_mean
from . import failures
from .common import CliError, Verb

__all__ = ["CliError", "Verb", "verbs", "build_parser", "main"]

# The modules of this package that are not verbs.
HELPERS = frozenset({"__main__", "common", "failures", "options"})


def verbs() -> dict[str, Verb]:
    """{name: Verb} of every verb module of this package, in `posecorr --help` order; a
    module that is no helper and defines no `VERB = Verb(...)` is refused by name."""
    found = []
    for info in pkgutil.iter_modules(__path__):
        if info.name in HELPERS:
            continue
        module = importlib.import_module(f".{info.name}", __name__)
        verb = getattr(module, "VERB", None)
        if not isinstance(verb, Verb):
            raise TypeError(f"{module.__name__} is no verb: it defines no VERB = Verb(...) "
                            f"(a helper module belongs in posecorr.cli.HELPERS)")
        found.append((verb.rank, info.name, verb))
    return {name: verb for _, name, verb in sorted(found)}


class _Parser(argparse.ArgumentParser):
    """A bad option is one line too (`posecorr fit: error: argument --epochs: ...`), not
    the usage block first: the line names the option, `--help` shows the rest. It is the
    verb's line (`posecorr fit: error:`, `see posecorr fit --help`), and a misspelled option
    is named before the required argument it may have hidden (`--efects` for `--effects`)."""

    _words: list[str] = []  # kept for error(): an unknown option among them explains a missing required one

    def parse_known_args(self, args: Any = None, namespace: Any = None) -> tuple[argparse.Namespace, list[str]]:
        self._words = list(sys.argv[1:] if args is None else args)
        namespace, extras = super().parse_known_args(args, namespace)
        # A verb's leftovers would otherwise reach the top parser, which names itself, not the verb.
        if extras and self._subparsers is None:
            self.error(self._unrecognized(extras) or f"unrecognized arguments: {' '.join(extras)}")
        return namespace, extras

    def error(self, message: str) -> None:  # type: ignore[override]
        if message.startswith("the following arguments are required"):
            message = self._unrecognized(self._words) or message
        self.exit(failures.EXIT_USAGE, f"{self.prog}: error: {message} (see {self.prog} --help)\n")

    def _unrecognized(self, words: list[str]) -> str:
        """'unrecognized option --efects (did you mean --effects?)' for the words that look
        like options this parser does not know, "" when there are none."""
        unknown = []
        for word in words:
            if word == "--":
                break
            if not word.startswith("-") or word == "-" or self._negative_number_matcher.match(word):
                continue
            name = word.split("=", 1)[0]
            known = name in self._option_string_actions or (
                not word.startswith("--") and word[:2] in self._option_string_actions) or (
                name.startswith("--") and any(o.startswith(name) for o in self._option_string_actions))
            if not known:
                unknown.append(name)
        if not unknown:
            return ""
        offered = [o for a in self._actions if a.help != argparse.SUPPRESS for o in a.option_strings
                   if o.startswith("--")]
        words_out = [name + did_you_mean(name, offered) for name in unknown]
        return f"unrecognized option{'s' if len(unknown) > 1 else ''} {', '.join(words_out)}"


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="posecorr", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"posecorr {__version__}")
    subparsers = parser.add_subparsers(dest="verb", required=True, metavar="VERB")
    for name, verb in verbs().items():
        p = subparsers.add_parser(name, help=verb.help, description=verb.help)
        p.add_argument("--json", action="store_true", help="machine-readable output on stdout")
        verb.add_arguments(p)
        p.set_defaults(verb_entry=verb)
    return parser


def main(argv: list[str] | None = None) -> int:
    from ..safeio import Terminated, sigterm_as_interrupt

    if sys.stdout is None:  # started with stdout closed (`posecorr ... >&-`): nothing to show
        sys.stdout = open(os.devnull, "w")
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as exc:  # --help, --version, a bad option: already said
        return int(exc.code or 0)
    verb = args.verb_entry
    prefix = f"posecorr {args.verb}: "
    debug = bool(os.environ.get("POSECORR_DEBUG"))
    try:
        # Library warnings wait for the verb's end: a failure is then its one line alone.
        with sigterm_as_interrupt(), warnings.catch_warnings(record=True) as held:
            failures.check_extras(verb)
            failures.check_paths(args, verb)
            failures.check_kinds(args, verb)
            verb.run(args)
            sys.stdout.flush()
        for w in held:
            print(prefix + f"warning: {w.category.__name__}: {w.message}", file=sys.stderr)
    except BrokenPipeError:
        # The reader went away (`posecorr info m.onnx | head`): stop quietly.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return failures.EXIT_INTERNAL
    except (Terminated, KeyboardInterrupt) as exc:
        what = "terminated" if isinstance(exc, Terminated) else "interrupted"
        print(prefix + what + "; nothing half-written was left behind", file=sys.stderr)
        return failures.EXIT_TERMINATED if isinstance(exc, Terminated) else failures.EXIT_INTERRUPTED
    except ModuleNotFoundError as exc:
        print(prefix + "error: " + failures.missing_module_line(exc), file=sys.stderr)
        return failures.EXIT_USAGE
    except Exception as exc:
        if debug:
            raise
        line = failures.error_line(exc, args, verb.outputs)
        if failures.anticipated(exc):
            print(prefix + "error: " + line, file=sys.stderr)
            return failures.EXIT_USAGE
        print(prefix + f"internal error: {type(exc).__name__}: {line} "
              "(a bug: set POSECORR_DEBUG=1 for the traceback and please report it)", file=sys.stderr)
        return failures.EXIT_INTERNAL
    return 0


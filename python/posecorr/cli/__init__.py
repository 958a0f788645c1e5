"""The `posecorr` command line: one entry point, one verb per job, `--json` everywhere.

Each verb is a module of this package (`VERBS`) that declares its arguments beside the code
that reads them. Verbs import what they need when they run, so the controller-side verbs
(`apply`, `info`, `bench`) work on an install with numpy only. Every anticipated failure
(bad table, bad model file, bad option, bad output path, a missing optional package) ends
with a one-line message naming the file and exit code 2, never a traceback; SIGTERM and
Ctrl-C end a verb cleanly (exit 143 / 130), and every file is written atomically (`safeio`).
"""
from __future__ import annotations

import argparse
import importlib
import os
import sys
import warnings

from .. import __version__
from . import failures
from .common import CliError

__all__ = ["CliError", "VERBS", "build_parser", "main"]

VERBS = ("simulate", "ingest", "fit", "diagnose", "report", "sweep", "export", "demo", "info", "apply",
         "ros2", "bench")


class _Parser(argparse.ArgumentParser):
    """A bad option is one line too (`posecorr fit: error: argument --epochs: ...`), not
    the usage block first: the line names the option, `--help` shows the rest."""

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(failures.EXIT_USAGE, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="posecorr", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"posecorr {__version__}")
    subparsers = parser.add_subparsers(dest="verb", required=True, metavar="VERB")
    for name in VERBS:
        verb = importlib.import_module(f".{name}", __name__)
        p = subparsers.add_parser(name, help=verb.HELP, description=verb.HELP)
        p.add_argument("--json", action="store_true", help="machine-readable output on stdout")
        verb.add_arguments(p)
        p.set_defaults(verb_module=verb)
    return parser


def main(argv: list[str] | None = None) -> int:
    from ..safeio import Terminated, sigterm_as_interrupt

    if sys.stdout is None:  # started with stdout closed (`posecorr ... >&-`): nothing to show
        sys.stdout = open(os.devnull, "w")
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as exc:  # --help, --version, a bad option: already said
        return int(exc.code or 0)
    verb = args.verb_module
    prefix = f"posecorr {args.verb}: "
    debug = bool(os.environ.get("POSECORR_DEBUG"))
    try:
        # Library warnings wait for the verb's end: a failure is then its one line alone.
        with sigterm_as_interrupt(), warnings.catch_warnings(record=True) as held:
            failures.check_extras(verb)
            failures.check_paths(args, verb)
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
        line = failures.error_line(exc, args, verb.OUTPUTS)
        if failures.anticipated(exc):
            print(prefix + "error: " + line, file=sys.stderr)
            return failures.EXIT_USAGE
        print(prefix + f"internal error: {type(exc).__name__}: {line} "
              "(a bug: set POSECORR_DEBUG=1 for the traceback and please report it)", file=sys.stderr)
        return failures.EXIT_INTERNAL
    return 0


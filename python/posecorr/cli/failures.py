"""Before a verb runs and after it fails: the optional packages it needs, its output paths,
whether its model and table arguments hold what they should, and the one line (exit 2)
that an anticipated failure becomes."""
from __future__ import annotations

import argparse
import importlib.util
from collections.abc import Collection
from pathlib import Path

from .common import DOCUMENT, EFFECT_FILE, ESTIMATOR, MODEL, PAGE, SOURCE, STORE, TABLE, CliError, Verb, printable

EXIT_USAGE = 2
EXIT_INTERNAL = 1
EXIT_INTERRUPTED = 130
EXIT_TERMINATED = 143

# The optional dependencies, by extra, and how to get them.
EXTRA_MODULES = {
    "train": ("torch", "scipy", "sklearn", "onnx", "onnxruntime", "matplotlib", "tqdm", "threadpoolctl"),
    "ros2": ("rclpy", "geometry_msgs", "diagnostic_msgs"),
}
INSTALL_HINT = {**dict.fromkeys(EXTRA_MODULES["train"], "pip install 'posecorr[train]'"),
                "ray": "pip install 'posecorr[ray]'",
                **dict.fromkeys((*EXTRA_MODULES["ros2"], "rcl_interfaces"), "pip install 'posecorr[ros2]'")}


def check_extras(verb: Verb) -> None:
    """A verb that needs an extra fails before any work when one of its modules is missing."""
    for module in EXTRA_MODULES.get(verb.needs, ()):
        if importlib.util.find_spec(module) is None:
            raise ModuleNotFoundError(f"No module named {module!r}", name=module)


def paths(args: argparse.Namespace, outputs: Collection[str]) -> tuple[list[Path], list[Path]]:
    """(inputs, outputs) named by the parsed arguments; `outputs` are the verb's output
    argument names, every other Path argument is an input."""
    ins: list[Path] = []
    outs: list[Path] = []
    for name, value in vars(args).items():
        for item in value if isinstance(value, list) else [value]:
            if isinstance(item, Path):
                (outs if name in outputs else ins).append(item)
    return ins, outs


def check_paths(args: argparse.Namespace, verb: Verb) -> None:
    """Paths are checked before the verb runs: inputs exist and are files (a device or a
    FIFO is refused unopened), outputs are new or regular files in a writable folder and
    neither an input, an input's sidecar nor another output; so `fit d.csv -o d.csv` or
    `apply m.onnx /dev/zero` fail before any work."""
    from ..safeio import check_input, check_output

    for name, value in vars(args).items():
        if name not in verb.outputs and name not in verb.checks_itself:
            for item in value if isinstance(value, list) else [value]:
                if isinstance(item, Path):
                    check_input(item, folder_ok=name in verb.folder_inputs)
    if verb.folder_output:
        return
    ins, outs = paths(args, verb.outputs)
    for i, out in enumerate(outs):
        check_output(out, ins + outs[:i])


# The first bytes of a file, which decide its kind where they can.
_HEAD_BYTES = 4096
# What a file's name says it holds, where its first bytes leave it open.
_KIND_BY_NAME = {".onnx": MODEL, ".csv": TABLE, ".py": EFFECT_FILE, ".html": PAGE, ".htm": PAGE, ".c": SOURCE,
                 ".h": SOURCE, ".md": DOCUMENT, ".markdown": DOCUMENT, ".rst": DOCUMENT, ".tex": DOCUMENT}
# Names whose text is a table where its first line holds a comma, prose otherwise.
_TEXT_NAMES = (".txt",)
_KIND_WORD = {MODEL: "MODEL", TABLE: "DATA"}


def file_kind(path: Path) -> str | None:
    """What the file clearly holds (one of `common.KINDS`: a model, a table, `fit --save`'s
    estimator, C source, a report page, an effect file, JSON lines; or a document), None
    where unsure. Its first bytes decide where they can (the saved estimator's magic, ONNX's
    opening, an HTML page's or a JSON object's opening, a proposal's docstring; other text is
    never a model), then its name (.onnx, .csv, .py, .html, .c, .md), and text whose first
    record (comments and blank lines apart) holds a comma is a table (a .txt without one is
    a document)."""
    from ..controller.onnx_meta import starts_like_onnx
    from ..saved import MAGIC

    try:
        with open(path, "rb") as handle:
            head = handle.read(_HEAD_BYTES)
    except OSError:
        return None   # the verb's own reading says why
    by_name = _KIND_BY_NAME.get(path.suffix.lower())
    if head.startswith(MAGIC):
        return ESTIMATOR
    if starts_like_onnx(head):
        return MODEL
    text = _text(head)
    if not text:
        return by_name if by_name in (MODEL, TABLE) else None
    if text.lstrip()[:15].lower().startswith(("<!doctype html", "<html")):
        return PAGE
    if _is_proposal(text):   # whatever its name: its first line, the command, holds commas
        return EFFECT_FILE
    if text.lstrip().startswith("{"):      # JSON lines: a sweep's store, a ledger
        return STORE
    if by_name not in (None, MODEL):
        return by_name
    if "," in _first_record(text):
        return TABLE
    return DOCUMENT if path.suffix.lower() in _TEXT_NAMES else None


def _first_record(text: str) -> str:
    """The first line that is neither blank nor a comment ('#', as a table's reader skips them)."""
    return next((line for line in text.splitlines() if line.strip() and not line.startswith("#")), "")


def _is_proposal(text: str) -> bool:
    """Whether a file's text opens as the proposals `diagnose --propose` writes (their docstring)."""
    from ..analysis.proposal import OPENING

    return text.startswith(OPENING)


def _proposal_file(path: Path) -> bool:
    with open(path, "rb") as handle:
        return _is_proposal(_text(handle.read(_HEAD_BYTES)))


def _compiled_file(path: Path) -> bool:
    """Whether a C file opens with the banner `posecorr compile` writes."""
    from ..controller.to_c import BANNER

    with open(path, "rb") as handle:
        return BANNER in _text(handle.read(_HEAD_BYTES)).split("\n", 1)[0]


def _simulated_table(path: Path) -> bool:
    """Whether a table opens with the line `posecorr simulate` writes."""
    from .simulate import MARK

    with open(path, "rb") as handle:
        return _text(handle.read(_HEAD_BYTES)).startswith(f"# {MARK}")


def _applied_table(path: Path) -> bool:
    """Whether a table's header holds the columns `posecorr apply` adds."""
    from ..controller.apply import CORR_COLUMNS

    with open(path, "rb") as handle:
        return set(CORR_COLUMNS) <= set(_first_record(_text(handle.read(_HEAD_BYTES))).split(","))


# The outputs a verb replaces only where the file is its own, and how its own are known: an
# effect file or C source is the user's code unless `diagnose --propose` or `posecorr
# compile` wrote it; a table may be a session of measurements, which `simulate` or `apply`
# would replace with no way back (`ingest` rewrites its own from the recording).
_REPLACED_IF_OWN = {("diagnose", EFFECT_FILE): _proposal_file, ("compile", SOURCE): _compiled_file,
                    ("simulate", TABLE): _simulated_table, ("apply", TABLE): _applied_table}


def _a(kind: str) -> str:
    """The kind with its article: "a model", "an effect file"."""
    return f"{'an' if kind[0] in 'aeiou' else 'a'} {kind}"


def _text(head: bytes) -> str:
    """The bytes as text where they are text (UTF-8 with no control character but tabs and
    line breaks; a character cut short at the end is no fault), else ""."""
    import codecs

    try:
        text = codecs.getincrementaldecoder("utf-8")().decode(head.removeprefix(codecs.BOM_UTF8))
    except UnicodeDecodeError:
        return ""
    return text if all(c.isprintable() or c in "\t\r\n" for c in text) else ""


def _operands(verb: Verb) -> list[tuple[str, str, str]]:
    """(argument, kind, its words in the usage) of the verb's models and tables, positional
    arguments first, each as its parser declares it: ("model", MODEL, "--model MODEL")."""
    parser = argparse.ArgumentParser(add_help=False)
    verb.add_arguments(parser)
    kinds = {**dict.fromkeys(verb.models, MODEL), **dict.fromkeys(verb.tables, TABLE)}
    actions = sorted((a for a in parser._actions if a.dest in kinds), key=lambda a: bool(a.option_strings))
    return [(a.dest, kinds[a.dest], " ".join([*a.option_strings[:1], _KIND_WORD[kinds[a.dest]]])) for a in actions]


def check_kinds(args: argparse.Namespace, verb: Verb) -> None:
    """A model given where the verb takes a table, or a table where it takes a model (`apply
    DATA MODEL`, in report's order), is refused before any work, with the verb's order: the
    file's own error would say what it is not ("missing column meas_x"), not the swap; and
    so is an output that would replace a file of another kind than the verb writes there
    (`Verb.outputs`), or one of its kind that it did not write. Runs after `check_paths`: a
    FIFO is refused before it could block this read."""
    _check_outputs(args, verb)
    expected = {**dict.fromkeys(verb.models, MODEL), **dict.fromkeys(verb.tables, TABLE)}
    found = {name: file_kind(path) for name in expected if isinstance(path := getattr(args, name, None), Path)}
    wrong = {name for name, kind in found.items() if kind is not None and kind != expected[name]}
    if not wrong:
        return
    operands = _operands(verb)
    name = next(name for name, _, _ in operands if name in wrong)   # the first in the verb's order
    path, kind, want = getattr(args, name), found[name], expected[name]
    if kind == ESTIMATOR and want == MODEL:
        raise CliError(f"{path} is {_a(kind)} (fit --save), not the {want} posecorr {args.verb} takes: `posecorr "
                       f"export {path} -o MODEL.onnx` writes its model")
    if not (verb.models and verb.tables):   # no order to get wrong: what the verb takes
        raise CliError(f"{path} is {_a(kind)}, not the {want} posecorr {args.verb} takes")
    usage = " ".join(["posecorr", args.verb, *(words for _, _, words in operands)])
    raise CliError(f"{path} is {_a(kind)}, not {_a(want)}: the order is {usage}")


def _check_outputs(args: argparse.Namespace, verb: Verb) -> None:
    """An output over a file of another kind than the verb writes there, over one whose kind
    is unclear (every file a verb writes is clearly of its kind), or over one of its own kind
    that it did not write (`_REPLACED_IF_OWN`), is refused. An empty file holds nothing to lose."""
    for name, want in verb.outputs.items():
        path = getattr(args, name, None)
        if path is None or not Path(path).is_file() or Path(path).stat().st_size == 0:
            continue
        kind = file_kind(Path(path))
        if kind is None:
            raise CliError(f"{path} holds something posecorr {args.verb} does not write (not {_a(want)}): refusing to "
                           "replace it (choose another output name, or remove it)")
        if kind != want:   # a page written over a table, a table over an effect file
            raise CliError(f"{path} is {_a(kind)}, and posecorr {args.verb} writes {_a(want)} there: refusing to "
                           "replace it (choose another output name)")
        own = _REPLACED_IF_OWN.get((args.verb, kind))
        if own is not None and not own(Path(path)):   # the user's effect file, a session of measurements
            raise CliError(f"{path} is {_a(kind)} that posecorr {args.verb} did not write: refusing to replace it "
                           "(give another name, or remove it)")


def missing_module_line(exc: ModuleNotFoundError) -> str:
    name = (exc.name or "").split(".")[0]
    hint = INSTALL_HINT.get(name)
    what = f"this needs the {name} package, which is not installed" if name else str(exc)
    return what + (f": {hint}" if hint else "")


def error_line(exc: BaseException, args: argparse.Namespace, outputs: Collection[str]) -> str:
    """One line: the message, its first line only, escaped, prefixed with the input it
    concerns when it names neither a file nor an option itself."""
    if isinstance(exc, OSError) and exc.filename is not None and exc.strerror:
        message = f"{exc.filename}: {exc.strerror}"
    else:
        message = str(exc) or type(exc).__name__
    ins, outs = paths(args, outputs)
    for path in ins + outs:  # a newline in a file name must not cut the line short
        message = message.replace(str(path), printable(str(path)))
    lines = [line for line in message.splitlines() if line.strip()] or [type(exc).__name__]
    message = printable(lines[0].strip()) + (" ..." if len(lines) > 1 else "")
    # A message that starts with an option (`--cv: ...`) is that option's fault, not the table's.
    names_option = isinstance(exc, CliError) and message.startswith("-")
    if ins and not names_option and not any(printable(str(p)) in message for p in ins + outs):
        message = f"{printable(str(ins[0]))}: {message}"
    return message


def anticipated(exc: BaseException) -> bool:
    """Failures that bad input, a bad file or a bad path cause: reported in one line.
    posecorr's own exceptions (table, model, export, parity, options) count, as do the
    ValueErrors and OSErrors of the numeric and file layers below it."""
    if isinstance(exc, (ValueError, OSError, CliError, EOFError)):
        return True
    return any(cls.__module__.split(".")[0] == "posecorr" for cls in type(exc).__mro__)

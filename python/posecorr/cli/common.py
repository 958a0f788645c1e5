"""What the verbs share: the user-facing error, output in text or JSON, and the option
groups several verbs declare (`-o`, `--seed`, `--effect-file`, `--backend`, `--threads`)."""
from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping

from ..jsonable import json_default

BACKENDS = ("c", "onnxruntime")


# What a file holds: the kinds a verb reads and writes. `failures.file_kind` recognises each
# but the folder in a file already there.
MODEL, TABLE, ESTIMATOR = "model", "pose table", "saved estimator"
SOURCE, PAGE, EFFECT_FILE = "C source", "report page", "effect file"
STORE, FOLDER = "results store (JSON lines)", "folder"
KINDS = (MODEL, TABLE, ESTIMATOR, SOURCE, PAGE, EFFECT_FILE, STORE, FOLDER)
# A kind no verb writes, recognised so that none writes over one: prose (a README, notes in Markdown).
DOCUMENT = "document"


class CliError(Exception):
    """A user-facing error: printed as one line, exit code 2."""


@dataclass(frozen=True)
class Verb:
    """What a verb is: each module of this package but the helpers defines `VERB = Verb(...)`
    beside the `add_arguments` and `run` it names, and the dispatcher finds it there.

    help: one line for `posecorr --help`. rank: its place there (the work's order).
    outputs: {argument name: what it writes, one of `KINDS`} for the files it writes
    (checked before it runs; every other path argument is an input). A file already at an
    output path that is clearly of another kind (`failures.file_kind`: a table where a page
    would go) is refused, not replaced, as is one of its own kind that the verb did not write
    (a hand-written effect file where `diagnose --propose` would go). needs: the extra it
    needs (`failures.EXTRA_MODULES`), "" for none. folder_inputs: inputs that may be folders. checks_itself: path arguments it
    checks itself. folder_output: its output is a folder it fills. models, tables: the
    arguments that name a model (ONNX) and a pose table (CSV); a file clearly of the other
    kind is refused before the verb runs, with the order of its arguments (`apply DATA MODEL`).
    """

    help: str
    rank: int
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], None]
    outputs: Mapping[str, str] = field(default_factory=dict)
    needs: str = ""
    folder_inputs: tuple[str, ...] = ()
    checks_itself: tuple[str, ...] = ()
    folder_output: bool = False
    models: tuple[str, ...] = ()
    tables: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        unknown = set(self.outputs.values()) - set(KINDS)
        if unknown:
            raise ValueError(f"unknown output kind {sorted(unknown)}; the kinds are {KINDS}")


def print_json(obj: Any) -> None:
    print(json.dumps(obj, indent=2, default=json_default))


def emit(args: argparse.Namespace, payload: dict[str, Any], text: Callable[[], str]) -> None:
    if args.json:
        print_json(payload)
    else:
        print(text())


def progress(args: argparse.Namespace) -> Callable[[str], None]:
    if args.json:
        return lambda message: None
    return lambda message: print(f"  {message}", file=sys.stderr, flush=True)


def printable(text: str) -> str:
    """Control and other non-printable characters as escapes (\\x1b, \\n, \\u202e)."""
    if text.isprintable():
        return text
    return "".join(c if c.isprintable() else c.encode("unicode_escape").decode("ascii") for c in text)


# --- option groups ---------------------------------------------------------------------

def output_option(p: argparse.ArgumentParser, help: str | None = None, **kw: Any) -> None:
    from .options import file_name

    p.add_argument("-o", "--output", type=file_name, required=kw.pop("required", True), help=help, **kw)


def seed_option(p: argparse.ArgumentParser) -> None:
    from .options import SEED

    p.add_argument("--seed", type=SEED, default=0, help="seed of the random draws (default: 0)")


def effect_file_option(p: argparse.ArgumentParser) -> None:
    p.add_argument("--effect-file", action="append", type=Path,
                   help="a Python file with user effects; it is run as Python code with your rights "
                        "(like `python FILE`): give only files you trust")


def station_pose_option(p: argparse.ArgumentParser, default: str = "the paper's station") -> None:
    from .options import station_pose

    p.add_argument("--station-pose", type=station_pose, metavar="POSE", action=Given,
                   help="where the base station stood, about which sweep, range_scale and incidence bend: paper "
                        "(the paper's, eq. 23), x,y,z[,qw,qx,qy,qz] (m, unit quaternion: the station's pose in the "
                        "reference frame, looking along its -z) or tracker:x,y,z[,qw,qx,qy,qz] (in the tracker's "
                        "own frame, as SteamVR reports a base station: placed by the session's rigid fit); "
                        f"default: {default}")


def backend_option(p: argparse.ArgumentParser) -> None:
    p.add_argument("--backend", choices=BACKENDS, default="c",
                   help="what runs the model: c, posecorr's C runtime, or onnxruntime (default: c)")


def allow_options(p: argparse.ArgumentParser) -> None:
    """--allow-unbounded, --allow-unsigned: load another producer's model that lacks the
    metadata a posecorr export carries (posecorr.h's PC_LOAD_ALLOW_* flags)."""
    p.add_argument("--allow-unbounded", action="store_true",
                   help="load a model without metadata input_bounds or correction_reach (its poses are "
                        "then not checked against them)")
    p.add_argument("--allow-unsigned", action="store_true",
                   help="load a model without metadata model_digest (a digest present is always checked)")


def allow_arguments(args: argparse.Namespace) -> dict[str, bool]:
    """The keyword arguments of Corrector that allow_options set."""
    return {"allow_unbounded": args.allow_unbounded, "allow_unsigned": args.allow_unsigned}


def threads_option(p: argparse.ArgumentParser, scope: str = "") -> None:
    from .options import THREADS

    p.add_argument("--threads", type=THREADS, metavar="N",
                   help=f"threads for torch and BLAS{' ' + scope if scope else ''} (default: the cores other "
                        "processes leave idle, at least 1)")


def diagnosis_options(p: argparse.ArgumentParser) -> None:
    """The diagnosis' cross-validation (diagnose, report), its seed and its threads."""
    p.add_argument("--cv", dest="folds", type=diagnosis_folds, default=5, metavar="K", action=Given,
                   help="number of folds of the diagnosis's held-out test (whole poses), 2..1000 (default: 5); "
                        "it needs folds, so fit's none and loo are not taken (report scores the model itself "
                        "on the folds its fit used)")
    p.add_argument("--folds", dest="folds", type=diagnosis_folds, action=Renamed, new="--cv", help=argparse.SUPPRESS)
    from .options import WORKERS

    p.add_argument("--workers", type=WORKERS, metavar="N",
                   help="processes the diagnosis fits each cross-validation's folds in, side by side: the same "
                        "result, sooner on a large table (default: the cores other processes leave idle, at most "
                        "the folds)")
    seed_option(p)
    threads_option(p)


def diagnosis_workers(args: argparse.Namespace) -> int:
    """--workers, or the idle cores up to one per fold; never more than the machine's cores."""
    from ..threads import available_cores
    from .options import cores

    return min(args.workers or min(available_cores(), args.folds), cores())


def diagnosis_folds(text: str) -> int:
    """A number of folds; a word of fit's --cv (loo, none) is named as such, not as a bad integer."""
    from .options import integer

    try:
        return integer(2, 1000)(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"expected a number of folds in 2..1000, got {text!r}"
                                         + (" (the diagnosis needs folds: fit's none and loo are not taken here)"
                                            if text.strip().lower() in ("loo", "none") else "")) from None


diagnosis_folds.__name__ = "number of folds"


class Given(argparse.Action):
    """Stores the value and that the user gave it (`given(args, dest)`): an option that means
    something only beside another can then be refused where it would be ignored."""

    def __call__(self, parser: Any, namespace: argparse.Namespace, values: Any, option_string: str | None = None) -> None:
        setattr(namespace, self.dest, values)
        setattr(namespace, f"{self.dest}_given", True)


def given(args: argparse.Namespace, dest: str) -> bool:
    return bool(getattr(args, f"{dest}_given", False))


def station_pose_of(args: argparse.Namespace, model: Path, info: Mapping[str, Any]) -> str | None:
    """--station-pose where given, else the station the model at `model` was fitted about
    (its metadata `station_pose`), else None: the paper's."""
    from ..geometry import parse_station_pose

    if given(args, "station_pose"):
        return args.station_pose
    stated = info.get("station_pose")
    if stated is None:
        return None
    text = stated.get("stated") if isinstance(stated, Mapping) else None
    if not isinstance(text, str):
        raise CliError(f"{model}: metadata station_pose {json.dumps(stated)[:80]}: expected {{\"stated\": POSE, \"reference\": "
                       "[x, y, z, qw, qx, qy, qz]}, as fit writes it")
    try:
        return parse_station_pose(text, CliError).text
    except CliError as exc:
        raise CliError(f"{model}: metadata station_pose: {exc}") from None


class Renamed(Given):
    """An option's old spelling: still taken, with a note naming the new one."""

    def __init__(self, option_strings: list[str], dest: str, new: str, **kwargs: Any) -> None:
        super().__init__(option_strings, dest, **kwargs)
        self.new = new

    def __call__(self, parser: Any, namespace: argparse.Namespace, values: Any, option_string: str | None = None) -> None:
        print(f"posecorr: note: {option_string} is now {self.new} (same meaning)", file=sys.stderr)
        super().__call__(parser, namespace, values, option_string)


# --- what the option groups give --------------------------------------------------------

def apply_threads(args: argparse.Namespace, workers: int = 1) -> int:
    """--threads (or the default), before anything trains: one call at the top of a verb."""
    from ..threads import set_threads

    return set_threads(args.threads, workers)


def load_effect_files(args: argparse.Namespace, exported: bool = False, advised: bool = False) -> list[str]:
    """Load each --effect-file; `exported` (a verb that exports the fit): each of their effects
    must also trace into an ONNX graph, checked now rather than after the fit; `advised` (a
    verb whose advice is a fit with them): one that does not trace is named in a warning,
    for the fit advised would refuse it."""
    files = [str(path) for path in getattr(args, "effect_file", None) or []]
    if not files:
        return files
    from ..effects import get_effect, load_effect_file
    from ..export.effect_trace import untraceable
    from ..safeio import warn

    for path in files:
        names = load_effect_file(path, untraceable if exported else None)
        for name in names if advised else ():
            problem = untraceable(get_effect(name), Path(path).resolve())
            if problem:
                warn(f"effect file {path}: effect {name!r}: {problem}; fit refuses it until then")
    return files


def effect_names(text: str | None) -> list[str]:
    """'station,mount' -> checked names; an unknown, empty or repeated one fails naming the
    option (the fault is the option's, not the table's), an unknown one with the likely name
    and the effects a model fits."""
    from ..effects import listed_effect

    names: list[str] = []
    if not text or not text.strip():
        return names
    for name in (n.strip() for n in text.split(",")):
        try:
            effect = listed_effect(name, names, text, fitted=True)
        except ValueError as exc:
            raise CliError(f"--effects: {exc}") from None
        names.append(name)
        if effect.random:
            raise CliError(f"--effects: {name} is random measurement noise, which a simulation draws and no model "
                           "corrects; leave it out (the fit weighs the residuals by the noise it estimates)")
    return names


def model_effect_names(path: Path, info: dict[str, Any]) -> list[str]:
    """The effects the model at `path` records (its ONNX metadata, `info`), for a diagnosis to
    refit: one outside the catalogue (a user effect whose --effect-file was not given) is the
    model's to name, before any work, not the table's once the refit looks it up."""
    from ..analysis.interpretation import effect_list
    from ..effects import EFFECTS, defined_by_effect_file

    names = effect_list(info.get("effects"))   # the file's author wrote it: any type
    twice = sorted({name for name in names if names.count(name) > 1})
    if twice:   # a model applies each effect once: a refit of two copies failed on the table
        raise CliError(f"{path}: its metadata 'effects' names {', '.join(repr(n) for n in twice)} more than once, "
                       "which no fit writes: the file was edited")
    missing = [name for name in names if name not in EFFECTS]
    if missing:
        one = len(missing) == 1
        raise CliError(f"{path}: uses effect{'' if one else 's'} {', '.join(repr(n) for n in missing)}, which "
                       f"{'is' if one else 'are'} not in the catalogue: {defined_by_effect_file(len(missing))}")
    return names


def check_effect_files(path: Path, info: dict[str, Any]) -> None:
    """The model at `path`'s effects that an --effect-file defines, as that file defines them
    (its ONNX metadata, `info`, parameter by parameter), or CliError: every proposal names its
    effect session_strain, and another session's file, with other terms kept, gave the report
    and the diagnosis another model than the one fitted, without a word."""
    from ..effects import EFFECTS

    fitted = info.get("effect_params")
    for name, params in (fitted if isinstance(fitted, dict) else {}).items():
        source = EFFECTS.sources.get(name)
        if not source or not isinstance(params, dict):   # not one of a file's: the catalogue's, or unknown
            continue
        for param in EFFECTS[name].params:
            values = params.get(param.name)
            if not isinstance(values, list) or not values:   # [value, its standard error], each a list or one number
                continue
            size = len(values[0]) if isinstance(values[0], list) else 1
            if size != param.size:
                raise CliError(f"{path} was fitted with {name}.{param.name} of {size} values; {name} as "
                               f"{source} defines it has {param.size}: give the effect file the model was "
                               "fitted with")
        _check_behaviour(path, info, name, params, source)


# How far the trial poses through the file's effect may lie from what the model states (m,
# rad): the file's map evaluated again, on another machine's floats, not another map.
BEHAVIOUR_TOLERANCE = 1e-9


def _check_behaviour(path: Path, info: dict[str, Any], name: str, params: dict[str, Any], source: str) -> None:
    """CliError where `name` as `source` defines it moves the trial poses otherwise than the
    model states at its fitted values (metadata `effect_behaviour`; a model of an older
    posecorr states none)."""
    import numpy as np

    from ..effects import EFFECTS, behaviour

    stated = (info.get("effect_behaviour") or {}).get(name) if isinstance(info.get("effect_behaviour"), dict) else None
    if not isinstance(stated, list):
        return
    try:   # the file's author wrote the metadata: what is not numbers states nothing
        stated = np.asarray(stated, float).reshape(-1)
        theta = np.concatenate([np.atleast_1d(np.asarray(params[param.name][0], float))
                                for param in EFFECTS[name].params])
    except (KeyError, TypeError, ValueError, IndexError):
        return
    again = np.asarray(behaviour(name, theta))
    if again.shape != stated.shape or not np.allclose(again, stated, rtol=0.0, atol=BEHAVIOUR_TOLERANCE):
        raise CliError(f"{path} was fitted with another {name} than {source} defines: at the model's values its map "
                       "moves the same poses elsewhere (other terms, another formula): give the effect file the "
                       "model was fitted with")


def effects_help(what: str, fitted: bool = True) -> str:
    """An --effects help naming the catalogue's effects (and forms) known when the parser is
    built: those a model fits, or (`fitted` False) those a simulation draws as well."""
    from ..effects import EFFECTS

    known = [name for name, effect in EFFECTS.items() if not (fitted and effect.random)]
    return f"{what}; known: {', '.join(known)} (an --effect-file adds its own)"


def read_data(args: argparse.Namespace, advised: bool = False) -> Any:
    """The verb's table, after --threads and --effect-file (`load_effect_files`) took effect."""
    from ..data import read_table

    apply_threads(args)
    load_effect_files(args, advised=advised)
    table = read_table(args.data)
    table.station_pose = getattr(args, "station_pose", None)
    return table

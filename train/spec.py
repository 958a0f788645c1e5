"""A model described once: `ModelSpec`, the value every data-driven core is built from.

`posecorr fit` (`spec_from_options`), the sweep's grid (`protocol.build_grid`), auto's
candidates (`pipeline.auto_candidates`), the shipped models (`tools/models.py`) and `posecorr
demo` describe their cores as ModelSpecs and build them with `make(seed)`. A spec names itself
three ways: `key` (the sweep store's), `label` / `name` (the paper's tables) and `file_name`
(the shipped models'). The defaults of a network live here (`DEFAULT_*`) and nowhere else;
the MLP estimator takes its own defaults from them.

The paper's names of networks are here too: table 1's sixteen architectures
(`ARCHITECTURES`) and its numbering of the learning algorithms, read and written as
"architecture/algorithm" labels ("16/2" = 20-20-20-20 trained by Bayesian regularisation).

Reading this module needs neither scikit-learn nor torch.
"""
from __future__ import annotations

import numbers
from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from posecorr.rotations import REPRESENTATIONS

from .methods import Method, get_method
from .trainers import TRAINERS

ARCHITECTURES: tuple[tuple[int, ...], ...] = tuple(
    tuple([n] * layers) for layers in (1, 2, 3, 4) for n in (5, 10, 15, 20))
# Table 1 numbering of the learning algorithms (for the "tansig 16/2" labels).
TRAINER_NUMBERS = {t.name: t.number for t in TRAINERS.values() if t.number is not None}

# A network's defaults: table 1's architecture 16, tansig, Bayesian regularisation, MATLAB's
# 1000 epochs (the paper's best Exp III network, "Zhou-tansig-16/2").
DEFAULT_HIDDEN: tuple[int, ...] = (20, 20, 20, 20)
DEFAULT_ACTIVATION = "tansig"
DEFAULT_TRAINER = "br"
DEFAULT_EPOCHS = 1000
# The paper's best representation (its table 5), and the orientation input of the shipped network.
DEFAULT_REPRESENTATION = "zhou"


def architecture_number(hidden: Any) -> int | None:
    """1..16 of table 1, or None for an architecture outside it."""
    try:
        return ARCHITECTURES.index(tuple(int(h) for h in hidden)) + 1
    except ValueError:
        return None


def architecture_label(hidden: Any) -> str:
    """Table 1's number ("16" = 20-20-20-20) or, outside table 1, the layer sizes in
    parentheses ("(16)" = one layer of 16, "(8-8)"): a bare number always means table 1,
    so no two architectures share a label."""
    sizes = parse_hidden(hidden)
    number = architecture_number(sizes)
    return str(number) if number is not None else "(" + "-".join(map(str, sizes)) + ")"


def trainer_label(trainer: str) -> str:
    """Table 1's algorithm number ("2" = br) or the trainer's name outside table 1 ("adam")."""
    number = TRAINER_NUMBERS.get(trainer)
    return str(number) if number is not None else trainer


def network_label(hidden: Any, trainer: str) -> str:
    """The paper's "architecture/algorithm" label: "16/2", "(16)/1", "(8-8)/adam"."""
    return f"{architecture_label(hidden)}/{trainer_label(trainer)}"


def parse_network(text: str) -> tuple[tuple[int, ...], str]:
    """The inverse of ``network_label``: "16/2" -> (table 1's architecture 16, "br").

    Left of "/" a table-1 architecture number or layer sizes in parentheses ("(16)",
    "(8-8)"); right of it a table-1 algorithm number or a trainer name.
    """
    arch, sep, alg = str(text).strip().partition("/")
    arch, alg = arch.strip(), alg.strip()
    if not sep or not arch or not alg:
        raise ValueError(f"network {text!r}: expected ARCHITECTURE/ALGORITHM as in the paper, e.g. 16/2 or (8-8)/adam")
    if arch.startswith("(") and arch.endswith(")"):
        hidden = parse_hidden(arch[1:-1])
    elif arch.isdigit() and 1 <= int(arch) <= len(ARCHITECTURES):
        hidden = ARCHITECTURES[int(arch) - 1]
    else:
        raise ValueError(f"network {text!r}: architecture {arch!r} is neither a table-1 number "
                         f"(1-{len(ARCHITECTURES)}) nor layer sizes in parentheses such as (8-8)")
    by_number = {str(n): name for name, n in TRAINER_NUMBERS.items()}
    trainer = by_number.get(alg, alg)
    if trainer not in TRAINERS:
        raise ValueError(f"network {text!r}: algorithm {alg!r} is neither a table-1 number "
                         f"(1-{len(by_number)}) nor one of {', '.join(TRAINERS)}")
    return hidden, trainer


# The paper's largest network is 4 x 20; layers of a few hundred already train for hours.
LAYER_WIDTH_MAX = 1024
# The paper's deepest network has 4 hidden layers; 16 leaves room and bounds the work.
LAYER_COUNT_MAX = 16


def parse_hidden(hidden: Any) -> tuple[int, ...]:
    """(20, 20), "20,20", "20-20", "20x20", "(20-20)", 16, or a table-1 number as "#16" -> a
    tuple of ints ("" is no hidden layer: a linear network). The one grammar of layer sizes
    (the command line's included) and the one place their bounds are checked: widths in
    1..LAYER_WIDTH_MAX, at most LAYER_COUNT_MAX layers; ValueError saying which otherwise."""
    if isinstance(hidden, str):
        text = hidden.strip()
        if text.startswith("#"):
            number = text[1:]
            if not number.isdigit() or not 1 <= int(number) <= len(ARCHITECTURES):
                raise ValueError(f"a table-1 architecture is #1..#{len(ARCHITECTURES)}, got {text!r}")
            return ARCHITECTURES[int(number) - 1]
        text = text.removeprefix("(").removesuffix(")")
        parts = [p.strip() for p in text.replace("-", ",").replace("x", ",").split(",")] if text else []
        bad = next((p for p in parts if not p.isdigit()), None)
        if bad is not None:
            got = repr(bad) if bad else f"an empty one in {hidden.strip()!r}"
            raise ValueError(f"layer sizes are integers in 1..{LAYER_WIDTH_MAX}, got {got}")
        hidden = [int(p) for p in parts]
    elif isinstance(hidden, (int, np.integer)):
        hidden = [int(hidden)]
    not_whole = next((h for h in hidden if not isinstance(h, (numbers.Real, np.number)) or isinstance(h, bool)
                      or not float(h).is_integer()), None)
    if not_whole is not None:   # int() made 2.5 a layer of 2
        raise ValueError(f"layer sizes are integers in 1..{LAYER_WIDTH_MAX}, got {not_whole!r}")
    out = tuple(int(h) for h in hidden)
    wrong = next((h for h in out if not 1 <= h <= LAYER_WIDTH_MAX), None)
    if wrong is not None:
        raise ValueError(f"layer sizes are integers in 1..{LAYER_WIDTH_MAX}, got {wrong}")
    if len(out) > LAYER_COUNT_MAX:
        raise ValueError(f"at most {LAYER_COUNT_MAX} hidden layers, got {len(out)}")
    return out


@dataclass(frozen=True)
class ModelSpec:
    """One data-driven core: its method (`methods.METHODS`), the representation it corrects
    in (`rotations.REPRESENTATIONS`, checked when the core is fitted, as every estimator
    parameter), a network's settings and further estimator parameters.

    hidden / activation / trainer: None takes the defaults above; a method that is not a
    network has none (they become (), None, None). epochs: the network's epoch cap, None for
    the estimator's default (`DEFAULT_EPOCHS`); it shows in `key` only when given. options:
    further estimator parameters, {name: value} or (name, value) pairs, kept sorted (e.g.
    {"alpha": "cv"} for a PMC whose ridge penalty is cross-validated).
    """

    method: str
    representation: str = DEFAULT_REPRESENTATION
    hidden: Any = None
    activation: str | None = None
    trainer: str | None = None
    epochs: int | None = None
    options: Any = ()

    def __post_init__(self) -> None:
        entry = get_method(self.method)
        options = dict(self.options)
        settings = {f.name for f in fields(self)} & set(options)
        if settings:
            raise ValueError(f"{', '.join(sorted(settings))}: a setting of the spec, not an option")
        takes = entry.settings
        normal = {
            "hidden": parse_hidden(DEFAULT_HIDDEN if self.hidden is None else self.hidden) if "hidden" in takes else (),
            "activation": (self.activation or DEFAULT_ACTIVATION) if "activation" in takes else None,
            "trainer": (self.trainer or DEFAULT_TRAINER) if "trainer" in takes else None,
            "epochs": None if self.epochs is None or "epochs" not in takes else int(self.epochs),
            "options": tuple(sorted(options.items())),
        }
        for name, value in normal.items():
            object.__setattr__(self, name, value)

    # --- what the method is --------------------------------------------------------------
    @property
    def method_entry(self) -> Method:
        return get_method(self.method)

    @property
    def is_network(self) -> bool:
        return self.method_entry.network

    @property
    def has_core(self) -> bool:
        return self.method_entry.has_core

    @property
    def with_rotation(self) -> bool:
        """The orientation is corrected and scored: False for a position-only representation
        (an unknown one is refused when the core is fitted)."""
        representation = REPRESENTATIONS.get(self.representation)
        return representation is None or representation.orientation

    # --- building ----------------------------------------------------------------------------
    def make(self, seed: int = 0) -> Any:
        """A fresh (unfitted) core (None for a method without one); ``seed`` is a network's
        random_state (initial weights, internal validation split)."""
        settings = {"hidden": self.hidden, "activation": self.activation, "trainer": self.trainer,
                    "random_state": seed}
        if self.epochs is not None:
            settings["epochs"] = self.epochs
        return self.method_entry.make(self.representation, settings, **dict(self.options))

    # --- names ---------------------------------------------------------------------------------
    @property
    def key(self) -> str:
        """The sweep store's identifier: "zhou-pmc", "zhou-tansig-20-20-20-20-br", with the
        options (and epochs, when given) in brackets: "zhou-tansig-10-lm[epochs=100]"."""
        if self.is_network:
            base = f"{self.representation}-{self.activation}-{'-'.join(map(str, self.hidden))}-{self.trainer}"
        else:
            base = f"{self.representation}-{self.method}"
        options = sorted(self.options + ((("epochs", self.epochs),) if self.epochs is not None else ()))
        if options:
            base += "[" + ",".join(f"{k}={v}" for k, v in options) + "]"
        return base

    @property
    def label(self) -> str:
        """The paper's table label: "PMC" or "tansig 16/2" (table 1 numbering, `network_label`)."""
        if self.is_network:
            return f"{self.activation} {network_label(self.hidden, self.trainer)}"
        return self.method_entry.title or self.method

    @property
    def name(self) -> str:
        """Table 5 style name: "Zhou-PMC", "Zhou-tansig-16/2"."""
        from .tables import SHORT_REP

        rep = SHORT_REP.get(self.representation, self.representation)
        return f"{rep}-{self.label.replace(' ', '-')}"

    @property
    def stem(self) -> str:
        """The shipped models' name: "pmc-zhou", "mlp-zhou-tansig-20x20x20x20-br"."""
        base = f"{self.method}-{self.representation}"
        if self.is_network:
            base += f"-{self.activation}-{'x'.join(map(str, self.hidden))}-{self.trainer}"
        return base

    @property
    def file_name(self) -> str:
        return f"{self.stem}.onnx"


def spec_from_options(method: str = "pmc", representation: str = DEFAULT_REPRESENTATION, *, hidden: Any = None,
                      network: str | None = None, activation: str | None = None, trainer: str | None = None,
                      epochs: int | None = None, **options: Any) -> ModelSpec:
    """The spec `posecorr fit` builds from its options: ``network`` (the paper's "16/2")
    overrides ``hidden`` and ``trainer``; the method's fit parameters (`Method.fit_params`,
    e.g. a PMC's cross-validated ridge penalty) join ``options``."""
    if network is not None:
        hidden, trainer = parse_network(network)
    return ModelSpec(method, representation, hidden, activation, trainer, epochs,
                     {**get_method(method).fit_params, **options})


# `fit`'s network where none is named. The paper's (DEFAULT_HIDDEN) was trained on data sets
# of thousands of poses; a network generalises when it has about ten numbers to fit for each
# weight (the rule of thumb from Baum and Haussler's bound, examples >= weights / error, at an
# error of 0.1). A session with fewer gets the network `auto` tries: one layer of
# SESSION_HIDDEN units for SESSION_EPOCHS epochs, which trains in seconds.
SESSION_HIDDEN: tuple[int, ...] = (5,)
SESSION_EPOCHS = 200
NUMBERS_PER_WEIGHT = 10


def session_network(spec: ModelSpec, poses: int) -> tuple[ModelSpec, str]:
    """(`spec` with the network a table of `poses` poses bears, what was chosen and why) for a
    network spec built without hidden layers, epochs or a network named: the paper's network
    where the table holds NUMBERS_PER_WEIGHT numbers for each of its weights, else the
    session network. ("" and `spec` unchanged for a method that is not a network.)"""
    from dataclasses import replace

    from .base import vector_size

    if not spec.is_network:
        return spec, ""
    paper = replace(spec, hidden=DEFAULT_HIDDEN, epochs=None)
    weights = paper.make().n_weights()
    numbers = poses * vector_size(spec.representation)
    label = "-".join(map(str, DEFAULT_HIDDEN))
    if numbers >= NUMBERS_PER_WEIGHT * weights:
        return paper, (f"network {label} (the default for {poses} poses: {numbers:,} numbers for its "
                       f"{weights:,} weights)")
    small = replace(spec, hidden=SESSION_HIDDEN, epochs=SESSION_EPOCHS)
    needed = -(-NUMBERS_PER_WEIGHT * weights // vector_size(spec.representation))
    return small, (f"network {'-'.join(map(str, SESSION_HIDDEN))} (hidden units), {SESSION_EPOCHS} epochs "
                   f"(the default for {poses} poses: the paper's {label} has {weights:,} weights and wants "
                   f"{NUMBERS_PER_WEIGHT} numbers for each, {needed:,} poses; --hidden or --network to choose)")

"""The catalogue of physical effects (docs/design.md, "Physical effects"): the public contract.

Each effect is a named, parametric, differentiable map of a tracker pose (p (N, 3) m, R (N, 3, 3))
in the robot base frame. The simulator applies the effects to reference poses in catalogue
order (`order`); a correction model applies the fitted ones inverse, in reverse order.
Every formula is written once against `posecorr._xp`, so it runs on numpy arrays, on torch
tensors (differentiable in p, R and theta) and on the ONNX exporter's symbolic tensors.

Frames: nominal station rotation R_S and origin t_S (eq. 23), station coordinates of a base
point s = R_S^T (p - t_S) (the station looks along -z), workspace centre c, Exp(w) the rotation
with rotation vector w. They travel in an `EffectContext`, together with per-pose extras
(the time t in s since the start of the session) and, for `noise`, its random draws.

| order | name | theta (in this order) |
|---|---|---|
| 1 | mount | d (3, rad), e (3, m) |
| 2 | sweep | phase_x, phase_y (rad), curve_x, curve_y (1/rad) |
| 3 | range_scale | k (1) |
| 4 | incidence | b1, b2 (m) |
| 5 | drift | d (3, m), tau (s) |
| 6 | station | w (3, rad), v (3, m) |
| 7 | noise | sigma_p (m), sigma_r (rad), k2 (1/m) |

theta is a flat vector (numpy or torch, shape (size,)) holding the parameters in that order.

User effects: subclass `Effect` in a Python file, set `name`, `params` (a tuple of `Param`) and
`order` (default 5.5: after drift, before the station registration), and write `forward`
against the namespace (see `tests/data/example_effect.py`); `load_effect_file(path)` registers
it. Without an `inverse` it is inverted by the generic fixed-point iteration of `Effect.inverse`.
"""
from __future__ import annotations

import importlib.util
import numbers
import re
import sys
import warnings
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable, ClassVar, Iterable, Mapping

import numpy as np

from ._xp import namespace
from .registry import Registry
from .rotations import matrix_to_rotvec, normalize, rotvec_to_matrix
from .textui import counted

__all__ = [
    "Param", "Effect", "EffectContext", "EffectRegistry", "EFFECTS", "BUILTIN_NAMES", "FORM_NAMES", "SENSITIVITIES",
    "REGISTRATION_ROLES", "registration_effects", "registration_names", "get_effect", "register_effect",
    "unregister_effect", "to_namespace", "checked_theta",
    "parse_effects_arg", "load_effect_file", "apply_effects", "invert_effects",
    "sorted_effects", "station_coords", "from_station", "sweep_direction", "Mount", "Sweep", "RangeScale", "Incidence", "Drift", "Station", "Noise",
]


# A fitted value counts as implausible only this many standard errors beyond its plausible
# range: the data must reject every plausible value, not merely prefer a far one.
PLAUSIBLE_SIGMAS = 2.0


@dataclass(frozen=True)
class Param:
    """One named parameter block of an effect.

    default: the default magnitude (what a bare NAME on the command line means), `size` values.
    scale: typical magnitude, for scaling the fit's unknowns to O(1).
    identity: the value of each entry that makes the effect the identity (with the others 0).
    bounds: (lower, upper) a fit keeps every entry in (None: unbounded).
    domain: where the map is defined at all, whatever a fit's bounds: a key of `DOMAINS`
        ("positive" for a divisor, "nonnegative" for a standard deviation, "scale" for the k
        of a factor 1 + k).
    plausible: (lower, upper) the values a real tracker shows (None: any); a fitted value the
        data puts outside (`Effect.implausible`) is no physical explanation, and the diagnosis
        does not mark the effect present.
    unbounded: a registration's parameter: unregistered frames put it anywhere (metres, any
        rotation), so no typical size bounds it, and no prior draws it towards its identity.
    """

    name: str
    size: int
    default: tuple[float, ...]
    scale: float
    unit: str
    identity: float = 0.0
    doc: str = ""
    bounds: tuple[float, float] | None = None
    domain: str = "real"
    plausible: tuple[float, float] | None = None
    unbounded: bool = False

    def __post_init__(self) -> None:
        if isinstance(self.size, bool) or not (isinstance(self.size, numbers.Integral) and self.size >= 1):
            raise ValueError(f"parameter {self.name}: size must be a whole number >= 1, got {self.size!r}")
        if len(self.default) != self.size:
            raise ValueError(f"parameter {self.name}: default has {len(self.default)} values, size is {self.size}")
        if self.domain not in DOMAINS:
            raise ValueError(f"parameter {self.name}: domain {self.domain!r} is not one of {', '.join(DOMAINS)}")
        # each a mistake the fit would meet later as another one's (the data's, the solver's)
        if not (np.isfinite(self.scale) and self.scale > 0):
            raise ValueError(f"parameter {self.name}: scale (its typical magnitude) must be finite and > 0, "
                             f"got {self.scale!r}")
        default = np.asarray(self.default, float)
        test, words = DOMAINS[self.domain]
        if not np.all(np.isfinite(default)):
            raise ValueError(f"parameter {self.name}: default {self.default} must be finite")
        if not np.all(test(default)):
            raise ValueError(f"parameter {self.name}: default {self.default} must be {words} (domain {self.domain!r})")
        for which, span in (("bounds", self.bounds), ("plausible", self.plausible)):
            if span is not None and not _interval(span):
                raise ValueError(f"parameter {self.name}: {which} must be (lower, upper) with lower < upper, "
                                 f"got {span!r}")
        if self.bounds is not None and np.any((default < self.bounds[0]) | (default > self.bounds[1])):
            raise ValueError(f"parameter {self.name}: default {self.default} lies outside its bounds {self.bounds}")

    def unit_after(self, separator: str = " ") -> str:
        """The unit as it follows a value in a message: nothing for a dimensionless one (unit
        '1'), where "0.012 1" would read as two numbers."""
        return "" if self.unit in ("", "1") else separator + self.unit


def _interval(span: Any) -> bool:
    """Whether `span` is (lower, upper), numbers (infinite ones too) with lower < upper."""
    try:
        lower, upper = (float(v) for v in span)
    except (TypeError, ValueError):
        return False
    return lower < upper


# A parameter's domain: name -> (the test of its values, the words of the refusal).
DOMAINS: dict[str, tuple[Callable[[np.ndarray], np.ndarray], str]] = {
    "real": (np.isfinite, "finite"),
    "positive": (lambda v: v > 0, "> 0"),
    "nonnegative": (lambda v: v >= 0, ">= 0"),
    # a scale written 1 + k: at k = -1 every point collapses onto one, below it the map mirrors
    "scale": (lambda v: v > -1, "> -1"),
}


@dataclass
class EffectContext:
    """Frame constants and per-pose extras the effect maps need.

    R_S (3, 3), t_S (3,) m: nominal base_T_station (eq. 23). c (3,) m: workspace centre.
    t: (N,) seconds since the session start, or None (then `drift` is the identity).
    noise_draws: standard normal draws of `noise` ({"p": (N, 3), "r": (N, 1), "w": (N, 3)}), or None
    (then `noise` draws them from `rng`).
    """

    R_S: np.ndarray
    t_S: np.ndarray
    c: np.ndarray
    t: Any = None
    noise_draws: dict[str, np.ndarray] | None = None
    rng: np.random.Generator | None = None

    @classmethod
    def default(cls, t: Any = None, **kwargs: Any) -> "EffectContext":
        """The paper's frames (geometry.station_pose, geometry.WORKSPACE_CENTRE)."""
        from .geometry import WORKSPACE_CENTRE, station_pose

        R_S, t_S = station_pose()
        return cls(R_S, t_S, WORKSPACE_CENTRE.copy(), t=t, **kwargs)

    def subset(self, index: np.ndarray) -> "EffectContext":
        """The context of a subset of the poses (per-pose extras indexed, constants kept)."""
        draws = None if self.noise_draws is None else {k: v[index] for k, v in self.noise_draws.items()}
        return replace(self, t=None if self.t is None else self.t[index], noise_draws=draws)


def _to_namespace(p: Any, R: Any, theta: Any) -> tuple[Any, Any, Any, Any]:
    """(xp, p, R, theta) with every argument converted to the namespace of the non-numpy ones."""
    xp = namespace(p, R, theta)
    if xp.name == "numpy":
        return xp, np.asarray(p, float), np.asarray(R, float), np.asarray(theta, float)
    like = next(x for x in (p, R, theta) if _belongs(x, xp))
    p, R, theta = (x if _belongs(x, xp) else xp.const(np.asarray(x, float), like) for x in (p, R, theta))
    return xp, p, R, theta


def _belongs(x: Any, xp: Any) -> bool:
    return namespace(x).name == xp.name


to_namespace = _to_namespace


def _rotate(R: Any, v: Any) -> Any:
    """R v for (..., 3, 3) R and (..., 3) v, as a broadcast product summed over the last axis."""
    xp = namespace(R, v)
    shape = tuple(v.shape[:-1]) + (1, 3)
    return xp.sum(R * xp.reshape(v, shape), axis=-1)


def _rows_times(p: Any, M: Any) -> Any:
    """p M for row vectors p (..., 3) and one matrix M (3, 3), or one matrix per row
    (..., 3, 3) (a parameter per row: a fit's batched finite differences)."""
    xp = namespace(p, M)
    if len(M.shape) == 2:
        return xp.matmul(p, M)
    return _rotate(xp.swap_last(M), p)


# What an effect declares about itself besides its map (see `Effect`).
CAPABILITIES = ("name", "params", "order", "random", "needs_time", "closed_form_inverse", "per_row_theta",
                "changes_rotation", "changes_position", "inverse_steps", "doc", "generic", "causes", "sensitivity", "registration",
                "typical_scale", "about_station")

# The parts an effect may play in registering the tracker's frames (`Effect.registration`),
# in the order a fit identifies them: the unknown rigid motion between the tracker's reporting
# frame and the base ("frame", the catalogue's station), then the tracker's unknown pose on
# its mount ("lever", the catalogue's mount).
REGISTRATION_ROLES = ("frame", "lever")

# What the poses must vary in for an effect to show (`Effect.sensitivity`): the words of
# "cannot be determined" name the one that is missing.
SENSITIVITIES = ("position", "orientation", "time")


class Effect:
    """Base class of all effects (built-in and user-defined).

    Subclasses set `name`, `params`, `order` and implement `forward`; `inverse` defaults to a
    fixed number of fixed-point steps x <- x - (F(x) - y), which converges for near-identity
    maps (all the catalogue's are: a map that moves poses by mm and mrad). Called through
    `apply_effects` / `invert_effects`, `forward` receives p, R and theta already converted to
    one namespace (`to_namespace`), so a user's map only needs `xp = namespace(p, R, theta)`.
    """

    name: ClassVar[str] = ""
    params: ClassVar[tuple[Param, ...]] = ()
    order: ClassVar[float] = 5.5
    random: ClassVar[bool] = False          # noise-like: simulated, never fitted as a bias
    needs_time: ClassVar[bool] = False      # uses ctx.t
    closed_form_inverse: ClassVar[bool] = False
    # forward accepts theta with one row per pose (N, size): a fit then evaluates all its
    # finite-difference steps in one call. A user effect written for one theta leaves it False.
    per_row_theta: ClassVar[bool] = False
    changes_rotation: ClassVar[bool] = True  # False: the generic inverse leaves R untouched
    # False: the map leaves p untouched, so a table without reference orientations cannot show it
    changes_position: ClassVar[bool] = True
    inverse_steps: ClassVar[int] = 6
    doc: ClassVar[str] = ""
    # A generic discrepancy form (`posecorr.forms`), not a physical effect: the diagnosis
    # proposes it only where no catalogue effect explains the error.
    generic: ClassVar[bool] = False
    causes: ClassVar[str] = ""                # physical causes of this shape, in words
    sensitivity: ClassVar[str] = "position"   # one of SENSITIVITIES
    registration: ClassVar[str] = ""          # one of REGISTRATION_ROLES, or "" for none
    # Each Param.scale is the size a real tracker shows, so a fit holds a direction the data
    # pin no better than ten of them (`train.identify`). False for a form, whose scale is only
    # the unit of its coefficients.
    typical_scale: ClassVar[bool] = True
    # The map bends about where the base station stands (ctx.R_S, ctx.t_S: the nominal
    # station), not only through the frames' registration: on unregistered frames, where
    # nobody knows where the user's station stands, a verdict on it holds only if it stands there.
    about_station: ClassVar[bool] = False

    def __init_subclass__(cls, **capabilities: Any) -> None:
        """The capabilities above may be given as class keywords, all in one line:
        `class Drift(Effect, name="drift", order=5, needs_time=True)`; a user effect may set
        them as class attributes instead."""
        super().__init_subclass__()
        for key, value in capabilities.items():
            if key not in CAPABILITIES:
                raise TypeError(f"effect class {cls.__name__}: unknown capability {key!r}; "
                                f"expected one of {', '.join(CAPABILITIES)}")
            setattr(cls, key, value)

    # -- parameters ------------------------------------------------------------------
    @property
    def size(self) -> int:
        return sum(p.size for p in self.params)

    @property
    def param_names(self) -> list[str]:
        return [p.name for p in self.params]

    def slices(self) -> dict[str, slice]:
        out, i = {}, 0
        for p in self.params:
            out[p.name] = slice(i, i + p.size)
            i += p.size
        return out

    def split(self, theta: Any) -> dict[str, Any]:
        """theta (size,) -> {param name: theta[..., i:j]} (last-axis slices, exporter-safe)."""
        return {name: theta[..., s.start:s.stop] for name, s in self.slices().items()}

    def default_theta(self) -> np.ndarray:
        return np.concatenate([np.asarray(p.default, float) for p in self.params]) if self.params else np.zeros(0)

    def identity_theta(self) -> np.ndarray:
        return np.concatenate([np.full(p.size, p.identity, float) for p in self.params]) if self.params else np.zeros(0)

    def scales(self) -> np.ndarray:
        """(size,) typical magnitude of each entry of theta, for scaling a fit's unknowns."""
        return np.concatenate([np.full(p.size, p.scale, float) for p in self.params]) if self.params else np.zeros(0)

    def signature(self) -> str:
        """'d[3] rad, e[3] m': the expected values, for messages."""
        return ", ".join(f"{p.name}[{p.size}] {p.unit}" if p.size > 1 else f"{p.name} {p.unit}"
                         for p in self.params)

    def validate(self, theta: Any) -> np.ndarray:
        """theta as a float vector of the right size; ValueError naming the effect otherwise."""
        values = np.asarray(theta, dtype=float).reshape(-1)
        if values.size != self.size:
            raise ValueError(f"effect {self.name!r} takes {self.size} values ({self.signature()}), "
                             f"got {values.size}")
        if not np.all(np.isfinite(values)):
            raise ValueError(f"effect {self.name!r}: parameters must be finite, got {values.tolist()}")
        return values

    def describe(self, theta: Any) -> dict[str, list[float]]:
        """{param name: values} of a numeric theta (for reports and JSON)."""
        values = np.asarray(theta, dtype=float).reshape(-1)
        return {name: values[s].tolist() for name, s in self.slices().items()}

    def implausible(self, theta: Any, std: Any = None) -> list[str]:
        """Words for each parameter whose fitted value the data puts outside its
        `Param.plausible`: beyond it by more than `PLAUSIBLE_SIGMAS` of its standard errors
        `std` (theta's shape; NaN or None: the value alone decides). A value the data does not
        determine is no evidence: over a session of about drift's time constant the data sees
        little more than the displacement over the session, and a fit may run along that
        valley to any d."""
        values = np.asarray(theta, float).reshape(-1)
        errors = np.full(values.shape, np.nan) if std is None else np.asarray(std, float).reshape(-1)
        out = []
        for param, part in zip(self.params, self.slices().values()):
            if param.plausible is None:
                continue
            lo, hi = param.plausible
            beyond = np.maximum(lo - values[part], values[part] - hi)
            known = np.isfinite(errors[part]) & (errors[part] > 0)
            outside = beyond > PLAUSIBLE_SIGMAS * np.where(known, errors[part], 0.0)
            if np.any(outside):
                k = int(np.argmax(np.where(outside, beyond, -np.inf)))
                worst, error = values[part][k], errors[part][k]
                firm = f" ({beyond[k] / error:.2g} standard errors beyond)" if known[k] else ""
                out.append(f"{self.name}.{param.name} = {worst:.3g}{param.unit_after()} lies outside the plausible "
                           f"{lo:g} to {hi:g}{param.unit_after()}{firm}")
        return out

    def notes(self, ctx: EffectContext) -> list[str]:
        """Why the effect cannot act on this data (empty when it can)."""
        return []

    # -- its part in the registration (effects with a `registration` role) ---------------
    def start(self, rigid: Any, ctx: EffectContext, roles: frozenset[str],
              mean_turn: np.ndarray | None) -> np.ndarray | None:
        """theta where a fit starts, from the closed-form rigid registration `rigid`
        (`identify.RigidRegistration`: p_ref = R (p_meas + R_meas lever) + t, R_ref = R R_meas
        mount^T), the roles present in the model, and the chordal mean of R_ref^T R_meas (None
        without reference orientations). None: start at the identity."""
        return None

    def held_without_orientation(self) -> tuple[str, ...]:
        """Parameters a table without reference orientations cannot show (held at identity)."""
        return ()

    def frame_rotation(self, theta: Any) -> Any:
        """For the "frame" role: the rotation vector by which the effect turns orientations,
        so that a position-only table's reference orientation can be recovered from the
        measured one."""
        raise NotImplementedError(f"effect {self.name!r} plays no frame role")

    # -- maps ------------------------------------------------------------------------
    def forward(self, p: Any, R: Any, theta: Any, ctx: EffectContext) -> tuple[Any, Any]:
        """Apply the effect: reference-side pose -> measured-side pose."""
        raise NotImplementedError(f"effect {self.name!r} has no forward map")

    def inverse(self, p: Any, R: Any, theta: Any, ctx: EffectContext) -> tuple[Any, Any]:
        """Undo `forward` by `inverse_steps` fixed-point steps (positions additively, rotations by
        left-multiplying the residual rotation R_target F_R(x)^T, then one Newton-Schulz step
        back onto the rotations: the residual holds x^T x, which doubles x's departure from
        orthogonality at every step, 3.6e-7 to 3.3e-5 in six float32 steps, and a user's
        rotation effect failed the export's parity check at 4.7e-5 rad)."""
        xp, p, R, theta = _to_namespace(p, R, theta)
        x_p, x_R = p, R
        for _ in range(self.inverse_steps):  # a fixed count: unrolled in the exported graph
            f_p, f_R = self.forward(x_p, x_R, theta, ctx)
            x_p = x_p - (f_p - p)
            if self.changes_rotation:
                x_R = xp.matmul(xp.matmul(R, xp.swap_last(f_R)), x_R)
                x_R = 1.5 * x_R - 0.5 * xp.matmul(xp.matmul(x_R, xp.swap_last(x_R)), x_R)
        return x_p, x_R

    def __repr__(self) -> str:
        return f"<effect {self.name}: {self.signature()}>"


# --- the built-in catalogue -----------------------------------------------------------

class Mount(Effect, name="mount", order=1, per_row_theta=True, closed_form_inverse=True, sensitivity="orientation",
            registration="lever"):
    """Error of the tracker adapter, i.e. of end_T_tracker (eq. 22), in the tracker frame.

    p <- p + R e;  R <- R Exp(d).  d (3, rad) and e (3, m) are expressed in the tracker frame
    (a rotated and shifted tracker on its adapter). Closed-form inverse: R <- R Exp(d)^T,
    p <- p - R e (with the restored R).
    """

    params = (Param("d", 3, (2e-3, -1e-3, 5e-3), 1e-2, "rad", doc="rotation vector, tracker frame", unbounded=True),
              Param("e", 3, (2e-3, -1e-3, 1.5e-3), 1e-2, "m", doc="offset, tracker frame"))

    def start(self, rigid, ctx, roles, mean_turn):
        """With the frame registered: the rigid fit's mount and lever (e = -X lever); without
        it, the mean turn between reference and measured orientations, no lever."""
        if "frame" in roles:
            return np.concatenate([matrix_to_rotvec(rigid.mount), -rigid.mount @ rigid.lever])
        if mean_turn is None:
            return None
        return np.concatenate([matrix_to_rotvec(mean_turn), np.zeros(3)])

    def held_without_orientation(self):
        # Without reference orientations the mount rotation only turns the lever.
        return ("d",)

    def forward(self, p, R, theta, ctx):
        xp, p, R, theta = _to_namespace(p, R, theta)
        d, e = theta[..., 0:3], theta[..., 3:6]
        return p + _rotate(R, e), xp.matmul(R, rotvec_to_matrix(d))

    def inverse(self, p, R, theta, ctx):
        xp, p, R, theta = _to_namespace(p, R, theta)
        d, e = theta[..., 0:3], theta[..., 3:6]
        R0 = xp.matmul(R, xp.swap_last(rotvec_to_matrix(d)))
        return p - _rotate(R0, e), R0


def station_coords(p: Any, ctx: EffectContext) -> Any:
    xp = namespace(p)
    return _rows_times(p - xp.const(ctx.t_S, p), xp.const(ctx.R_S, p))   # (p - t_S)^T R_S = (R_S^T (p - t_S))^T


def from_station(s: Any, ctx: EffectContext) -> Any:
    xp = namespace(s)
    return xp.const(ctx.t_S, s) + _rows_times(s, xp.swap_last(xp.const(ctx.R_S, s)))


def sweep_angles(xp: Any, s: Any) -> tuple[Any, Any, Any]:
    """Sweep angles (alpha, beta) and range of station-frame points s: the inverse of
    r * sweep_direction(alpha, beta)."""
    sx, sy, sz = s[..., 0], s[..., 1], s[..., 2]
    r = xp.sqrt(xp.sum(s * s, axis=-1, keepdims=True))
    return xp.atan2(sx, -sz), xp.atan2(sy, -sz), r


def sweep_direction(xp: Any, alpha: Any, beta: Any) -> Any:
    """Unit direction s / |s| of a point at sweep angles (alpha, beta), station frame."""
    return normalize(xp.stack([xp.tan(alpha), xp.tan(beta), -1.0], axis=-1))


class Sweep(Effect, name="sweep", order=2, per_row_theta=True, inverse_steps=8, about_station=True):
    """Lighthouse sweep-angle calibration error (phase and curvature), station frame.

    alpha = atan2(s_x, -s_z), beta = atan2(s_y, -s_z) (rad), r = |s| (m);
    alpha' = alpha + phase_x + curve_x beta^2;  beta' = beta + phase_y + curve_y alpha^2;
    s' = r normalise(tan alpha', tan beta', -1);  p <- t_S + R_S s'.  R is unchanged.
    Valid in front of the station (s_z < 0). Inverse: the angles are recovered by a fixed
    number of fixed-point steps alpha <- alpha' - phase_x - curve_x beta^2 (and likewise beta),
    a contraction with factor 2 |curve| |angle| << 1.
    """

    params = (Param("phase_x", 1, (1e-3,), 1e-3, "rad", plausible=(-0.01, 0.01)),
              Param("phase_y", 1, (-1e-3,), 1e-3, "rad", plausible=(-0.01, 0.01)),
              Param("curve_x", 1, (0.02,), 1e-2, "1/rad", plausible=(-0.2, 0.2)),
              Param("curve_y", 1, (-0.02,), 1e-2, "1/rad", plausible=(-0.2, 0.2)))

    def forward(self, p, R, theta, ctx):
        xp, p, R, theta = _to_namespace(p, R, theta)
        px, py, cx, cy = theta[..., 0], theta[..., 1], theta[..., 2], theta[..., 3]
        alpha, beta, r = sweep_angles(xp, station_coords(p, ctx))
        a2 = alpha + px + cx * beta * beta
        b2 = beta + py + cy * alpha * alpha
        return from_station(r * sweep_direction(xp, a2, b2), ctx), R

    def inverse(self, p, R, theta, ctx):
        xp, p, R, theta = _to_namespace(p, R, theta)
        px, py, cx, cy = theta[..., 0], theta[..., 1], theta[..., 2], theta[..., 3]
        a2, b2, r = sweep_angles(xp, station_coords(p, ctx))
        alpha, beta = a2 - px, b2 - py
        for _ in range(self.inverse_steps):
            alpha, beta = a2 - px - cx * beta * beta, b2 - py - cy * alpha * alpha
        return from_station(r * sweep_direction(xp, alpha, beta), ctx), R


class RangeScale(Effect, name="range_scale", order=3, per_row_theta=True, closed_form_inverse=True):
    """Range scale error of the station (e.g. a wrong sensor-constellation scale).

    p <- t_S + (1 + k)(p - t_S); k dimensionless. R unchanged. Inverse: divide by (1 + k).
    """

    params = (Param("k", 1, (5e-3,), 1e-2, "1", domain="scale", plausible=(-0.02, 0.02)),)

    def forward(self, p, R, theta, ctx):
        xp, p, R, theta = _to_namespace(p, R, theta)
        t_S = xp.const(ctx.t_S, p)
        return t_S + (1.0 + theta[..., 0:1]) * (p - t_S), R

    def inverse(self, p, R, theta, ctx):
        xp, p, R, theta = _to_namespace(p, R, theta)
        t_S = xp.const(ctx.t_S, p)
        return t_S + (p - t_S) / (1.0 + theta[..., 0:1]), R


class Incidence(Effect, name="incidence", order=4, per_row_theta=True, changes_rotation=False, inverse_steps=6,
                sensitivity="orientation", about_station=True):
    """Position bias growing with the incidence angle of the station's light on the tracker.

    u = unit(p - t_S) (station -> tracker), a = R[:, 2] (tracker z axis, base frame),
    cos th = -a . u, e = unit(a - (a . u) u);  p <- p + b1 (1 - cos th) u + b2 sin th e  (b1, b2 m).
    Implemented as the identical smooth form b1 (1 + a . u) u + b2 (a - (a . u) u), since
    sin th e = a - (a . u) u for a unit a; this is also 0 where e is degenerate (th = 0 or pi).
    R unchanged. Inverse: fixed-point steps (the bias changes by ~b/|p - t_S| per metre).
    """

    params = (Param("b1", 1, (1e-3,), 1e-3, "m", doc="along the line of sight", plausible=(-5e-3, 5e-3)),
              Param("b2", 1, (1e-3,), 1e-3, "m", doc="across it, towards the tracker z axis",
                    plausible=(-5e-3, 5e-3)))

    def forward(self, p, R, theta, ctx):
        xp, p, R, theta = _to_namespace(p, R, theta)
        b1, b2 = theta[..., 0:1], theta[..., 1:2]
        u = normalize(p - xp.const(ctx.t_S, p))
        a = R[..., 2]                         # third column: the tracker z axis
        au = xp.sum(a * u, axis=-1, keepdims=True)
        return p + b1 * (1.0 + au) * u + b2 * (a - au * u), R


class Drift(Effect, name="drift", order=5, per_row_theta=True, closed_form_inverse=True, needs_time=True,
            sensitivity="time"):
    """Slow drift of the tracking solution over a session (thermal, IMU bias), base frame.

    p <- p + d (1 - exp(-t / tau)); d (3, m), tau (s), t (s since the session start) from
    ctx.t. Without a time column the effect is the identity (and warns once). Closed-form inverse.
    """

    params = (Param("d", 3, (1e-3, -5e-4, 1e-3), 1e-3, "m", plausible=(-0.02, 0.02)),
              Param("tau", 1, (3600.0,), 3600.0, "s", identity=3600.0,
                    bounds=(60.0, 1e7), doc="time constant; a minute to months", domain="positive"))

    def notes(self, ctx):
        return [] if ctx.t is not None else ["no time column t: drift is the identity"]

    def _offset(self, xp: Any, p: Any, theta: Any, ctx: EffectContext) -> Any | None:
        if ctx.t is None:
            warnings.warn("drift: the data has no time column t, so drift is the identity", stacklevel=3)
            return None
        t = ctx.t if _belongs(ctx.t, xp) else xp.const(np.asarray(ctx.t, float), p)
        t = xp.reshape(t, tuple(t.shape) + (1,))
        return theta[..., 0:3] * (1.0 - xp.exp(-t / theta[..., 3:4]))

    def forward(self, p, R, theta, ctx):
        xp, p, R, theta = _to_namespace(p, R, theta)
        off = self._offset(xp, p, theta, ctx)
        return (p if off is None else p + off), R

    def inverse(self, p, R, theta, ctx):
        xp, p, R, theta = _to_namespace(p, R, theta)
        off = self._offset(xp, p, theta, ctx)
        return (p if off is None else p - off), R


class Station(Effect, name="station", order=6, per_row_theta=True, closed_form_inverse=True, registration="frame"):
    """Error of the single-measurement station registration (eq. 23), a rigid motion about c.

    p <- c + Exp(w)(p - c) + v;  R <- Exp(w) R;  w (3, rad), v (3, m), base frame. Rotating
    about the workspace centre c (not the base origin) keeps w and v nearly uncorrelated.
    Closed-form inverse: p <- c + Exp(w)^T (p - v - c), R <- Exp(w)^T R.
    """

    params = (Param("w", 3, (2e-3, -1e-3, 3e-3), 1e-2, "rad", doc="rotation vector, base frame", unbounded=True),
              Param("v", 3, (1e-2, -5e-3, 5e-3), 1e-2, "m", doc="translation, base frame", unbounded=True))

    def start(self, rigid, ctx, roles, mean_turn):
        """measured = W(reference + R_ref e), W = (R^T, -R^T t) the inverse of the rigid fit,
        written as a rotation about c and a translation."""
        R_W, t_W = rigid.R.T, -rigid.R.T @ rigid.t
        return np.concatenate([matrix_to_rotvec(R_W), t_W - ctx.c + R_W @ ctx.c])

    def frame_rotation(self, theta):
        return theta[..., 0:3]

    def forward(self, p, R, theta, ctx):
        xp, p, R, theta = _to_namespace(p, R, theta)
        W = rotvec_to_matrix(theta[..., 0:3])
        c = xp.const(ctx.c, p)
        return c + _rows_times(p - c, xp.swap_last(W)) + theta[..., 3:6], xp.matmul(W, R)

    def inverse(self, p, R, theta, ctx):
        xp, p, R, theta = _to_namespace(p, R, theta)
        W = rotvec_to_matrix(theta[..., 0:3])
        c = xp.const(ctx.c, p)
        # p - (v + c): one subtraction from the measured position, the rest folded into one
        # constant, so a graph working metres from the tracker's origin rounds once (float32).
        return c + _rows_times(p - (theta[..., 3:6] + c), W), xp.matmul(xp.swap_last(W), R)


class Noise(Effect, name="noise", order=7, random=True):
    """Random measurement noise (simulated only; never fitted as a bias, has no inverse).

    p <- p + sigma_p n_p + k2 r^2 n_r u;  R <- R Exp(sigma_r n_w), with n_p, n_w ~ N(0, I_3),
    n_r ~ N(0, 1) per pose, r = |p - t_S| (m), u = unit(p - t_S). sigma_p (m), sigma_r (rad,
    per axis, tracker frame), k2 (1/m: the range-noise standard deviation is k2 r^2 metres).
    The draws come from ctx.noise_draws (so two tables can share them) or else ctx.rng.
    """

    params = (Param("sigma_p", 1, (3e-4,), 1e-4, "m", domain="nonnegative"),
              Param("sigma_r", 1, (5e-4,), 1e-4, "rad", domain="nonnegative"),
              Param("k2", 1, (2e-4,), 1e-4, "1/m", domain="nonnegative"))

    @staticmethod
    def draw(rng: np.random.Generator, n: int) -> dict[str, np.ndarray]:
        """Standard normal draws for n poses: {"p": (n, 3), "r": (n, 1), "w": (n, 3)}."""
        return {"p": rng.standard_normal((n, 3)), "r": rng.standard_normal((n, 1)), "w": rng.standard_normal((n, 3))}

    def forward(self, p, R, theta, ctx):
        xp, p, R, theta = _to_namespace(p, R, theta)
        draws = ctx.noise_draws
        if draws is None:
            rng = ctx.rng if ctx.rng is not None else np.random.default_rng()
            draws = self.draw(rng, int(np.prod(p.shape[:-1])))
        n_p, n_r, n_w = (xp.const(np.asarray(draws[k], float).reshape(tuple(p.shape)[:-1] + (-1,)), p)
                         for k in ("p", "r", "w"))
        sigma_p, sigma_r, k2 = theta[..., 0:1], theta[..., 1:2], theta[..., 2:3]
        d = p - xp.const(ctx.t_S, p)
        r2 = xp.sum(d * d, axis=-1, keepdims=True)
        p_out = p + sigma_p * n_p + k2 * r2 * n_r * normalize(d)
        return p_out, xp.matmul(R, rotvec_to_matrix(sigma_r * n_w))

    def inverse(self, p, R, theta, ctx):
        raise TypeError("noise is random: it has no inverse and is never fitted as a bias")


# --- registry -------------------------------------------------------------------------

class EffectRegistry(Registry):
    """The catalogue, the forms and the user's effects, in application order; each entry
    remembers its source file ("" for built-ins), so loading the same file again replaces its
    effects while another file (or the catalogue) keeps its names."""

    def __init__(self) -> None:
        super().__init__("effect")
        self.sources: dict[str, str] = {}

    def add(self, name: str, entry: Any, source: str = "") -> Any:
        if name in self and self.sources.get(name, "") != source:
            where = self.sources.get(name) or "the built-in catalogue"
            raise ValueError(f"effect {name!r} is already defined by {where}")
        self[name] = entry
        self.sources[name] = source
        ordered = sorted(self.values(), key=lambda e: e.order)   # stable for equal orders
        self.clear()
        self.update({e.name: e for e in ordered})
        return entry

    def remove(self, name: str) -> None:
        self.lookup(name)
        if not self.sources[name]:
            raise ValueError(f"effect {name!r} is built in and cannot be removed")
        del self[name], self.sources[name]


EFFECTS = EffectRegistry()


def register_effect(effect: Effect | type[Effect], source: str = "") -> Effect:
    """Add an effect (instance or class) to the catalogue; built-in names cannot be replaced."""
    if isinstance(effect, type):
        effect = effect()
    name = effect.name
    if not name or not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", name):
        raise ValueError(f"effect class {type(effect).__name__} needs a name that is an identifier, got {name!r}")
    for p in effect.params:
        if not isinstance(p, Param):
            raise ValueError(f"effect {name!r}: params must be Param instances, got {p!r}")
    for capability, allowed in (("sensitivity", SENSITIVITIES), ("registration", ("",) + REGISTRATION_ROLES)):
        if getattr(effect, capability) not in allowed:
            raise ValueError(f"effect {name!r}: {capability} must be one of "
                             f"{', '.join(repr(a) for a in allowed)}, got {getattr(effect, capability)!r}")
    return EFFECTS.add(name, effect, source)


for _cls in (Mount, Sweep, RangeScale, Incidence, Drift, Station, Noise):
    register_effect(_cls)

BUILTIN_NAMES: tuple[str, ...] = tuple(EFFECTS)

# The forms subclass Effect (defined above) and register themselves when their module ends,
# so that importing posecorr.forms first works too.
from . import forms as _forms  # noqa: E402,F401


def __getattr__(name: str) -> Any:
    # Computed when asked: were posecorr.forms imported first, it registers after this module ends.
    if name == "FORM_NAMES":
        return tuple(key for key, effect in EFFECTS.items() if effect.generic)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def unregister_effect(name: str) -> None:
    """Remove a user effect from the catalogue (built-ins stay)."""
    EFFECTS.remove(name)


def get_effect(name: str) -> Effect:
    """The registered effect called `name`; ValueError listing the known ones otherwise."""
    return EFFECTS.lookup(name)


def defined_by_effect_file(count: int = 1) -> str:
    """What a message says of `count` effects outside the catalogue: one phrasing wherever one
    is named (an --effects list, a model's metadata)."""
    return f"give the --effect-file that defines {'it' if count == 1 else 'them'}"


def listed_effect(name: str, seen: Iterable[str], text: str, fitted: bool = False) -> Effect:
    """The effect an item of the list `text` names, the items before it `seen`: ValueError
    where the name is empty (two separators in a row, or one at an end), unknown (naming the
    effects a model fits where `fitted`, else every effect, and the --effect-file an effect of
    the user's own needs) or given twice, which a fit would take as two copies of one effect
    and a simulation as one."""
    if not name:
        raise ValueError(f"an effect name is empty in {text!r} (two separators in a row, or one at an end)")
    # a name of the user's own, its --effect-file forgotten, is as likely as a misspelling
    effect = EFFECTS.lookup(name, [n for n, e in EFFECTS.items() if not e.random] if fitted else None,
                            hint=f"for an effect of your own, {defined_by_effect_file()}")
    if name in seen:
        raise ValueError(f"effect {name!r} is given twice in {text!r}")
    return effect


def require_time(names: Iterable[str], table: Any) -> None:
    """TableError before any work where an effect of `names` works on time (`needs_time`,
    drift) and the PoseTable `table` has no time column."""
    from .data import TableError

    timed = [name for name in names if get_effect(name).needs_time]
    if timed and table.time() is None:
        raise TableError(table.path, f"{', '.join(timed)} {'needs' if len(timed) == 1 else 'need'} each pose's time "
                         "(seconds since the session's start), and the table has no such column", column="t")


def registration_effects() -> dict[str, str]:
    """{role: name} of the registered effects that play a registration role (the first of each)."""
    out: dict[str, str] = {}
    for name, effect in EFFECTS.items():
        if effect.registration:
            out.setdefault(effect.registration, name)
    return out


def registration_names() -> list[str]:
    """The registration effects' names, frame first (`REGISTRATION_ROLES`): station, mount."""
    roles = registration_effects()
    return [roles[role] for role in REGISTRATION_ROLES if role in roles]


def sorted_effects(names: Iterable[str] | str) -> list[Effect]:
    """The named effects in application order: `names` an iterable of names or one string of
    them with commas, as the command line takes them (a string was iterated letter by
    letter: "unknown effect 's'")."""
    if isinstance(names, str):
        names = [name.strip() for name in names.split(",")]
    return sorted((get_effect(n) for n in names), key=lambda e: e.order)


def load_effect_file(path: str | Path, check: Callable[[Effect, Path], str | None] | None = None) -> list[str]:
    """Import a user's Python file and register every `Effect` subclass it defines.

    Returns the registered names. Loading the same file again re-registers its effects. Each
    effect's forward map is tried on a few poses, and `check(effect, path)` (what is wrong,
    or None) is asked too; a problem unregisters the file's effects and raises ValueError.
    """
    path = Path(path).resolve()
    if not path.is_file():
        raise ValueError(f"effect file {path} does not exist")
    module_name = "posecorr_user_effects_" + re.sub(r"\W", "_", str(path))
    spec = importlib.util.spec_from_file_location(module_name, path)
    if spec is None or spec.loader is None:
        raise ValueError(f"effect file {path} cannot be imported as Python")
    module = importlib.util.module_from_spec(spec)
    sys.modules[module_name] = module
    try:
        spec.loader.exec_module(module)
    except (Exception, SystemExit) as exc:  # a file calling sys.exit() must not end posecorr
        del sys.modules[module_name]
        raise ValueError(f"effect file {path}: {type(exc).__name__}: {exc}") from None
    classes = [obj for obj in vars(module).values()
               if isinstance(obj, type) and issubclass(obj, Effect) and obj.__module__ == module_name]
    if not classes:
        raise ValueError(f"effect file {path} defines no subclass of posecorr.effects.Effect")
    names = _register_file(classes, path)
    for name in names:
        problem = _trial_forward(get_effect(name), path) or (check(get_effect(name), path) if check else None)
        if problem:
            for registered in names:
                unregister_effect(registered)
            raise ValueError(f"effect file {path}: effect {name!r}: {problem}")
    return names


def _register_file(classes: list[type[Effect]], path: Path) -> list[str]:
    """Register the classes of the effect file `path`, all or none. A name two of its classes
    share is refused (the second replaced the first in silence), and a refusal names the file:
    its fault, not that of the table the verb reads."""
    first: dict[str, str] = {}
    for cls in classes:
        name = getattr(cls, "name", "")
        if name and name in first:
            raise ValueError(f"effect file {path}: classes {first[name]} and {cls.__name__} are both named {name!r}; "
                             "give each effect its own name")
        first[name] = cls.__name__
    names: list[str] = []
    try:
        for cls in classes:
            names.append(register_effect(cls, source=str(path)).name)
    except ValueError as exc:
        for registered in names:
            unregister_effect(registered)
        raise ValueError(f"effect file {path}: {exc}") from None
    return names


def raised_in(exc: BaseException, path: str | Path) -> str:
    """'TypeError: message (line 11: the line)': an exception a user's effect file raised,
    with the last line of that file it passed through."""
    import traceback

    frames = [f for f in traceback.extract_tb(exc.__traceback__) if Path(f.filename) == Path(path).resolve()]
    where = f" (line {frames[-1].lineno}: {frames[-1].line})" if frames else ""
    return f"{type(exc).__name__}: {exc}{where}"


# The poses a user effect is tried on when its file loads: about the workspace centre,
# turned every way, a few seconds apart.
_TRIAL_POSES = 4


def _trial() -> tuple[np.ndarray, np.ndarray, EffectContext]:
    """The poses (p, R) a user effect is tried on, and their context."""
    ctx = EffectContext.default(t=np.arange(_TRIAL_POSES) * 5.0, rng=np.random.default_rng(0))
    p = ctx.c + np.linspace(-0.2, 0.2, _TRIAL_POSES * 3).reshape(_TRIAL_POSES, 3)
    R = rotvec_to_matrix(np.linspace(-1.0, 1.0, _TRIAL_POSES * 3).reshape(_TRIAL_POSES, 3))
    return p, R, ctx


def behaviour(name: str, theta: Any) -> list[float]:
    """What the effect `name` does at `theta` to the trial poses: their positions and rotation
    vectors after its forward map, flat. A model states it for each of its effects an effect
    file defines, so that another file's effect of the same name and sizes (a proposal of
    another session, other terms kept) is told apart from the one it was fitted with."""
    p, R, ctx = _trial()
    with np.errstate(all="ignore"):
        q, Q = get_effect(name).forward(p, R, np.asarray(theta, float), ctx)
    return [float(v) for v in np.concatenate([np.asarray(q, float).ravel(),
                                               matrix_to_rotvec(np.asarray(Q, float)).ravel()])]


def _trial_forward(effect: Effect, path: Path) -> str | None:
    """What is wrong with `effect.forward` on a few poses at its default theta (an exception,
    with the line of `path` it came from, or an output of the wrong shape or not finite);
    None when nothing is. Said at load, not as a fit's error naming the data file."""
    p, R, ctx = _trial()
    call = f"forward(p, R, theta, ctx) on {_TRIAL_POSES} poses at its default theta"
    try:
        with np.errstate(all="ignore"):   # a non-finite result is named below, in one line
            out = effect.forward(p, R, effect.default_theta(), ctx)
    except Exception as exc:  # the user's code: any exception is its error
        return f"{call} raised {raised_in(exc, path)}"
    if not (isinstance(out, tuple) and len(out) == 2):
        return f"{call} returned {type(out).__name__}, expected the pair (p, R)"
    for name, value, shape in (("p", out[0], p.shape), ("R", out[1], R.shape)):
        value = np.asarray(value)
        if value.shape != shape:
            return f"{call} returned {name} of shape {value.shape}, expected {shape}"
        if not np.all(np.isfinite(value)):
            return f"{call} returned {name} with values that are not finite"
    # what the effect says of itself decides what a fit undoes and what a table must hold
    turn = np.linalg.norm(matrix_to_rotvec(np.swapaxes(R, -1, -2) @ np.asarray(out[1], float)), axis=-1).max()
    if not effect.changes_rotation and turn > 1e-9:
        return (f"{call} turns R (by up to {turn:.3g} rad), but the effect says changes_rotation = False, and the "
                "fit would not undo the turn: set changes_rotation = True")
    if not (effect.needs_time or effect.random) and not _same_without_time(effect, p, R, out, ctx):
        return (f"{call} reads ctx.t, the poses' times, but the effect does not say needs_time = True (a table "
                "without a t column would give it none): set needs_time = True")
    return None


def _same_without_time(effect: Effect, p: np.ndarray, R: np.ndarray, out: tuple, ctx: EffectContext) -> bool:
    """Whether `effect.forward` gives `out` again when `ctx` has no times."""
    try:
        with np.errstate(all="ignore"):
            again = effect.forward(p, R, effect.default_theta(), replace(ctx, t=None))
        return all(np.array_equal(np.asarray(a, float), np.asarray(b, float)) for a, b in zip(again, out))
    except Exception:  # the user's code, reading the times it was not given
        return False


def parse_effects_arg(text: str) -> dict[str, np.ndarray]:
    """Parse the CLI syntax 'NAME=V1,V2,...;NAME;NAME=off' into {name: theta}.

    Values are in parameter order; a bare NAME means its default magnitude; NAME=off gives
    None (remove the effect from a base mix). Bare names may also be separated by ','
    ('sweep,range_scale'): an item without '=' has no values for ',' to separate. ValueError
    on unknown or empty names, wrong value counts, non-numbers or a name given twice.
    """
    out: dict[str, np.ndarray | None] = {}
    if not text.strip():
        return out  # type: ignore[return-value]
    items = [s.strip() for s in text.split(";")]
    for item in (part.strip() for s in items for part in (s.split(",") if "=" not in s else [s])):
        name, sep, values = (s.strip() for s in item.partition("="))
        if "," in name:
            raise ValueError(f"unknown effect {name!r}: separate effects with ';', as values take ',' "
                             "(sweep;drift=0.002,-0.001,0.0015,1800)")
        effect = listed_effect(name, out, text)
        if not sep:
            out[name] = effect.default_theta()
            continue
        if values.lower() == "off":
            out[name] = None
            continue
        try:
            numbers = [float(v) for v in values.split(",")]
        except ValueError:
            stray = next((v.strip() for v in values.split(",") if v.strip() in EFFECTS), None)
            raise ValueError(f"effect {name!r}: expected {counted(effect.size, 'number')} "
                             f"({effect.signature()}), got {values!r}"
                             + (f"; separate effects with ';', as values take ',' ({name}=...;{stray})" if stray
                                else "")) from None
        out[name] = checked_theta(effect, numbers)
    return out  # type: ignore[return-value]


def checked_theta(effect: Effect, theta: Any) -> np.ndarray:
    """Validate a numeric theta for `effect`: size, finiteness and each parameter's `domain`."""
    values = effect.validate(theta)
    for param, part in zip(effect.params, effect.slices().values()):
        test, words = DOMAINS[param.domain]
        if not np.all(test(values[part])):
            got = values[part].tolist()
            raise ValueError(f"effect {effect.name!r}: {param.name} must be {words}{param.unit_after()}, "
                             f"got {got[0] if len(got) == 1 else got}")
    return values


# --- chains ---------------------------------------------------------------------------

def apply_effects(p: Any, R: Any, effects: Mapping[str, Any], ctx: EffectContext) -> tuple[Any, Any]:
    """Apply {name: theta} in application order (reference -> measured)."""
    for effect in sorted_effects(effects):
        # Convert first so a user's forward always sees p, R and theta of one namespace.
        _, p, R, theta = _to_namespace(p, R, effects[effect.name])
        p, R = effect.forward(p, R, theta, ctx)
    return p, R


def invert_effects(p: Any, R: Any, effects: Mapping[str, Any], ctx: EffectContext) -> tuple[Any, Any]:
    """Undo {name: theta} in reverse application order (measured -> reference); random effects are skipped."""
    for effect in reversed(sorted_effects(effects)):
        if not effect.random:
            _, p, R, theta = _to_namespace(p, R, effects[effect.name])
            p, R = effect.inverse(p, R, theta, ctx)
    return p, R

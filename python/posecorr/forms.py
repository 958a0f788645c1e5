"""Generic discrepancy forms: low-order shapes of error beside the physical catalogue.

A real tracker is not bound by the catalogue (`posecorr.effects`). When the catalogue leaves a
held-out error that a low-order field of the workspace explains, the diagnosis tests these
forms exactly like catalogue effects (held-out score and prediction tests, a gain in every
fold, a minimum gain) and proposes the smallest that captures the gain (`posecorr diagnose --propose`). Each
form is an `Effect`: written once against the array namespace, so it fits (numpy), trains
(torch), exports to ONNX and runs in the C runtime like the catalogue's.

d = p - c is the position relative to the workspace centre c (m); a = R[:, 2] the tracker's z
axis in the base frame; Exp(w) the rotation with rotation vector w.

| name | size | form |
|---|---|---|
| strain | 6 | p <- p + S d, S symmetric (its skew part is a rotation: the station's) |
| quadratic | 18 | p_i <- p_i + sum_m q_im m(d), m the six second-order monomials of d |
| orientation_field | 9 | R <- Exp(G d) R (a small rotation varying linearly over the workspace) |
| orientation_bias | 9 | p <- p + K a (a bias that turns with the tracker; K = e I is a rigid lever: the mount's) |
| time_trend | 6 | p <- p + u1 (t / T) + u2 (t / T)^2, T = 1000 s |
| sweep_harmonics | 8 | alpha' = alpha + sum_k (a_k cos k alpha + b_k sin k alpha), k = 1, 2 (likewise beta) |

Each form declares `causes`: in words, the physical causes that produce its shape, for the
proposal's text, and `labels`: one short name per coefficient. A session's proposal keeps only
the coefficients its data needs (`Form.keeping`: SINDy's sparse regression over a library of
terms, here over one form's terms): the others are held at zero, so the effect file says which
terms the error has and fits fewer numbers on few poses.
"""
from __future__ import annotations

from typing import Any, ClassVar, Sequence

import numpy as np

from ._xp import namespace
from .effects import (Effect, Param, _to_namespace, from_station, register_effect, station_coords,
                      sweep_angles, sweep_direction)
from .rotations import rotvec_to_matrix

TIME_SCALE_S = 1000.0


class Form(Effect):
    """A generic form: a field of `labels` coefficients, all fitted, or only `terms` (indices
    into `labels`, the others held at zero) in a subclass made by `keeping`."""

    labels: ClassVar[tuple[str, ...]] = ()
    terms: ClassVar[tuple[int, ...] | None] = None
    typical_scale = False   # the scale is the coefficients' unit: real errors run to many of it

    def __init__(self) -> None:
        if self.terms is not None:
            self._check_terms(self.name, self.terms, self.size)
            # theta (..., kept) @ select = the full coefficients: one product in every namespace
            self._select = np.zeros((len(self.terms), len(self.labels)))
            self._select[np.arange(len(self.terms)), list(self.terms)] = 1.0

    @classmethod
    def _check_terms(cls, name: str, terms: Sequence[Any], size: int) -> None:
        terms = tuple(terms)
        if (len(set(terms)) != len(terms) or len(terms) != size
                or any(not isinstance(t, int) or not 0 <= t < len(cls.labels) for t in terms)):
            raise ValueError(f"effect {name!r}: terms must be {size} distinct indices of its "
                             f"{len(cls.labels)} coefficients ({', '.join(cls.labels)}), got {terms}")

    def coefficients(self, theta: Any) -> Any:
        """The full coefficient vector (..., len(labels)) of a theta that keeps `terms`."""
        if self.terms is None:
            return theta
        xp = namespace(theta)
        return xp.matmul(theta, xp.const(self._select, theta))

    def term_labels(self) -> list[str]:
        """The labels of the coefficients this effect fits."""
        return list(self.labels) if self.terms is None else [self.labels[t] for t in self.terms]

    @classmethod
    def keeping(cls, terms: Sequence[int], name: str, values: Sequence[float] | None = None) -> type["Form"]:
        """A subclass of this form that fits only `terms` (defaults `values`, else zero)."""
        terms = tuple(int(t) for t in terms)
        cls._check_terms(name, terms, len(terms))
        first = cls.params[0]
        default = tuple(float(v) for v in values) if values is not None else (0.0,) * len(terms)
        # one block of the form's unit; named as the form's block when it has one
        param = Param(first.name if len(cls.params) == 1 else "c", len(terms), default, first.scale, first.unit,
                      doc="coefficients of " + ", ".join(cls.labels[t] for t in terms))
        return type(f"{cls.__name__}Terms", (cls,), {"name": name, "terms": terms, "params": (param,),
                                                     "generic": False, "__doc__": cls.__doc__})


def _centred(p: Any, ctx: Any) -> Any:
    xp = namespace(p)
    return p - xp.const(ctx.c, p)


def _rows(theta: Any, first: int, d: Any) -> Any:
    """(..., 1): sum_j theta[..., first + j] d[..., j], one row of a 3 x n matrix times d."""
    xp = namespace(theta, d)
    n = d.shape[-1]
    return xp.sum(theta[..., first:first + n] * d, axis=-1, keepdims=True)


def _matrix_times(theta: Any, first: int, d: Any) -> Any:
    """(..., 3): M d for M the 3 x n matrix stored row by row in theta[..., first:first + 3n]."""
    xp = namespace(theta, d)
    n = d.shape[-1]
    return xp.concat([_rows(theta, first + i * n, d) for i in range(3)], axis=-1)


class Strain(Form, name="strain", order=5.7, per_row_theta=True, changes_rotation=False, generic=True,
             causes="a strain of the tracking space: a wrong base-station geometry (the stations' distance "
                    "or angle between them) or a scale of one sweep axis"):
    """An affine strain of the tracking space about the workspace centre.

    p <- p + S d, S symmetric (s_xx, s_yy, s_zz, s_xy, s_xz, s_yz, dimensionless); R unchanged.
    A uniform S = k I is `range_scale` seen about c; the skew part of a general affine map is
    a rotation, which the station registration holds. Inverted by fixed-point steps.
    """

    labels = ("s_xx", "s_yy", "s_zz", "s_xy", "s_xz", "s_yz")
    params = (Param("s", 6, (2e-3, -1e-3, 1e-3, 5e-4, -5e-4, 5e-4), 1e-3, "1",
                    doc="S entries xx, yy, zz, xy, xz, yz"),)

    def forward(self, p, R, theta, ctx):
        xp, p, R, theta = _to_namespace(p, R, theta)
        theta = self.coefficients(theta)
        d = _centred(p, ctx)
        s = [theta[..., k:k + 1] for k in range(6)]
        dx, dy, dz = d[..., 0:1], d[..., 1:2], d[..., 2:3]
        shift = xp.concat([s[0] * dx + s[3] * dy + s[4] * dz,
                           s[3] * dx + s[1] * dy + s[5] * dz,
                           s[4] * dx + s[5] * dy + s[2] * dz], axis=-1)
        return p + shift, R


def _monomials(d: Any) -> Any:
    xp = namespace(d)
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    return xp.stack([x * x, y * y, z * z, x * y, x * z, y * z], axis=-1)


class Quadratic(Form, name="quadratic", order=5.8, per_row_theta=True, changes_rotation=False, generic=True,
                causes="a curved tracking space: a lens or sweep-curvature error of a base station, or "
                       "a reference (the robot's) whose own calibration bends its workspace"):
    """A second-order field of position over the workspace.

    p_i <- p_i + sum_m q_im m(d), m = (dx^2, dy^2, dz^2, dx dy, dx dz, dy dz) (1/m), q stored
    row by row (x's six, then y's, then z's); R unchanged. Inverted by fixed-point steps.
    """

    labels = tuple(f"{axis} on {m}" for axis in "xyz" for m in ("dx^2", "dy^2", "dz^2", "dx dy", "dx dz", "dy dz"))
    params = (Param("q", 18, (2e-3,) + (0.0,) * 8 + (-2e-3,) + (0.0,) * 7 + (1e-3,), 1e-3, "1/m",
                    doc="coefficients of x, y, z on dx^2, dy^2, dz^2, dx dy, dx dz, dy dz"),)

    def forward(self, p, R, theta, ctx):
        xp, p, R, theta = _to_namespace(p, R, theta)
        theta = self.coefficients(theta)
        return p + _matrix_times(theta, 0, _monomials(_centred(p, ctx))), R


class OrientationField(Form, name="orientation_field", order=5.75, per_row_theta=True, generic=True,
                       closed_form_inverse=True, changes_position=False,
                       causes="an orientation error that varies over the workspace: the IMU fusion's "
                              "heading pulled by a magnetic or optical field, or a wrong station tilt "
                              "seen differently across the space"):
    """A small rotation of the orientation that varies linearly over the workspace.

    R <- Exp(G d) R, G (3 x 3, rad/m, row by row); p unchanged. Closed-form inverse
    R <- Exp(G d)^T R (d does not change).
    """

    labels = tuple(f"turn {axis} per d{along}" for axis in "xyz" for along in "xyz")
    params = (Param("g", 9, (2e-3, 0.0, 0.0, 0.0, -2e-3, 0.0, 1e-3, 0.0, 0.0), 1e-3, "rad/m",
                    doc="G entries, row by row"),)

    def _turn(self, p, theta, ctx):
        return rotvec_to_matrix(_matrix_times(theta, 0, _centred(p, ctx)))

    def forward(self, p, R, theta, ctx):
        xp, p, R, theta = _to_namespace(p, R, theta)
        theta = self.coefficients(theta)
        return p, xp.matmul(self._turn(p, theta, ctx), R)

    def inverse(self, p, R, theta, ctx):
        xp, p, R, theta = _to_namespace(p, R, theta)
        theta = self.coefficients(theta)
        return p, xp.matmul(xp.swap_last(self._turn(p, theta, ctx)), R)


class OrientationBias(Form, name="orientation_bias", order=1.5, per_row_theta=True, changes_rotation=False,
                      sensitivity="orientation",
                      generic=True, closed_form_inverse=True,
                      causes="a position bias that turns with the tracker but is no rigid lever: the "
                             "sensor constellation's optical centre moving with the photodiodes the "
                             "stations see, or a compliant mount that sags with the tracker's attitude"):
    """A position bias linear in the tracker's z axis a = R[:, 2] (base frame).

    p <- p + K a, K (3 x 3, m, row by row); R unchanged. A rigid lever along z (K = e_z I) is
    the mount's and is held by it; every other K is not a lever. Closed-form inverse: R is
    unchanged, so p <- p - K a.
    """

    labels = tuple(f"{axis} per a_{along}" for axis in "xyz" for along in "xyz")
    params = (Param("k", 9, (1e-3, 0.0, 0.0, 0.0, -1e-3, 0.0, 0.0, 0.0, 5e-4), 1e-3, "m",
                    doc="K entries, row by row"),)

    def _bias(self, R, theta):
        return _matrix_times(theta, 0, R[..., 2])

    def forward(self, p, R, theta, ctx):
        xp, p, R, theta = _to_namespace(p, R, theta)
        theta = self.coefficients(theta)
        return p + self._bias(R, theta), R

    def inverse(self, p, R, theta, ctx):
        xp, p, R, theta = _to_namespace(p, R, theta)
        theta = self.coefficients(theta)
        return p - self._bias(R, theta), R


class TimeTrend(Form, name="time_trend", order=5.1, per_row_theta=True, changes_rotation=False, generic=True,
                closed_form_inverse=True, needs_time=True, sensitivity="time",
                causes="a slow change over the session that does not settle: a station warming up or "
                       "moving on its stand, the robot's base creeping"):
    """A polynomial drift of position over the session.

    p <- p + u1 (t / T) + u2 (t / T)^2, u1, u2 (3, m), T = 1000 s, t (s) since the session
    start from ctx.t (the identity without it). Closed-form inverse.
    """

    labels = tuple(f"{axis} on {power}" for power in ("t", "t^2") for axis in "xyz")
    params = (Param("u1", 3, (1e-3, -5e-4, 0.0), 1e-3, "m", doc="linear term, per T"),
              Param("u2", 3, (0.0, 0.0, 5e-4), 1e-3, "m", doc="quadratic term, per T^2"))

    def notes(self, ctx):
        return [] if ctx.t is not None else ["no time column t: time_trend is the identity"]

    def _offset(self, p, theta, ctx):
        xp = namespace(p, theta)
        if ctx.t is None:
            return None
        t = ctx.t if namespace(ctx.t).name == xp.name else xp.const(ctx.t, p)
        s = xp.reshape(t, tuple(t.shape) + (1,)) / TIME_SCALE_S
        return theta[..., 0:3] * s + theta[..., 3:6] * (s * s)

    def forward(self, p, R, theta, ctx):
        xp, p, R, theta = _to_namespace(p, R, theta)
        theta = self.coefficients(theta)
        off = self._offset(p, theta, ctx)
        return (p if off is None else p + off), R

    def inverse(self, p, R, theta, ctx):
        xp, p, R, theta = _to_namespace(p, R, theta)
        theta = self.coefficients(theta)
        off = self._offset(p, theta, ctx)
        return (p if off is None else p - off), R


def _harmonics(xp: Any, angle: Any, theta: Any, first: int) -> Any:
    """sum_k a_k cos(k angle) + b_k sin(k angle), k = 1, 2; theta[first:first + 4] = a1, b1, a2, b2."""
    c = [theta[..., first + i] for i in range(4)]
    return c[0] * xp.cos(angle) + c[1] * xp.sin(angle) + c[2] * xp.cos(2.0 * angle) + c[3] * xp.sin(2.0 * angle)


class SweepHarmonics(Form, name="sweep_harmonics", order=2.5, per_row_theta=True, changes_rotation=False,
                     generic=True, inverse_steps=8, about_station=True,
                     causes="a periodic error of a station's sweep angles: the rotor's speed ripple or "
                            "a wobble of its optics (SteamVR's gibbous terms)"):
    """First- and second-order harmonics of the station's sweep angles (station frame).

    alpha' = alpha + a1 cos alpha + b1 sin alpha + a2 cos 2 alpha + b2 sin 2 alpha, and
    beta' likewise with its own four (rad); r kept, R unchanged (the angles as in `sweep`).
    Inverse: fixed-point steps on the angles, a contraction for coefficients << 1 rad.
    """

    labels = tuple(f"{angle} {wave}" for angle in ("alpha", "beta") for wave in ("cos", "sin", "cos 2", "sin 2"))
    params = (Param("alpha", 4, (1e-3, 0.0, 5e-4, 0.0), 1e-3, "rad", doc="a1, b1, a2, b2 of alpha"),
              Param("beta", 4, (0.0, -1e-3, 0.0, 5e-4), 1e-3, "rad", doc="a1, b1, a2, b2 of beta"))

    def forward(self, p, R, theta, ctx):
        xp, p, R, theta = _to_namespace(p, R, theta)
        theta = self.coefficients(theta)
        alpha, beta, r = sweep_angles(xp, station_coords(p, ctx))
        a2 = alpha + _harmonics(xp, alpha, theta, 0)
        b2 = beta + _harmonics(xp, beta, theta, 4)
        return from_station(r * sweep_direction(xp, a2, b2), ctx), R

    def inverse(self, p, R, theta, ctx):
        xp, p, R, theta = _to_namespace(p, R, theta)
        theta = self.coefficients(theta)
        a2, b2, r = sweep_angles(xp, station_coords(p, ctx))
        alpha, beta = a2, b2
        for _ in range(self.inverse_steps):
            alpha, beta = a2 - _harmonics(xp, alpha, theta, 0), b2 - _harmonics(xp, beta, theta, 4)
        return from_station(r * sweep_direction(xp, alpha, beta), ctx), R


FORMS: tuple[type[Form], ...] = (Strain, Quadratic, OrientationField, OrientationBias, TimeTrend, SweepHarmonics)

for _form in FORMS:
    register_effect(_form)

__all__ = ["FORMS", "Form", "Strain", "Quadratic", "OrientationField", "OrientationBias", "TimeTrend", "SweepHarmonics",
           "TIME_SCALE_S"]

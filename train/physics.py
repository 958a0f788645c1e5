"""The physics stage: the catalogue's effects fitted jointly to paired poses.

Generative model (docs/design.md, "Physical effects"): measured = F_theta(reference), F the
fitted effects applied in catalogue order. The fit minimises the whitened residuals

    r_i = [(p_F,i - p_meas,i) / sigma_p,  log(R_meas,i^T R_F,i) / sigma_r]

by nonlinear least squares (MINPACK's Levenberg-Marquardt, scipy's trust-region reflective
solver where a parameter is bounded; the Jacobian by vectorised forward differences,
`WhitenedResidual`). `station` and `mount` start from the closed-form rigid registration
(`identify.rigid_registration`), which holds for ANY rotation between the tracker's
reporting frame and the base frame and for yaw-only, single-orientation and position-only
tables, so data recorded in the tracker's own frame converges too. Only the directions the
data determine are fitted (`identify.determined_directions`); the rest are held at their
nominal value and named in `fixed_`. sigma_p and sigma_r are re-estimated from the residuals
of a first fit unless given. With `prior_strength` s > 0 the physical parameters outside the
registration are drawn towards their identity (standard deviation `Param.scale` / sqrt(s)):
the MAP estimate, a step from the free fit (`PhysicsModel._shrink`). The correction applies the fitted effects inverse, in reverse order: closed
forms where they exist, a fixed number of Newton / fixed-point steps otherwise
(`posecorr.effects.invert_effects`), so the same `forward` runs in numpy, torch and ONNX.
"""
from __future__ import annotations

import numbers
import sys
from contextlib import contextmanager
from dataclasses import replace
from typing import Any, Iterator, Sequence

import numpy as np
from sklearn.base import BaseEstimator, clone
from sklearn.exceptions import NotFittedError

from posecorr import rotations
from posecorr._xp import namespace
from posecorr.effects import (REGISTRATION_ROLES, EffectContext, get_effect, invert_effects, registration_effects,
                              sorted_effects)
from posecorr.metrics import pose_metrics

from .base import PoseRegressorMixin, check_pair, check_parameters, check_poses, check_times, keeps_last_fit
from .identify import (FORM_LIMIT_SCALES, LIMIT_SCALES, Block, RigidRegistration, chordal_mean, describe_spread,
                       determined_directions, direction_label, poses_lack, rigid_registration,
                       station_in_reference)
from .splits import MIN_FIT_POSES

DEFAULT_SIGMA_P = 3e-4   # m, docs/design.md default noise
DEFAULT_SIGMA_R = 5e-4   # rad
# Noise levels never assumed below a hundredth of the defaults: a perfect fit of few poses must
# not make the whitened Jacobian claim a precision no tracker has.
SIGMA_P_FLOOR = 3e-6     # m
SIGMA_R_FLOOR = 5e-6     # rad


@contextmanager
def single_threaded() -> Iterator[None]:
    """The residuals are a few hundred small elementwise ops and the solver's SVDs are of
    thin matrices: one thread (torch and BLAS) is several times faster than two that
    contend for them. torch is limited only where it is loaded already: small tables never
    need it (`WhitenedResidual`), and importing it costs seconds."""
    from threadpoolctl import threadpool_limits

    torch = sys.modules.get("torch")
    before = torch.get_num_threads() if torch is not None else None
    if torch is not None:
        torch.set_num_threads(1)
    try:
        with threadpool_limits(limits=1):
            yield
    finally:
        if torch is not None and before is not None:
            torch.set_num_threads(before)


# What only `PhysicsModel.shrunk` reads (the free fit's solution, Jacobian and data): neither
# pickled nor kept after `forget_free_fit`.
_FREE_FIT = ("_free", "_data")


class PhysicsModel(PoseRegressorMixin, BaseEstimator):
    """Fit the named effects (station, mount, sweep, ...) and correct by their inverse.

    Parameters: `effects` names from the catalogue (or user effects once loaded);
    `sigma_p` (m) and `sigma_r` (rad) weight the position and orientation residuals
    (None: estimated); `max_nfev` bounds the solver's evaluations; `with_rotation` False for a
    position-only table (`PoseTable.has_orientation`), whose reference orientation is the
    measured one (`PoseTable.reference`) and carries no information; `station_pose` where the
    base station stood (`geometry.parse_station_pose`: None for the paper's, eq. 23), about
    which sweep, range scale and incidence bend.
    Fitted: `params_` {effect: theta}, `std_errors_` {effect: std of theta, NaN where not
    determined}, `sigma_p_`, `sigma_r_`, `ctx_` (frames used), `with_rotation_`, `cost_`,
    `spread_` (`identify.Spread`), `basis_` (the determined directions, scaled units;
    `directions_` in the parameters' units) and
    `fixed_` {parameter or direction: why the data cannot determine it}; those are held at
    their start value (the rigid registration's, or the identity). `prior_strength` s >= 0:
    the prior's weight (`_shrink`); `effective_params_` the number of parameters the fit used.
    """

    method = "physics"
    representation = rotations.POSITION_ONLY

    def __init__(self, effects: Sequence[str] = ("station", "mount"), sigma_p: float | None = None,
                 sigma_r: float | None = None, max_nfev: int = 200, with_rotation: bool = True,
                 prior_strength: float = 0.0, station_pose: str | None = None) -> None:
        self.effects = effects
        self.sigma_p = sigma_p
        self.sigma_r = sigma_r
        self.max_nfev = max_nfev
        self.with_rotation = with_rotation
        self.prior_strength = prior_strength
        self.station_pose = station_pose

    # --- fitting ----------------------------------------------------------------------
    @keeps_last_fit
    def fit(self, measured: Any, reference: Any, t: np.ndarray | None = None, validation: Any = None, *,
            warm_start: "dict[str, np.ndarray] | PhysicsModel | None" = None) -> "PhysicsModel":
        """Fit the effects the data determine; hold the others at their start value.

        validation is accepted for the common signature: a least-squares fit does not stop early.

        warm_start: {effect: theta} replaces the closed-form start; a fitted PhysicsModel (of
        the same effects, on a superset of these poses: a cross-validation fold) also lends
        its determined directions and noise levels, so the fold solves once.
        """
        measured, reference, chosen = self._setup(measured, reference, t)
        with_rotation = self.with_rotation_
        prior, thetas = _warm(warm_start, chosen)
        if prior is not None and all(effect.name in thetas for effect in chosen):
            # A fold of a fitted model: it lends the start and the noise levels, so the
            # closed-form start (and its noise estimate) would be discarded.
            theta0 = np.concatenate([np.asarray(thetas[e.name], float) for e in chosen]) if chosen else np.zeros(0)
        else:
            theta0, sigma_p, sigma_r, _ = self._initial_theta(measured, reference, chosen, thetas)
            # The registration the data cannot see is held where the closed form puts it for
            # these effects: a warm start from a model of other effects (mount fitted without
            # the station, say) is no registration of these.
            start = self._initial_theta(measured, reference, chosen, {})[0] if thetas else theta0
        with single_threaded():
            if prior is not None:
                self.sigma_p_, self.sigma_r_ = prior.sigma_p_, prior.sigma_r_
                self.basis_, self.fixed_ = prior.basis_, dict(prior.fixed_)
                theta = self._solve(theta0, measured, reference, self.sigma_p_, self.sigma_r_ or DEFAULT_SIGMA_R)
            else:
                sigma_p = self.sigma_p or sigma_p
                sigma_r = self.sigma_r or sigma_r
                self.basis_, self.fixed_ = self._identify(theta0, measured, reference, sigma_p, sigma_r)
                theta0 = self._hold_nominal(theta0, start)
                theta = self._solve(theta0, measured, reference, sigma_p, sigma_r)
                if self.sigma_p is None or (self.sigma_r is None and with_rotation):
                    # Re-weight position against orientation by the noise the first free fit
                    # leaves (the noise, not what a prior adds to it).
                    if self._free is not None:
                        theta = self._free[0]
                    dp, dr = self._raw_residuals(theta, measured, reference)
                    dof = max(dp.size + (dr.size if with_rotation else 0) - self.basis_.shape[1], 1)
                    share = dof / (dp.size + (dr.size if with_rotation else 0))
                    sigma_p = self.sigma_p or max(float(np.sqrt(np.mean(dp ** 2) / share)), SIGMA_P_FLOOR)
                    if with_rotation:
                        sigma_r = self.sigma_r or max(float(np.sqrt(np.mean(dr ** 2) / share)), SIGMA_R_FLOOR)
                    theta = self._solve(theta, measured, reference, sigma_p, sigma_r)
                self.sigma_p_, self.sigma_r_ = sigma_p, (sigma_r if with_rotation else None)
            self.params_ = self._unflatten(theta)
            # Standard errors cost a Jacobian: computed when first asked for (folds never are).
            self._std_source = (theta, measured, reference)
            self.__dict__.pop("_std_errors_cache", None)   # an earlier fit's, on other data
            self._data = (measured, reference)
        self.n_features_in_ = 7
        return self

    def _setup(self, measured: Any, reference: Any, t: np.ndarray | None) -> tuple:
        """Checked poses, the frames and the spread: what fitting and `identifiability` share."""
        measured, reference = check_pair(measured, reference)
        t = check_times(t, len(measured))
        for name in ("sigma_p", "sigma_r"):
            sigma = getattr(self, name)
            if sigma is not None and not (isinstance(sigma, numbers.Real) and 0 < sigma < np.inf):
                raise ValueError(f"{name} must be None (estimated from the fit) or a number > 0, got {sigma!r}")
        chosen = sorted_effects(self.effects)
        for effect in chosen:
            if effect.random:
                raise ValueError(f"effect {effect.name!r} is random noise; it cannot be fitted as a bias")
        if len(measured) < MIN_FIT_POSES:
            raise ValueError(f"fitting {', '.join(e.name for e in chosen) or 'a registration'} needs at least "
                             f"{MIN_FIT_POSES} poses, got {len(measured)}")
        R_S, t_S = station_in_reference(self.station_pose, measured, reference)
        self.ctx_ = EffectContext(R_S, t_S, reference[:, :3].mean(axis=0), t=t)
        check_parameters(self, {}, flags=("with_rotation",))
        self.with_rotation_ = bool(self.with_rotation)
        self._chosen = chosen
        self.spread_ = describe_spread(measured[:, :3], rotations.quat_to_matrix(measured[:, 3:7]),
                                       self.with_rotation_)
        return measured, reference, chosen

    def identifiability(self, measured: Any, reference: Any, t: np.ndarray | None = None) -> dict[str, str]:
        """{parameter or direction: why} of what these poses cannot determine, without fitting
        (the first step of `fit`). Leaves the estimator as it was: the setup is a clone's."""
        probe = clone(self)
        measured, reference, chosen = probe._setup(measured, reference, t)
        theta0, sigma_p, sigma_r, _ = probe._initial_theta(measured, reference, chosen, {})
        with single_threaded():
            _, fixed = probe._identify(theta0, measured, reference, self.sigma_p or sigma_p, self.sigma_r or sigma_r)
        return fixed

    def _initial_theta(self, measured: np.ndarray, reference: np.ndarray, chosen: list,
                       given: dict[str, np.ndarray], variant: str | None = None,
                       ) -> tuple[np.ndarray, float, float, RigidRegistration]:
        """theta at the closed-form start, the noise levels (m, rad) the rigid fit leaves, and
        that rigid fit.

        `station` and `mount` start from the rigid registration (Kabsch on positions, the lever
        arm along the directions the orientations determine, the mean mount rotation), which
        holds for any rotation between the frames and for yaw-only, single-orientation and
        position-only tables alike; with reference orientations about two axes or more (a
        robot carrying the tracker) from the closed-form hand-eye solution, whose lever arm and
        mount rotation come from the orientations as well. The other effects start at their
        identity. `variant` names the rigid fit instead (`identify.RIGID_VARIANTS`).
        """
        thetas = {e.name: e.identity_theta() for e in chosen}
        measured_R = rotations.quat_to_matrix(measured[:, 3:7])
        reference_R = rotations.quat_to_matrix(reference[:, 3:7]) if self.with_rotation_ else None
        if variant is None:
            variant = "hand-eye" if reference_R is not None and self.spread_.rotation_axes >= 2 else "lever"
        rigid = rigid_registration(measured[:, :3], measured_R, reference[:, :3], reference_R, variant=variant)
        sigma_r = DEFAULT_SIGMA_R
        if reference_R is not None:
            # Orientation residual of the rigid fit: R_ref vs R R_meas X^T.
            predicted = rigid.R @ measured_R @ rigid.mount.T
            dr = rotations.matrix_to_rotvec(np.swapaxes(reference_R, -1, -2) @ predicted)
            sigma_r = max(float(np.sqrt(np.mean(dr ** 2) * len(dr) / max(len(dr) - 1, 1))), SIGMA_R_FLOOR)
        sigma_p = max(rigid.sigma_p, SIGMA_P_FLOOR)
        # The effects that register the frames start from the rigid fit (`Effect.start`).
        roles = frozenset(e.registration for e in chosen if e.registration)
        mean_turn = None if reference_R is None else chordal_mean(np.swapaxes(reference_R, -1, -2) @ measured_R)
        for effect in chosen:
            start = effect.start(rigid, self.ctx_, roles, mean_turn)
            if start is not None:
                thetas[effect.name] = np.asarray(start, float)
        thetas.update({name: np.asarray(theta, float) for name, theta in given.items() if name in thetas})
        theta = np.concatenate([thetas[e.name] for e in chosen]) if chosen else np.zeros(0)
        return theta, sigma_p, sigma_r, rigid

    def _hold_nominal(self, theta: np.ndarray, start: np.ndarray) -> np.ndarray:
        """theta with every held direction at its nominal value: a physical effect's identity
        (the closed-form start may have put noise there, and what the data cannot see must not
        carry it), a registration's closed-form `start` (its frames are anywhere: no value of
        theirs is nominal, and the rigid fit's is the one consistent with the rest; at the
        identity a mount rotation the orientations cannot separate from the station's made
        the station turn to fit the orientations against the positions)."""
        if theta.size == 0:
            return theta
        nominal = np.where(self._unbounded(), start, self._identity_theta())
        scales = self._scales()
        u = (theta - nominal) / scales
        return nominal + scales * (self.basis_ @ (self.basis_.T @ u))

    def _blocks(self) -> list[Block]:
        """Parameter blocks in the order the identification takes them: the registration
        (its roles in `REGISTRATION_ROLES` order) first, then the other effects in catalogue order."""
        first = {role: rank for rank, role in enumerate(REGISTRATION_ROLES)}
        i, owned = 0, []
        for effect in self._chosen:
            reason = self._undetermined_words(effect)
            for param in effect.params:
                index = np.arange(i, i + param.size)
                label = f"{effect.name}.{param.name}"
                limit = None if param.unbounded else LIMIT_SCALES if effect.typical_scale else FORM_LIMIT_SCALES
                owned.append((first.get(effect.registration, len(first)), len(owned),
                              Block(label, index, param.scale, param.unit, reason, limit)))
                i += param.size
        return [block for _, _, block in sorted(owned, key=lambda item: item[:2])]

    def _undetermined_words(self, effect: Any) -> str:
        return poses_lack(effect, self.spread_, self.ctx_.t)

    def _identify(self, theta0: np.ndarray, measured: np.ndarray, reference: np.ndarray,
                  sigma_p: float, sigma_r: float) -> tuple[np.ndarray, dict[str, str]]:
        """The determined directions of theta (`identify.determined_directions`), judged on the
        Jacobian with every non-registration effect at its typical magnitude (at the identity
        some effects cannot show their own parameters, e.g. drift's time constant)."""
        if theta0.size == 0:
            return np.zeros((0, 0)), {}
        probe, i = theta0.copy(), 0
        for effect in self._chosen:
            if not effect.registration:
                probe[i:i + effect.size] = effect.default_theta()
            i += effect.size
        with np.errstate(all="ignore"):   # a value not finite is named below, in one line
            J = self._residual_fn(measured, reference, sigma_p, sigma_r).jacobian(probe)
        blocks = self._blocks()
        if not np.all(np.isfinite(J)):
            self._require_defined(probe, reference, "at its default values")
            # the poses are finite there: one a finite-difference step away is not
            label = next(b.label for b in blocks if not np.all(np.isfinite(J[:, b.index])))
            raise ValueError(f"{self._named(label.split('.')[0])} gives poses that are not finite a small step "
                             f"from its default values (in {label}, for the fit's derivatives): its forward must "
                             "be defined around them")
        fixed: dict[str, str] = {}
        if not self.with_rotation_:
            held = {f"{e.name}.{name}" for e in self._chosen for name in e.held_without_orientation()}
            for block in blocks:
                if block.label in held:
                    J[:, block.index] = 0.0
                    fixed[block.label] = "the reference has no orientation"
        B, more = determined_directions(J, blocks)
        fixed.update({k: v for k, v in more.items() if not k.startswith(tuple(fixed))})
        return B, fixed

    def _require_defined(self, theta: np.ndarray, reference: np.ndarray, where: str) -> None:
        """ValueError naming the effect (and the file that defines it) whose map gives poses
        that are not finite at `theta`, where one does: a user's effect undefined at its
        identity values met the solver as "Residuals are not finite in the initial point",
        blamed on the table."""
        from posecorr.effects import apply_effects

        p, R = reference[..., 0:3], rotations.quat_to_matrix(reference[..., 3:7])
        thetas = self._unflatten(theta)
        with np.errstate(all="ignore"):
            for effect in self._chosen:
                q, Q = apply_effects(p, R, {effect.name: thetas[effect.name]}, self.ctx_)
                if not (np.all(np.isfinite(q)) and np.all(np.isfinite(Q))):
                    values = ", ".join(f"{v:.6g}" for v in thetas[effect.name])
                    raise ValueError(f"{self._named(effect.name)} gives poses that are not finite {where}, theta = "
                                     f"[{values}]: its forward must be defined there")

    @staticmethod
    def _named(name: str) -> str:
        """"effect 'name' (the file that defines it)", the file where a user's effect has one."""
        from posecorr.effects import EFFECTS

        source = EFFECTS.sources.get(name)
        return f"effect {name!r}" + (f" ({source})" if source else "")

    def _unflatten(self, theta: np.ndarray) -> dict[str, np.ndarray]:
        out, i = {}, 0
        for effect in self._chosen:
            out[effect.name] = np.array(theta[i:i + effect.size])
            i += effect.size
        return out

    def _model_poses(self, theta: Any, reference: Any, ctx: EffectContext | None = None) -> tuple[Any, Any]:
        """F_theta(reference): positions (N, 3) and rotations (N, 3, 3), any namespace.

        A position-only table carries the measured orientation in the reference's place
        (`PoseTable.reference`); the reference orientation the effects need is then the one the
        correction recovers from it, Exp(w)^T R_meas (station w; the mount rotation is held),
        so that a lever arm in the tracker frame is fitted the way it is later undone.
        """
        from posecorr.effects import apply_effects

        p = reference[..., 0:3]
        R = rotations.quat_to_matrix(reference[..., 3:7])
        thetas, i = {}, 0
        for effect in self._chosen:
            thetas[effect.name] = theta[..., i:i + effect.size]
            i += effect.size
        frame = next((e for e in self._chosen if e.registration == "frame"), None)
        if not self.with_rotation_ and frame is not None:
            xp = namespace(R)
            W = rotations.rotvec_to_matrix(frame.frame_rotation(thetas[frame.name]))
            R = xp.matmul(xp.swap_last(W), R)
        return apply_effects(p, R, thetas, ctx or self.ctx_)

    def _raw_residuals(self, theta: np.ndarray, measured: np.ndarray,
                       reference: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p, R = self._model_poses(theta, reference)
        dp = p - measured[:, :3]
        dr = rotations.matrix_to_rotvec(np.swapaxes(rotations.quat_to_matrix(measured[:, 3:7]), -1, -2) @ R)
        return dp, dr

    def _residual_fn(self, measured: np.ndarray, reference: np.ndarray, sigma_p: float,
                     sigma_r: float) -> "WhitenedResidual":
        return WhitenedResidual(self, measured, reference, sigma_p, sigma_r)

    def _scales(self) -> np.ndarray:
        return np.concatenate([e.scales() for e in self._chosen]) if self._chosen else np.zeros(0)

    @property
    def directions_(self) -> np.ndarray:
        """The determined directions in the parameters' units, (theta size, k): the fit moves
        theta along these only (`basis_` scaled by the parameters' typical magnitudes)."""
        return self._scales()[:, None] * self.basis_

    def _bounds(self) -> tuple[np.ndarray, np.ndarray]:
        lower, upper = [], []
        for effect in self._chosen:
            for param in effect.params:
                lo, hi = param.bounds or (-np.inf, np.inf)
                lower += [lo] * param.size
                upper += [hi] * param.size
        return np.asarray(lower, float), np.asarray(upper, float)

    def _solve(self, theta0: np.ndarray, measured: np.ndarray, reference: np.ndarray,
               sigma_p: float, sigma_r: float) -> np.ndarray:
        """Nonlinear least squares over the determined directions: theta = theta0 + S B z
        (S the parameters' typical magnitudes, B = `basis_`), the rest held at theta0."""
        from scipy.optimize import least_squares

        residual = self._residual_fn(measured, reference, sigma_p, sigma_r)
        if theta0.size == 0 or self.basis_.shape[1] == 0:
            self.cost_ = float(np.sum(residual(theta0) ** 2)) if theta0.size else 0.0
            self.effective_params_ = 0.0
            self._free = None
            return theta0
        SB = self.directions_
        lower, upper = self._bounds()
        theta0 = np.clip(theta0, lower, upper)
        # A bounded parameter is a block of its own: its direction is +-1 on that entry alone.
        z_lower, z_upper = np.full(SB.shape[1], -np.inf), np.full(SB.shape[1], np.inf)
        for k in np.flatnonzero(np.isfinite(lower) | np.isfinite(upper)):
            column = np.flatnonzero(SB[k] != 0)
            for j in column:
                bound = sorted(((lower[k] - theta0[k]) / SB[k, j], (upper[k] - theta0[k]) / SB[k, j]))
                z_lower[j], z_upper[j] = max(z_lower[j], bound[0]), min(z_upper[j], bound[1])
        z_lower = np.where(np.isfinite(z_lower), np.minimum(z_lower, -1e-12), z_lower)
        z_upper = np.where(np.isfinite(z_upper), np.maximum(z_upper, 1e-12), z_upper)

        def f(z: np.ndarray) -> np.ndarray:
            return residual(theta0 + SB @ z)

        def jac(z: np.ndarray) -> np.ndarray:
            return residual.jacobian(theta0 + SB @ z) @ SB

        bounded = bool(np.any(np.isfinite(z_lower) | np.isfinite(z_upper)))
        # MINPACK's Levenberg-Marquardt where nothing is bounded: a third of trf's overhead.
        method = "trf" if bounded or residual.size < SB.shape[1] else "lm"
        with np.errstate(all="ignore"):   # one evaluation of the (1 + free parameters) each step takes
            start_finite = np.all(np.isfinite(f(np.zeros(SB.shape[1]))))
        if not start_finite:   # scipy's words were "Residuals are not finite in the initial point", on the table
            self._require_defined(theta0, reference, "where the fit starts")
        result = least_squares(f, np.zeros(SB.shape[1]), jac=jac, method=method,
                               bounds=(z_lower, z_upper) if bounded else (-np.inf, np.inf),
                               max_nfev=self.max_nfev, xtol=1e-9, ftol=1e-9, gtol=1e-9)
        self.cost_ = float(2.0 * result.cost)
        self._at_bound = np.asarray(result.active_mask != 0)
        theta = theta0 + SB @ result.x
        self._free = (theta, SB, result.fun, result.jac)
        return self._shrink(*self._free)

    def _shrink(self, theta: np.ndarray, SB: np.ndarray, r: np.ndarray, Jz: np.ndarray) -> np.ndarray:
        """The MAP estimate under the prior (`prior_strength` s > 0), from the free fit theta
        (whitened residuals r, their Jacobian Jz over the determined directions): every
        physical parameter outside the registration is drawn towards its identity with a
        standard deviation of its typical magnitude (`Param.scale`) over sqrt(s). One
        Gauss-Newton step of the penalised problem from the free optimum, on the free fit's
        own Jacobian: exact where the model is linear in its parameters, and within 1e-6
        typical magnitudes of the penalised solve for strengths up to 10 (7e-4 at 1e8,
        `tests/test_identify.py`), so every strength a cross-validation tries costs no solve.

        Sets `effective_params_`, the trace of the hat matrix Jz (Jz^T Jz + P)^-1 Jz^T: each
        determined direction counts 1 without prior and less as the prior holds it."""
        weights = self._prior_weights()[:, None] * SB
        rows = np.flatnonzero(np.any(weights != 0, axis=1))
        Jp = weights[rows]
        rp = (self._prior_weights() * (theta - self._identity_theta()))[rows]
        data = Jz.T @ Jz
        inverse = np.linalg.pinv(data + Jp.T @ Jp)
        self.effective_params_ = float(np.trace(inverse @ data))
        if not len(rows):
            return theta
        lower, upper = self._bounds()
        return np.clip(theta - SB @ (inverse @ (Jz.T @ r + Jp.T @ rp)), lower, upper)

    def shrunk(self, prior_strength: float) -> "PhysicsModel":
        """This free fit (prior_strength 0) under a prior of the given strength (`_shrink`),
        without solving again: how a cross-validation tries several strengths."""
        self._check_fitted()
        if self.prior_strength != 0:
            raise ValueError("shrunk starts from a free fit (prior_strength 0)")
        if "_free" not in self.__dict__:
            raise ValueError("shrunk needs the fit's data, which a pickled or saved model does not "
                             "keep, nor one after forget_free_fit: fit it again")
        model = object.__new__(type(self))     # not copy.copy: __getstate__ resolves std errors and drops the data
        model.__dict__.update(self.__dict__)
        model.prior_strength = prior_strength
        model.__dict__.pop("_std_errors_cache", None)
        if self._free is None:      # nothing determined: nothing to shrink
            return model
        theta = model._shrink(*self._free)
        model.params_ = model._unflatten(theta)
        model._std_source = (theta,) + self._data
        return model

    def forget_free_fit(self) -> "PhysicsModel":
        """Drops what only `shrunk` reads: the free fit's Jacobian (rows x parameters) and its
        data. A model kept for its predictions, parameters and standard errors, many at once
        (the diagnosis keeps every cross-validation it runs), need not hold them: on 300 poses
        of the paper's Experiment II they were a third of the diagnosis' memory."""
        for kept in _FREE_FIT:
            self.__dict__.pop(kept, None)
        return self

    def _identity_theta(self) -> np.ndarray:
        return np.concatenate([e.identity_theta() for e in self._chosen]) if self._chosen else np.zeros(0)

    def _unbounded(self) -> np.ndarray:
        """For each entry of theta: does its parameter belong to the registration (`Param.unbounded`)?"""
        return np.array([param.unbounded for effect in self._chosen for param in effect.params
                         for _ in range(param.size)], bool)

    def _prior_weights(self) -> np.ndarray:
        """sqrt(prior_strength) / typical magnitude for each entry of theta outside the
        registration (whose frames are anywhere: no physical size bounds them), 0 elsewhere."""
        if not self.prior_strength >= 0:
            raise ValueError(f"prior_strength must be a number >= 0, got {self.prior_strength!r}")
        return np.where(self._unbounded(), 0.0, np.sqrt(self.prior_strength) / self._scales())

    def _param_label(self, k: int) -> str:
        i = 0
        for effect in self._chosen:
            for param in effect.params:
                if i <= k < i + param.size:
                    return f"{effect.name}.{param.name}[{k - i}]" if param.size > 1 else f"{effect.name}.{param.name}"
                i += param.size
        return str(k)

    def _std_errors(self, theta: np.ndarray, measured: np.ndarray, reference: np.ndarray) -> np.ndarray:
        """Standard errors from the Gauss-Newton covariance s^2 (J^T J)^-1 of the whitened fit,
        over the determined directions only. NaN ("not determined") for an entry that a held
        direction touches or that sits on a bound: no number is better than a false one."""
        if theta.size == 0:
            return theta
        SB = self.directions_
        std = np.full(theta.size, np.nan)
        if SB.shape[1]:
            residual = self._residual_fn(measured, reference, self.sigma_p_, self.sigma_r_ or DEFAULT_SIGMA_R)
            r = residual(theta)
            Jz = residual.jacobian(theta) @ SB
            dof = max(r.size - SB.shape[1], 1)
            cov = SB @ np.linalg.pinv(Jz.T @ Jz) @ SB.T * float(r @ r) / dof
            std = np.sqrt(np.clip(np.diag(cov), 0.0, None))
            at_bound = getattr(self, "_at_bound", np.zeros(SB.shape[1], bool))
            for j in np.flatnonzero(at_bound):
                std[SB[:, j] != 0] = np.nan
        # Entries that a held direction touches (more than a tenth of it) are not determined.
        scaled_basis = self.basis_
        held = np.eye(theta.size) - scaled_basis @ scaled_basis.T if scaled_basis.size else np.eye(theta.size)
        std[np.diag(held) > 0.01] = np.nan
        return std

    def residual_jacobian(self, measured: Any, reference: Any, t: np.ndarray | None = None,
                          extra: Sequence[str] = ()) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Whitened residuals r (m,) and Jacobian J (m, n) at the fitted parameters, with the
        `extra` effects appended at their identity value (the score test's point).

        Uses this fit's frames and sigmas on any poses (held-out ones, say). Returns
        (r, J, is_extra) with is_extra (n,) marking the columns of the extra effects.
        """
        residual, theta, is_extra = self._probe(measured, reference, t, extra, (self.sigma_p_, self.sigma_r_))
        with single_threaded():
            r, J = residual(theta), residual.jacobian(theta)
        return r, J, is_extra

    def whitened_residual(self, measured: Any, reference: Any, t: np.ndarray | None = None,
                          sigmas: tuple[float, float | None] | None = None) -> np.ndarray:
        """The whitened residuals r (m,) of this fit on any poses, laid out as
        `residual_jacobian`'s, whitened by `sigmas` (sigma_p, sigma_r; this fit's if None), so
        that two fits' residuals on the same poses compare entry by entry."""
        residual, theta, _ = self._probe(measured, reference, t, (), sigmas or (self.sigma_p_, self.sigma_r_))
        return residual(theta)

    def _probe(self, measured: Any, reference: Any, t: np.ndarray | None, extra: Sequence[str],
               sigmas: tuple[float, float | None]) -> tuple["WhitenedResidual", np.ndarray, np.ndarray]:
        """This fit's residual function on other poses, with `extra` effects at identity."""
        self._check_fitted()
        measured, reference = check_pair(measured, reference)
        t = check_times(t, len(measured))
        probe = PhysicsModel(tuple(self.params_) + tuple(extra), self.sigma_p_, self.sigma_r_,
                             station_pose=self.station_pose)
        probe._chosen = sorted_effects(probe.effects)
        probe.ctx_ = EffectContext(self.ctx_.R_S, self.ctx_.t_S, self.ctx_.c, t=t)
        probe.with_rotation_ = self.with_rotation_
        theta = np.concatenate([self.params_[e.name] if e.name in self.params_ else e.identity_theta()
                                for e in probe._chosen] or [np.zeros(0)])
        is_extra = np.concatenate([np.full(e.size, e.name not in self.params_) for e in probe._chosen]
                                  or [np.zeros(0, bool)])
        sigma_p, sigma_r = sigmas
        return probe._residual_fn(measured, reference, sigma_p, sigma_r or DEFAULT_SIGMA_R), theta, is_extra

    @property
    def std_errors_(self) -> dict[str, np.ndarray]:
        """{effect: standard error of theta}, NaN where not determined (see `_std_errors`)."""
        self._check_fitted()
        if "_std_errors_cache" not in self.__dict__:
            theta, measured, reference = self._std_source
            with single_threaded():
                self._std_errors_cache = self._unflatten(self._std_errors(theta, measured, reference))
            del self._std_source
        return self._std_errors_cache

    def detach(self) -> dict[str, Any]:
        """What cannot cross to another process inside the fitted model, taken out of it for
        `attach` there: the data its standard errors are computed from when first asked for
        (pickling would compute them, which a fold's model is never asked for), and its
        effects by name (a form cut to its terms is a class made at run time, which pickle
        cannot name)."""
        detached = {"effects": [effect.name for effect in self.__dict__.pop("_chosen", [])]}
        if "_std_source" in self.__dict__:
            detached["std_source"] = self.__dict__.pop("_std_source")
        return detached

    def attach(self, detached: dict[str, Any]) -> "PhysicsModel":
        """The model whole again after `detach`, its effects those registered here by name."""
        self._chosen = [get_effect(name) for name in detached["effects"]]
        if "std_source" in detached:
            self._std_source = detached["std_source"]
        return self

    def __getstate__(self) -> dict:
        if "_std_source" in self.__dict__:
            self.std_errors_  # noqa: B018  (resolve before pickling: the data is not kept)
        state = dict(super().__getstate__())   # object's is the live __dict__ itself
        for kept in _FREE_FIT:
            state.pop(kept, None)
        return state

    # --- inference ----------------------------------------------------------------------
    def _check_fitted(self) -> None:
        if not hasattr(self, "params_"):
            raise NotFittedError(f"this {type(self).__name__} is not fitted yet: call fit first")

    def forward(self, pose: Any, t: Any = None) -> Any:
        """(N, 7) measured -> (N, 7) corrected: the fitted effects inverted in reverse order.

        `t` (N,) s (seconds since the session's start) feeds the time-dependent effects
        (`Effect.needs_time`, e.g. drift); the exported graph takes it as its optional second
        input. Without `t` those effects are left out (their correction at t = 0 is none).
        """
        self._check_fitted()
        xp = namespace(pose)
        p = pose[..., 0:3]
        R = rotations.quat_to_matrix(pose[..., 3:7])
        ctx = EffectContext(self.ctx_.R_S, self.ctx_.t_S, self.ctx_.c, t=t)
        thetas = {name: (theta if xp.name == "numpy" else xp.const(theta, pose)) for name, theta in self.params_.items()}
        if t is None:
            thetas = {name: theta for name, theta in thetas.items() if not get_effect(name).needs_time}
        p, R = invert_effects(p, R, thetas, ctx)
        q = rotations.matrix_to_quat(R) if self.with_rotation_ else rotations.unit_quat(pose[..., 3:7])
        return xp.concat([p, q], axis=-1)

    def predict(self, measured: Any, t: np.ndarray | None = None) -> np.ndarray:
        self._check_fitted()
        measured = check_poses(measured, "measured")
        return np.asarray(self.forward(measured, check_times(t, len(measured))), dtype=np.float64)

    def score(self, measured: Any, reference: Any, t: np.ndarray | None = None) -> float:
        """-rmse_total of the corrected poses (higher is better)."""
        self._check_fitted()
        measured, reference = check_pair(measured, reference)
        return -pose_metrics(reference, self.predict(measured, t), self.with_rotation_)["rmse_total"]

    def export_info(self) -> dict[str, str]:
        self._check_fitted()
        info = {"method": "physics", "representation": "R" if self.with_rotation_ else rotations.POSITION_ONLY,
                "effects": ",".join(self.params_)}
        return info

    def station_placed(self) -> dict[str, Any]:
        """Where the fit took the base station to stand: `station_pose` as stated, and its pose
        in the reference frame [x, y, z (m), qw, qx, qy, qz] (metadata `station_pose`)."""
        self._check_fitted()
        q = rotations.matrix_to_quat(self.ctx_.R_S)
        return {"stated": self.station_pose, "reference": [float(v) for v in np.concatenate([self.ctx_.t_S, q])]}

    @property
    def needs_time(self) -> bool:
        """The fitted effects include a time-dependent one: the graph takes the input `t`."""
        self._check_fitted()
        return any(get_effect(name).needs_time for name in self.params_)

    def user_behaviours(self) -> dict[str, list[float]]:
        """{effect: `effects.behaviour` at its fitted theta} for the effects an effect file
        defines: what `check_effect_files` compares another file's effect of that name with."""
        from posecorr.effects import EFFECTS, behaviour

        self._check_fitted()
        return {name: behaviour(name, theta) for name, theta in self.params_.items() if EFFECTS.sources.get(name)}

    def describe(self) -> dict[str, dict[str, list]]:
        """{effect: {param: [value, std_error]}} (lists for vector parameters), SI units."""
        self._check_fitted()
        out: dict[str, dict[str, list]] = {}
        for name, theta in self.params_.items():
            std = self.std_errors_[name]
            out[name] = {}
            for param, sl in get_effect(name).slices().items():
                value = theta[sl].tolist()
                error = [None if not np.isfinite(e) else float(e) for e in std[sl]]
                out[name][param] = [value[0], error[0]] if len(value) == 1 else [value, error]
        return out


def _warm(warm_start: Any, chosen: list) -> tuple["PhysicsModel | None", dict[str, np.ndarray]]:
    """(the fitted model of these effects a fold starts from, or None; {effect: theta} to
    start from), ValueError where `warm_start` cannot be either: it met numpy's shapes ("could
    not be broadcast together") or was ignored without a word."""
    sizes = {effect.name: effect.size for effect in chosen}
    if isinstance(warm_start, PhysicsModel):
        warm_start._check_fitted()
        if set(warm_start.params_) == set(sizes):
            return warm_start, dict(warm_start.params_)
        warm_start = {name: theta for name, theta in warm_start.params_.items() if name in sizes}
    thetas = dict(warm_start or {})
    for name, theta in thetas.items():
        if name not in sizes:
            raise ValueError(f"warm_start names {name!r}, which is not one of the effects fitted "
                             f"({', '.join(sizes)})")
        value = np.asarray(theta, float).reshape(-1)
        if value.size != sizes[name] or not np.all(np.isfinite(value)):
            raise ValueError(f"warm_start[{name!r}] must be {sizes[name]} finite numbers, got {theta!r}")
        thetas[name] = value
    return None, thetas


class RigidModel(PhysicsModel):
    """The plain rigid fit as a correction: `identify.rigid_registration` in closed form (one of
    `identify.RIGID_VARIANTS`: no lever arm, the lever in the tracker frame or in the
    reference frame), held in the `station` and `mount` effects so that it exports and runs
    like any physics stage. The variants are the floor of every fit (`pipeline.fit_table`): a
    model that does not beat the best of them on held-out poses is not returned."""

    method = "rigid"

    def __init__(self, with_rotation: bool = True, variant: str = "lever") -> None:
        roles = registration_effects()
        super().__init__(effects=tuple(roles[role] for role in REGISTRATION_ROLES), with_rotation=with_rotation)
        self.variant = variant

    @keeps_last_fit
    def fit(self, measured: Any, reference: Any, t: np.ndarray | None = None, validation: Any = None, *,
            warm_start: Any = None) -> "RigidModel":
        """The closed form of the variant; "joint" is the physics stage of station and mount
        (free, from `warm_start` when given)."""
        if self.variant == "joint":
            return super().fit(measured, reference, t, validation, warm_start=warm_start)
        measured, reference = check_pair(measured, reference)
        check_times(t, len(measured))
        if len(measured) < MIN_FIT_POSES:
            raise ValueError(f"a rigid registration needs at least {MIN_FIT_POSES} poses, got {len(measured)}")
        measured, reference, chosen = self._setup(measured, reference, None)
        with_rotation = self.with_rotation_
        theta, self.sigma_p_, sigma_r, rigid = self._initial_theta(measured, reference, chosen, {}, self.variant)
        self.sigma_r_ = sigma_r if with_rotation else None
        lever = get_effect(registration_effects()["lever"])
        held = lever.held_without_orientation()
        self.fixed_ = {} if with_rotation else {f"{lever.name}.{name}": "the reference has no orientation"
                                                for name in held}
        # the lever directions the variant holds, as the lever effect's arm holds them (e = -X lever)
        self._held_arm = [rigid.mount @ v for v in rigid.lever_fixed]
        if len(rigid.lever_fixed):
            arm = f"{lever.name}.{next(p.name for p in lever.params if p.name not in held)}"
            label = arm if len(rigid.lever_fixed) == 3 else f"{arm} along " + "; ".join(
                direction_label(rigid.mount @ v) for v in rigid.lever_fixed)   # e = -X lever
            self.fixed_[label] = ("the plain Kabsch fit has no lever arm" if self.variant == "kabsch"
                                  else self.spread_.orientation_words())
        self.basis_ = np.zeros((theta.size, 0))
        self.cost_ = float("nan")
        self.params_ = self._unflatten(theta)
        self._std_source = (theta, measured, reference)
        self.__dict__.pop("_std_errors_cache", None)   # an earlier fit's, on other data
        self.n_features_in_ = 7
        return self

    def _std_errors(self, theta: np.ndarray, measured: np.ndarray, reference: np.ndarray) -> np.ndarray:
        """As for the physics stage, over the directions the identification finds determined
        at the closed-form solution (the rigid fit holds nothing the data could move)."""
        if self.variant == "joint":
            return super()._std_errors(theta, measured, reference)
        self.basis_, _ = self._identify(theta, measured, reference, self.sigma_p_, self.sigma_r_ or DEFAULT_SIGMA_R)
        std = super()._std_errors(theta, measured, reference)
        # What the variant holds it did not fit, whatever the data could determine (a Kabsch
        # fit's lever: no standard error beside its 0), by the physics stage's rule: an entry a
        # held direction touches by more than a tenth.
        lever = get_effect(registration_effects()["lever"])
        arm = next(param.name for param in lever.params if param.name not in lever.held_without_orientation())
        start = sum(effect.size for effect in self._chosen[:[e.name for e in self._chosen].index(lever.name)])
        entries = np.arange(theta.size)[start:start + lever.size][lever.slices()[arm]]
        for direction in self._held_arm:
            std[entries[np.abs(direction) > 0.1]] = np.nan
        return std

    def export_info(self) -> dict[str, str]:
        info = super().export_info()
        info["method"] = "rigid"
        info["rigid_variant"] = self.variant
        return info


class WhitenedResidual:
    """r(theta) = [(p_F - p_meas) / sigma_p, log(R_meas^T R_F) / sigma_r] of a physics model, and
    its Jacobian by forward differences of the numpy residual (steps of 1e-7 of each
    parameter's typical magnitude: about 1e-8 relative accuracy, ample for Levenberg-Marquardt
    and for standard errors). With effects that take one parameter row per pose
    (`Effect.per_row_theta`, every built-in one) all the steps are one vectorised evaluation:
    several times faster than autodiff through the same formulas, whose per-call overhead
    dominates on the 6-40 poses of a real session (fitted hundreds of times in a nested
    cross-validation) and whose import alone costs seconds.
    """

    FD_STEP = 1e-7     # in units of each parameter's typical magnitude

    def __init__(self, model: PhysicsModel, measured: np.ndarray, reference: np.ndarray,
                 sigma_p: float, sigma_r: float) -> None:
        self.model, self.measured, self.reference = model, measured, reference
        self.sigma_p, self.sigma_r = sigma_p, sigma_r
        self.meas_RT = np.swapaxes(rotations.quat_to_matrix(measured[:, 3:7]), -1, -2)
        self.size = len(measured) * (6 if model.with_rotation_ else 3)

    def __call__(self, theta: np.ndarray) -> np.ndarray:
        p, R = self.model._model_poses(np.asarray(theta, float), self.reference)
        parts = [((p - self.measured[:, :3]) / self.sigma_p).reshape(-1)]
        if self.model.with_rotation_:
            parts.append((rotations.matrix_to_rotvec(self.meas_RT @ R) / self.sigma_r).reshape(-1))
        return np.concatenate(parts)

    def jacobian(self, theta: np.ndarray) -> np.ndarray:
        theta = np.asarray(theta, float)
        steps = self.FD_STEP * self.model._scales()
        points = np.concatenate([theta[None], theta + np.diag(steps)])        # (1 + n, n)
        if all(effect.per_row_theta for effect in self.model._chosen):
            values = self._batched(points)
        else:
            values = np.stack([self(point) for point in points])
        return ((values[1:] - values[0]) / steps[:, None]).T

    def _batched(self, points: np.ndarray) -> np.ndarray:
        """r at each row of `points` (k, n) in one evaluation: the poses repeated k times, each
        copy with its own parameters."""
        k, n = len(points), len(self.measured)
        ctx = self.model.ctx_
        if ctx.t is not None:
            ctx = replace(ctx, t=np.tile(np.asarray(ctx.t, float), k))
        p, R = self.model._model_poses(np.repeat(points, n, axis=0), np.tile(self.reference, (k, 1)), ctx)
        dp = ((p - np.tile(self.measured[:, :3], (k, 1))) / self.sigma_p).reshape(k, n * 3)
        if not self.model.with_rotation_:
            return dp
        dr = rotations.matrix_to_rotvec(np.tile(self.meas_RT, (k, 1, 1)) @ R) / self.sigma_r
        return np.concatenate([dp, dr.reshape(k, n * 3)], axis=1)

"""The physics stage: the catalogue's effects fitted jointly to paired poses.

Generative model (DESIGN.md): measured = F_theta(reference), F the fitted effects applied in
catalogue order. The fit minimises the whitened residuals

    r_i = [(p_F,i - p_meas,i) / sigma_p,  log(R_meas,i^T R_F,i) / sigma_r]

by nonlinear least squares (scipy's trust-region reflective solver with the exact Jacobian
from torch forward-mode autodiff). `station` and `mount` start from closed forms that hold
for ANY rotation between the tracker's reporting frame and the base frame (robot-world-
hand-eye AX = YB with orientations, Umeyama without), so data recorded in the tracker's own
frame converges too. sigma_p and sigma_r are re-estimated from the residuals of a first fit
unless given. The correction applies the fitted effects inverse, in reverse order: closed
forms where they exist, a fixed number of Newton / fixed-point steps otherwise
(`posecorr.effects.invert_effects`), so the same `forward` runs in numpy, torch and ONNX.
"""
from __future__ import annotations

from contextlib import contextmanager
from typing import Any, Iterator, Sequence

import numpy as np

from posecorr import rotations
from posecorr._xp import namespace
from posecorr.effects import EffectContext, get_effect, invert_effects, sorted_effects
from posecorr.metrics import pose_metrics
from posecorr.registration import homogeneous, robot_world_hand_eye, umeyama

from .base import check_poses

DEFAULT_SIGMA_P = 3e-4   # m, DESIGN.md default noise
DEFAULT_SIGMA_R = 5e-4   # rad
# Bounds keep each parameter in its physical range; drift's time constant must stay positive.
_TAU_BOUNDS = (60.0, 1e7)


@contextmanager
def single_threaded() -> Iterator[None]:
    """The residuals are a few hundred small elementwise ops and the solver's SVDs are of
    thin matrices: one thread (torch and BLAS) is several times faster than two that
    contend for them."""
    import torch
    from threadpoolctl import threadpool_limits

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with threadpool_limits(limits=1):
            yield
    finally:
        torch.set_num_threads(before)


class PhysicsModel:
    """Fit the named effects (station, mount, sweep, ...) and correct by their inverse.

    Parameters: `effects` names from the catalogue (or user effects once loaded);
    `sigma_p` (m) and `sigma_r` (rad) weight the position and orientation residuals
    (None: estimated); `max_nfev` bounds the solver's evaluations.
    Fitted: `params_` {effect: theta}, `std_errors_` {effect: std of theta}, `sigma_p_`,
    `sigma_r_`, `ctx_` (frames used), `with_rotation_`, `cost_`, `frozen_` (parameters the
    data cannot determine, held at their start value).
    """

    method = "physics"
    representation = "pos"

    def __init__(self, effects: Sequence[str] = ("station", "mount"), sigma_p: float | None = None,
                 sigma_r: float | None = None, max_nfev: int = 200) -> None:
        self.effects = effects
        self.sigma_p = sigma_p
        self.sigma_r = sigma_r
        self.max_nfev = max_nfev

    # --- fitting ----------------------------------------------------------------------
    def fit(self, measured: Any, reference: Any, t: np.ndarray | None = None,
            with_rotation: bool = True, warm_start: dict[str, np.ndarray] | None = None) -> "PhysicsModel":
        """Fit the effects; `warm_start` {effect: theta} replaces the closed-form start (CV folds)."""
        measured = check_poses(measured, "measured")
        reference = check_poses(reference, "reference", len(measured))
        chosen = sorted_effects(self.effects)
        for effect in chosen:
            if effect.random:
                raise ValueError(f"effect {effect.name!r} is random noise; it cannot be fitted as a bias")
        needed = max(3, sum(e.size for e in chosen) // (6 if with_rotation else 3) + 1)
        if len(measured) < needed:
            raise ValueError(f"fitting {', '.join(e.name for e in chosen)} needs at least {needed} poses, "
                             f"got {len(measured)}")
        base = EffectContext.default()
        self.ctx_ = EffectContext(base.R_S, base.t_S, reference[:, :3].mean(axis=0),
                                  t=None if t is None else np.asarray(t, float))
        self.with_rotation_ = bool(with_rotation)
        self._chosen = chosen
        theta0 = self._initial_theta(measured, reference, chosen, warm_start or {})
        sigma_p = self.sigma_p or DEFAULT_SIGMA_P
        sigma_r = self.sigma_r or DEFAULT_SIGMA_R
        with single_threaded():
            theta = self._solve(theta0, measured, reference, sigma_p, sigma_r)
            if self.sigma_p is None or (self.sigma_r is None and with_rotation):
                # Re-weight position against orientation by the noise the first fit leaves.
                dp, dr = self._raw_residuals(theta, measured, reference)
                sigma_p = self.sigma_p or float(np.sqrt(np.mean(dp ** 2)))
                if with_rotation:
                    sigma_r = self.sigma_r or float(np.sqrt(np.mean(dr ** 2)))
                theta = self._solve(theta, measured, reference, sigma_p, sigma_r)
            self.sigma_p_, self.sigma_r_ = sigma_p, (sigma_r if with_rotation else None)
            self.params_ = self._unflatten(theta)
            self.std_errors_ = self._unflatten(self._std_errors(theta, measured, reference))
        self.n_features_in_ = 7
        return self

    def _initial_theta(self, measured: np.ndarray, reference: np.ndarray, chosen: list,
                       warm_start: dict[str, np.ndarray]) -> np.ndarray:
        thetas = {e.name: e.identity_theta() for e in chosen}
        names = {e.name for e in chosen}
        if ("station" in names and "station" not in warm_start) or ("mount" in names and "mount" not in warm_start):
            T = homogeneous(rotations.quat_to_matrix(reference[:, 3:7]), reference[:, :3])
            M = homogeneous(rotations.quat_to_matrix(measured[:, 3:7]), measured[:, :3])
            if self.with_rotation_:
                X, Y = robot_world_hand_eye(T, M)
                W = np.linalg.inv(Y)
            else:
                R_W, t_W, _ = umeyama(reference[:, :3], measured[:, :3])
                W, X = homogeneous(R_W, t_W), np.eye(4)
            if "mount" in names:
                thetas["mount"] = np.concatenate([rotations.matrix_to_rotvec(X[:3, :3]), X[:3, 3]])
            if "station" in names:
                c = self.ctx_.c
                R_W, t_W = W[:3, :3], W[:3, 3]
                thetas["station"] = np.concatenate([rotations.matrix_to_rotvec(R_W), t_W - c + R_W @ c])
        if "drift" in names:
            thetas["drift"][3] = get_effect("drift").default_theta()[3]
        thetas.update({name: np.asarray(theta, float) for name, theta in warm_start.items() if name in thetas})
        return np.concatenate([thetas[e.name] for e in chosen]) if chosen else np.zeros(0)

    def _unflatten(self, theta: np.ndarray) -> dict[str, np.ndarray]:
        out, i = {}, 0
        for effect in self._chosen:
            out[effect.name] = np.array(theta[i:i + effect.size])
            i += effect.size
        return out

    def _model_poses(self, theta: Any, reference: Any) -> tuple[Any, Any]:
        """F_theta(reference): positions (N, 3) and rotations (N, 3, 3), any namespace."""
        from posecorr.effects import apply_effects

        p = reference[..., 0:3]
        R = rotations.quat_to_matrix(reference[..., 3:7])
        thetas, i = {}, 0
        for effect in self._chosen:
            thetas[effect.name] = theta[..., i:i + effect.size]
            i += effect.size
        return apply_effects(p, R, thetas, self.ctx_)

    def _raw_residuals(self, theta: np.ndarray, measured: np.ndarray,
                       reference: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p, R = self._model_poses(theta, reference)
        dp = p - measured[:, :3]
        dr = rotations.matrix_to_rotvec(np.swapaxes(rotations.quat_to_matrix(measured[:, 3:7]), -1, -2) @ R)
        return dp, dr

    def _residual_fn(self, measured: np.ndarray, reference: np.ndarray, sigma_p: float, sigma_r: float):
        import torch

        meas_p = torch.from_numpy(measured[:, :3])
        meas_RT = torch.from_numpy(np.swapaxes(rotations.quat_to_matrix(measured[:, 3:7]), -1, -2).copy())
        ref = torch.from_numpy(reference)
        with_rotation = self.with_rotation_

        def residual(theta: "torch.Tensor") -> "torch.Tensor":
            p, R = self._model_poses(theta, ref)
            parts = [((p - meas_p) / sigma_p).reshape(-1)]
            if with_rotation:
                parts.append((rotations.matrix_to_rotvec(torch.matmul(meas_RT, R)) / sigma_r).reshape(-1))
            return torch.cat(parts)

        return residual

    def _solve(self, theta0: np.ndarray, measured: np.ndarray, reference: np.ndarray,
               sigma_p: float, sigma_r: float) -> np.ndarray:
        import torch
        from scipy.optimize import least_squares

        if theta0.size == 0:
            return theta0
        residual = self._residual_fn(measured, reference, sigma_p, sigma_r)
        jacobian = torch.func.jacfwd(residual)
        scales = np.concatenate([e.scales() for e in self._chosen])
        lower, upper = np.full(theta0.size, -np.inf), np.full(theta0.size, np.inf)
        i = 0
        for effect in self._chosen:
            if effect.name == "drift":
                lower[i + 3], upper[i + 3] = _TAU_BOUNDS
            i += effect.size
        x0 = np.clip(theta0, lower, upper)

        # Parameters the data cannot move (e.g. mount rotation without reference
        # orientations) have zero Jacobian columns: hold them, report them frozen.
        J0 = jacobian(torch.from_numpy(x0)).numpy()
        col = np.linalg.norm(J0, axis=0)
        free = col > 1e-9 * max(col.max(), 1e-300)
        self.frozen_ = [self._param_label(k) for k in np.flatnonzero(~free)]

        def f(x: np.ndarray) -> np.ndarray:
            full = x0.copy()
            full[free] = x
            with torch.no_grad():
                return residual(torch.from_numpy(full)).numpy()

        def jac(x: np.ndarray) -> np.ndarray:
            full = x0.copy()
            full[free] = x
            return jacobian(torch.from_numpy(full)).numpy()[:, free]

        result = least_squares(f, x0[free], jac=jac, bounds=(lower[free], upper[free]), x_scale=scales[free],
                               method="trf", max_nfev=self.max_nfev, xtol=1e-12, ftol=1e-12, gtol=1e-10)
        theta = x0.copy()
        theta[free] = result.x
        self.cost_ = float(2.0 * result.cost)
        self._jacobian = jacobian
        self._residual = residual
        return theta

    def _param_label(self, k: int) -> str:
        i = 0
        for effect in self._chosen:
            for param in effect.params:
                if i <= k < i + param.size:
                    return f"{effect.name}.{param.name}[{k - i}]" if param.size > 1 else f"{effect.name}.{param.name}"
                i += param.size
        return str(k)

    def _std_errors(self, theta: np.ndarray, measured: np.ndarray, reference: np.ndarray) -> np.ndarray:
        """Standard errors from the Gauss-Newton covariance s^2 (J^T J)^-1 of the whitened fit."""
        import torch

        if theta.size == 0:
            return theta
        residual = self._residual_fn(measured, reference, self.sigma_p_, self.sigma_r_ or DEFAULT_SIGMA_R)
        r = residual(torch.from_numpy(theta)).detach().numpy()
        J = torch.func.jacfwd(residual)(torch.from_numpy(theta)).numpy()
        dof = max(r.size - theta.size, 1)
        cov = np.linalg.pinv(J.T @ J) * float(r @ r) / dof
        return np.sqrt(np.clip(np.diag(cov), 0.0, None))

    def residual_jacobian(self, measured: Any, reference: Any, t: np.ndarray | None = None,
                          extra: Sequence[str] = ()) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Whitened residuals r (m,) and Jacobian J (m, n) at the fitted parameters, with the
        `extra` effects appended at their identity value (the score test's point).

        Uses this fit's frames and sigmas on any poses (held-out ones, say). Returns
        (r, J, is_extra) with is_extra (n,) marking the columns of the extra effects.
        """
        import torch

        self._check_fitted()
        measured = check_poses(measured, "measured")
        reference = check_poses(reference, "reference", len(measured))
        probe = PhysicsModel(tuple(self.params_) + tuple(extra), self.sigma_p_, self.sigma_r_)
        probe._chosen = sorted_effects(probe.effects)
        probe.ctx_ = EffectContext(self.ctx_.R_S, self.ctx_.t_S, self.ctx_.c,
                                   t=None if t is None else np.asarray(t, float))
        probe.with_rotation_ = self.with_rotation_
        theta = np.concatenate([self.params_[e.name] if e.name in self.params_ else e.identity_theta()
                                for e in probe._chosen])
        is_extra = np.concatenate([np.full(e.size, e.name not in self.params_) for e in probe._chosen])
        residual = probe._residual_fn(measured, reference, self.sigma_p_, self.sigma_r_ or DEFAULT_SIGMA_R)
        with single_threaded():
            x = torch.from_numpy(theta)
            r = residual(x).detach().numpy()
            J = torch.func.jacfwd(residual)(x).numpy()
        return r, J, is_extra

    # --- inference ----------------------------------------------------------------------
    def _check_fitted(self) -> None:
        if not hasattr(self, "params_"):
            raise RuntimeError("this PhysicsModel is not fitted yet: call fit first")

    def forward(self, pose: Any, t: Any = None) -> Any:
        """(N, 7) measured -> (N, 7) corrected: the fitted effects inverted in reverse order.

        `t` (N,) s feeds `drift`; the exported graph has no time input, so there drift is
        left out (recorded in the model's metadata).
        """
        self._check_fitted()
        xp = namespace(pose)
        p = pose[..., 0:3]
        R = rotations.quat_to_matrix(pose[..., 3:7])
        ctx = EffectContext(self.ctx_.R_S, self.ctx_.t_S, self.ctx_.c, t=t)
        thetas = {name: (theta if xp.name == "numpy" else xp.const(theta, pose)) for name, theta in self.params_.items()}
        if t is None:
            thetas.pop("drift", None)
        p, R = invert_effects(p, R, thetas, ctx)
        q = rotations.matrix_to_quat(R) if self.with_rotation_ else rotations.canonical_quat(pose[..., 3:7])
        return xp.concat([p, q], axis=-1)

    def predict(self, measured: Any, t: np.ndarray | None = None) -> np.ndarray:
        measured = check_poses(measured, "measured")
        return np.asarray(self.forward(measured, t), dtype=np.float64)

    def score(self, measured: Any, reference: Any, t: np.ndarray | None = None) -> float:
        """-rmse_total of the corrected poses (higher is better)."""
        reference = check_poses(reference, "reference", len(measured))
        return -pose_metrics(reference, self.predict(measured, t), self.with_rotation_)["rmse_total"]

    def export_info(self) -> dict[str, str]:
        self._check_fitted()
        info = {"method": "physics", "representation": "pos" if not self.with_rotation_ else "R",
                "effects": ",".join(self.params_)}
        if "drift" in self.params_:
            info["drift"] = "fitted; not applied in the exported graph (no time input)"
        return info

    def describe(self) -> dict[str, dict[str, list]]:
        """{effect: {param: [value, std_error]}} (lists for vector parameters), SI units."""
        self._check_fitted()
        out: dict[str, dict[str, list]] = {}
        for name, theta in self.params_.items():
            std = self.std_errors_[name]
            out[name] = {}
            for param, sl in get_effect(name).slices().items():
                value, error = theta[sl].tolist(), std[sl].tolist()
                out[name][param] = [value[0], error[0]] if len(value) == 1 else [value, error]
        return out

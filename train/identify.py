"""What a table can determine, decided before anything is fitted.

Real sessions (docs/design.md, "Real sessions") have 6 to 40 poses, frames nobody registered,
often one orientation or yaw only, sometimes no reference orientation. Fitting a parameter
the data cannot see turns noise into metres (a "2 m mount lever" cancelling a 2 m station
offset). Three pieces keep that from happening:

- `describe_spread`: how far positions and orientations spread (principal extents, axes).
- `rigid_registration`: the plain rigid fits in closed form (`RIGID_VARIANTS`): Kabsch from
  tracker position to reference position, without lever arm, with the lever arm between the
  tracker and the reference point along the directions the tracker's orientations determine,
  or with it in the reference frame; with reference orientations about two axes or more the
  robot-world-hand-eye solution AX = YB. Each adds (with reference orientations) the mean
  mount rotation. Together with the joint fit (`physics.RigidModel`) they are the floor every
  model must beat, and one of them is the start of every fit.
- `determined_directions`: which directions of a parameter space the whitened Jacobian pins
  down, block by block in a priority order (registration first), so that a direction one
  block shares with an earlier one (mount offset along the yaw axis ~ station offset) stays
  with the earlier block and the later one holds its nominal value.

A direction counts as determined when its standard error, given the blocks before it, is
below `LIMIT_SCALES` times the parameter's typical magnitude (`Param.scale`; for a form,
whose scale is only its coefficients' unit, `FORM_LIMIT_SCALES`), and when at
least `MIN_INDEPENDENT` of its effect on the data is not already the effect of an earlier
block: otherwise the fit would only move it by noise (with thousands of poses the noise
itself makes a tiny, meaningless difference look "determined"). Whether a determined but weak parameter pays is then a
question for cross-validation (`pipeline.fit_table` compares every model with the rigid fit).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple, Sequence

import numpy as np

from posecorr.geometry import nearest_rotation, parse_station_pose
from posecorr.registration import umeyama
from posecorr.rotations import quat_to_matrix

LIMIT_SCALES = 10.0            # determined: std error < LIMIT_SCALES * Param.scale
# A form's scale is the unit of its coefficients, not the size of the error it stands for (a
# strain of several % on a real session whose rigid floor is tens of mm): its directions are
# held only where the data pin them no better than this many units.
FORM_LIMIT_SCALES = 100.0
MIN_INDEPENDENT = 0.02         # ... and at least 2 % of its effect unexplained by earlier blocks
LEVER_LIMIT = 0.1              # m: the same rule for the rigid fit's lever arm (mount e scale 1e-2 m)
AXIS_MIN_RAD = np.deg2rad(1.0)  # an orientation axis "spreads" beyond 1 deg RMS
AXIS_MIN_M = 0.01              # a position axis "spreads" beyond 1 cm RMS


@dataclass(frozen=True)
class Spread:
    """How a table's poses spread: what its data can possibly determine.

    position_extent (3,) m: RMS extent of the positions along their principal axes (largest
    first); rotation_extent (3,) rad: RMS angle of the measured orientations about their
    chordal mean along their principal axes; rotation_span: largest angle between any
    orientation and that mean (rad); has_orientation: the reference has orientations.
    """

    n: int
    position_extent: np.ndarray
    rotation_extent: np.ndarray
    rotation_span: float
    has_orientation: bool

    @property
    def position_axes(self) -> int:
        return int(np.sum(self.position_extent > AXIS_MIN_M))

    @property
    def rotation_axes(self) -> int:
        return int(np.sum(self.rotation_extent > AXIS_MIN_RAD))

    def orientation_words(self) -> str:
        """'orientations within 13.1 deg of their mean, about one axis' and the like (the largest
        angle from the chordal mean: the pairwise span is up to twice it)."""
        span = np.rad2deg(self.rotation_span)
        axes = {0: "", 1: ", about one axis", 2: ", about two axes", 3: ", about three axes"}[self.rotation_axes]
        return f"orientations within {span:.1f} deg of their mean{axes}"

    def position_words(self) -> str:
        extent = ", ".join(f"{1000 * e:.0f}" for e in self.position_extent)
        return f"positions spread ({extent}) mm RMS along their principal axes"

    def to_json(self) -> dict:
        return {"n": self.n, "position_extent_m": self.position_extent.tolist(),
                "rotation_extent_deg": np.rad2deg(self.rotation_extent).tolist(),
                "rotation_span_deg": float(np.rad2deg(self.rotation_span)),
                "position_axes": self.position_axes, "rotation_axes": self.rotation_axes,
                "has_orientation": self.has_orientation}


# A drift 1 - exp(-t / tau) is within 1 % of its end after this many time constants.
ENDED_TIME_CONSTANTS = 5.0


def poses_lack(effect: Any, spread: Spread, t: np.ndarray | None) -> str:
    """What these poses offer `effect` to show in, by what it varies with
    (`Effect.sensitivity`): the session's length, the orientations' span or the positions'."""
    if effect.sensitivity == "time":
        if t is None:
            return "the table has no time column t"
        bounded = [p for p in effect.params if p.bounds is not None]
        words = f"the session lasts {float(np.ptp(t)):.0f} s"
        if bounded:
            ranges = ", ".join(f"{effect.name}.{p.name} {p.bounds[0]:g} to {p.bounds[1]:g} {p.unit}" for p in bounded)
            # Tested at its default time constant, a drift either has not ended by the last
            # pose (a straight line, only its slope shows) or had ended by the first (a
            # constant offset, the station's: times in ms put every pose there).
            tested = bounded[0]
            tau = float(np.ravel(tested.default)[0])
            why = (f"at {effect.name}.{tested.name} = {tau:g} {tested.unit}, where it is tested, it is over before "
                   f"the first pose, t = {float(np.min(t)):.6g} s, and shows only as a constant offset; is t in seconds?"
                   if float(np.min(t)) > ENDED_TIME_CONSTANTS * tau
                   else "a time constant longer than the session shows only as a straight line")
            words += f", against {ranges} ({why})"
        return words
    if not spread.has_orientation and not effect.changes_position:
        return f"the reference has no orientation, and {effect.name} turns the orientation alone"
    if effect.sensitivity == "orientation":
        return spread.orientation_words()
    return spread.position_words()


def chordal_mean(R: np.ndarray) -> np.ndarray:
    """The rotation nearest (Frobenius) to the mean of (N, 3, 3) rotations."""
    return nearest_rotation(np.mean(R, axis=0))


def describe_spread(measured_p: np.ndarray, measured_R: np.ndarray, has_orientation: bool) -> Spread:
    from posecorr.rotations import matrix_to_rotvec

    centred = measured_p - measured_p.mean(axis=0)
    position_extent = np.linalg.svd(centred / np.sqrt(len(centred)), compute_uv=False)
    mean = chordal_mean(measured_R)
    w = matrix_to_rotvec(np.swapaxes(mean, -1, -2)[None] @ measured_R)     # in the mean's frame
    rotation_extent = np.linalg.svd(w / np.sqrt(len(w)), compute_uv=False)
    span = float(np.max(np.linalg.norm(w, axis=1))) if len(w) else 0.0
    return Spread(len(measured_p), np.pad(position_extent, (0, 3 - len(position_extent))),
                  np.pad(rotation_extent, (0, 3 - len(rotation_extent))), span, bool(has_orientation))


@dataclass
class RigidRegistration:
    """p_ref = R (p_meas + R_meas lever) + t, R_ref = R R_meas mount^T (see the module docstring).

    lever (3,) m in the tracker frame, zero along `lever_fixed` (unit vectors, tracker frame)
    where the orientations cannot determine it; mount (3, 3): the tracker frame in the
    reference orientation's frame (identity without reference orientations); sigma_p: RMS
    per-coordinate position residual (m) with the degrees of freedom taken off.
    """

    R: np.ndarray
    t: np.ndarray
    lever: np.ndarray
    lever_fixed: np.ndarray
    mount: np.ndarray
    sigma_p: float

    def predict_position(self, measured_p: np.ndarray, measured_R: np.ndarray) -> np.ndarray:
        return (measured_p + measured_R @ self.lever) @ self.R.T + self.t


# The plain rigid fits, the floor every model must beat (issue 23: a user's 20-line Kabsch must
# never beat the tool): which lever arm each fits. "lever-ref" needs reference orientations.
RIGID_VARIANTS = {
    "kabsch": "Kabsch of tracker to reference positions, no lever arm",
    "lever": "Kabsch with the lever arm in the tracker frame (along the directions its orientations turn about)",
    "lever-ref": "Kabsch with the lever arm in the reference frame (along the directions its orientations turn about)",
    "hand-eye": "the robot-world-hand-eye solution AX = YB in closed form (reference orientations about 2+ axes)",
    "joint": "registration, mount rotation and lever fitted to positions and orientations jointly, each weighted "
             "by its noise (the physics stage of station and mount)",
}
# The variants `rigid_registration` solves in closed form; "joint" is iterative (`physics.RigidModel`).
CLOSED_FORM = ("kabsch", "lever", "lever-ref", "hand-eye")
# What each variant needs beyond positions: reference orientations, turning about at least
# this many axes (AX = YB leaves the mount's rotation undetermined with fewer than two).
_NEEDS_ORIENTATION = {"lever-ref": 0, "hand-eye": 2}


def rigid_variants(has_orientation: bool, rotation_axes: int = 0) -> tuple[str, ...]:
    """The rigid variants a table allows (see `_NEEDS_ORIENTATION`)."""
    return tuple(name for name in RIGID_VARIANTS if name not in _NEEDS_ORIENTATION
                 or (has_orientation and rotation_axes >= _NEEDS_ORIENTATION[name]))


def rigid_registration(measured_p: np.ndarray, measured_R: np.ndarray, reference_p: np.ndarray,
                       reference_R: np.ndarray | None = None, iterations: int = 30,
                       variant: str = "lever") -> RigidRegistration:
    """The closed-form rigid fit of a table (see `RigidRegistration`), one of `RIGID_VARIANTS`.

    The lever arm's directions come from the spread of the orientations that carry it (the
    tracker's for "lever", the reference's for "lever-ref"): with orientations that all agree
    it is invisible (it only shifts t), with yaw only its component along the yaw axis is. A
    direction is fitted when its standard error, with the residual of the fit without lever,
    is below LEVER_LIMIT; otherwise it stays zero and is reported. "kabsch" fits no lever and
    reports every direction held.

    The reference-frame lever l_ref (p_ref + R_ref l_ref = R p_meas + t) is returned as the
    tracker-frame lever it equals under the fitted mount, -X^T l_ref: one correction formula
    for every variant, only the estimate differs (which orientations, with their own noise,
    carry the lever).
    """
    if variant not in CLOSED_FORM:
        raise ValueError(f"no closed form for the rigid variant {variant!r}; expected one of {', '.join(CLOSED_FORM)}")
    if variant in _NEEDS_ORIENTATION and reference_R is None:
        raise ValueError(f"the rigid variant {variant!r} needs reference orientations")
    if variant == "hand-eye":
        return hand_eye_registration(measured_p, measured_R, reference_p, reference_R)
    n = len(measured_p)
    R, t = _kabsch(measured_p, reference_p)
    carrier_R = reference_R if variant == "lever-ref" else measured_R
    determined, vectors = _lever_directions(measured_p, reference_p, R, t, carrier_R, variant)
    free = vectors[:, determined]
    lever = np.zeros(3)
    if free.shape[1]:
        R, t, lever = _alternate_lever(measured_p, measured_R, reference_p, reference_R,
                                       free, R, t, iterations, variant)
    mount = np.eye(3)
    if reference_R is not None:
        # R_ref = R R_meas X^T  =>  X = mean of R_ref^T R R_meas.
        mount = chordal_mean(np.swapaxes(reference_R, -1, -2) @ R @ measured_R)
    held = vectors[:, ~determined].T
    if variant == "lever-ref":
        lever, held = -mount.T @ lever, held @ mount       # reference frame -> tracker frame (X^T v)
    fitted = measured_p + measured_R @ lever
    residual = reference_p - (fitted @ R.T + t)
    sigma_p = float(np.sqrt(np.sum(residual ** 2) / max(3 * n - 6 - free.shape[1], 1)))
    return RigidRegistration(R, t, lever, held, mount, sigma_p)


def station_in_reference(station_pose: str | None, measured: np.ndarray, reference: np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray]:
    """(R_S, t_S) in the reference frame of the station stated by `station_pose`
    (`geometry.parse_station_pose`); one stated in the tracker's own frame is placed there by
    the closed-form rigid fit of these (N, 7) poses."""
    stated = parse_station_pose(station_pose)
    if not stated.in_tracker_frame:
        return stated.in_reference(None)
    rigid = rigid_registration(measured[:, :3], quat_to_matrix(measured[:, 3:7]), reference[:, :3])
    return stated.in_reference((rigid.R, rigid.t))


def _lever_directions(measured_p: np.ndarray, reference_p: np.ndarray, R: np.ndarray,
                      t: np.ndarray, carrier_R: np.ndarray, variant: str) -> tuple[np.ndarray, np.ndarray]:
    """Which lever directions the table determines (a mask over the eigenvectors of the
    carrier's information) and the eigenvectors, from the residual of the fit without lever."""
    n = len(measured_p)
    residual = reference_p - (measured_p @ R.T + t)
    sigma0 = float(np.sqrt(np.sum(residual ** 2) / max(3 * n - 6, 1)))
    # The lever's carrier: p_ref = R p_meas + t + C_i z, C_i = R R_meas,i ("lever") or -R_ref,i.
    # Information about the lever along direction u: sum_i |(R_i - mean R) u|^2.
    centred = carrier_R - carrier_R.mean(axis=0)
    info = np.einsum("nki,nkj->ij", centred, centred)
    values, vectors = np.linalg.eigh(info)
    std = max(sigma0, 1e-6) / np.sqrt(np.maximum(values, 1e-300))
    # The orientations must really turn about a direction (not by their noise) to show the lever.
    turned = np.sqrt(np.maximum(values, 0.0) / n) > AXIS_MIN_RAD
    return (std < LEVER_LIMIT) & turned & (variant != "kabsch"), vectors


def _alternate_lever(measured_p: np.ndarray, measured_R: np.ndarray, reference_p: np.ndarray,
                     reference_R: np.ndarray | None, free: np.ndarray, R: np.ndarray,
                     t: np.ndarray, iterations: int, variant: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The lever along the `free` directions and the rotation and translation, by alternating
    a linear fit of (t, lever) given R with a Kabsch fit of (R, t) given the lever."""
    n = len(measured_p)
    lever = np.zeros(3)
    for _ in range(iterations):
        carrier = R @ measured_R @ free if variant == "lever" else -reference_R @ free
        # Given R: p_ref - R p_meas = t + C_i (free z), linear in (t, z).
        A = np.concatenate([np.broadcast_to(np.eye(3), (n, 3, 3)), carrier], axis=2)
        sol, *_ = np.linalg.lstsq(A.reshape(3 * n, -1), (reference_p - measured_p @ R.T).reshape(-1), rcond=None)
        new = free @ sol[3:]
        if variant == "lever":
            R, t = _kabsch(measured_p + measured_R @ new, reference_p)
        else:
            R, t = _kabsch(measured_p, reference_p + reference_R @ new)
        if np.max(np.abs(new - lever)) < 1e-10:   # m: alternation converges linearly
            return R, t, new
        lever = new
    return R, t, lever


def hand_eye_registration(measured_p: np.ndarray, measured_R: np.ndarray, reference_p: np.ndarray,
                          reference_R: np.ndarray) -> RigidRegistration:
    """The rigid fit of a table with reference orientations as the robot-world-hand-eye problem
    (`registration.robot_world_hand_eye`, closed form, no iteration): T_i X = Y M_i, T the
    reference pose, M the measured one, X the mount (reference point to tracker), Y the
    registration (tracker frame to reference frame). In `RigidRegistration`'s terms R, t = Y,
    mount = R_X and the lever -R_X^T t_X; every lever direction is fitted."""
    from posecorr.geometry import homogeneous
    from posecorr.registration import robot_world_hand_eye

    X, Y = robot_world_hand_eye(homogeneous(reference_R, reference_p), homogeneous(measured_R, measured_p))
    R, t, mount = Y[:3, :3], Y[:3, 3], X[:3, :3]
    lever = -mount.T @ X[:3, 3]
    residual = reference_p - ((measured_p + measured_R @ lever) @ R.T + t)
    sigma_p = float(np.sqrt(np.sum(residual ** 2) / max(3 * len(measured_p) - 9, 1)))
    return RigidRegistration(R, t, lever, np.zeros((0, 3)), mount, sigma_p)


def _kabsch(source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    R, t, _ = umeyama(source, target)
    return R, t


def direction_label(v: np.ndarray) -> str:
    """'[0.02, -0.01, 1.00]': a unit direction, its largest entry positive (no '-0.00')."""
    v = np.asarray(v, float) * np.sign(v[np.argmax(np.abs(v))])
    return "[" + ", ".join(f"{round(float(x), 2) + 0.0:.2f}" for x in v) + "]"


# A pose is a gross outlier when the rigid fit of the others misses it by more than this
# many times their median miss, and by at least OUTLIER_MIN_M: real sessions show per-pose
# errors of 60-100 mm that are data, not blunders; a unit slip or a swapped row is metres.
OUTLIER_FACTOR = 20.0
OUTLIER_MIN_M = 0.5
# A pose missed by more than this many times the others' median, and not gross, is a suspect:
# named, kept. The corpus of simulated sessions (300 seeds, 6 to 60 poses, every spread and
# error no model removes) and the paper's experiments give at most 6.0 times, the two real
# sessions 3.0 and 6.5; one real pose moved 50 mm by a glitch is 16 times, and took the
# session's leave-one-out error from 5.7 to 19 mm.
SUSPECT_FACTOR = 10.0


class Outlier(NamedTuple):
    """A pose the rigid fit of the others misses far more than them."""

    index: int
    miss: float       # m
    typical: float    # the others' median miss, m
    gross: bool       # beyond OUTLIER_FACTOR and OUTLIER_MIN_M: a blunder no model is fitted to


def outliers(measured_p: np.ndarray, measured_R: np.ndarray, reference_p: np.ndarray) -> list[Outlier]:
    """The poses that a rigid fit of the other poses misses by more than SUSPECT_FACTOR times
    their median miss, worst first. One least-squares fit is pulled by a blunder, so the worst
    pose is taken out and the rest refitted, repeatedly."""
    n = len(measured_p)
    keep = np.ones(n, bool)
    found: list[Outlier] = []
    while keep.sum() > max(4, n // 2):
        fit = rigid_registration(measured_p[keep], measured_R[keep], reference_p[keep])
        miss = np.linalg.norm(fit.predict_position(measured_p, measured_R) - reference_p, axis=1)
        candidates = np.flatnonzero(keep)
        worst = int(candidates[np.argmax(miss[candidates])])
        rest = keep.copy()
        rest[worst] = False
        refit = rigid_registration(measured_p[rest], measured_R[rest], reference_p[rest])
        miss = np.linalg.norm(refit.predict_position(measured_p, measured_R) - reference_p, axis=1)
        typical = float(np.median(miss[rest]))
        if miss[worst] <= SUSPECT_FACTOR * typical:
            break
        found.append(Outlier(worst, float(miss[worst]), typical,
                             bool(miss[worst] > max(OUTLIER_MIN_M, OUTLIER_FACTOR * typical))))
        keep = rest
    return found


@dataclass
class Block:
    """A block of parameters judged together (one Param of one effect): its column indices in
    theta, a label ('mount.e'), a physical typical magnitude, and the reason to give if fixed."""

    label: str
    index: np.ndarray
    scale: float
    unit: str
    reason: str
    # The largest standard error, in `scale`s, of a direction kept. None for the registration
    # (station w, v; mount rotation d): unregistered frames put them anywhere (metres, any
    # rotation), so no typical size bounds their standard error; only whether the data can
    # tell them from the blocks before them counts.
    limit: float | None = LIMIT_SCALES


def determined_directions(J: np.ndarray, blocks: Sequence[Block]) -> tuple[np.ndarray, dict[str, str]]:
    """Basis B (n_theta, k) of the determined directions of theta, and {label: reason} of the rest.

    J: the whitened Jacobian (residuals / their noise), columns in theta's units. Blocks are
    taken in the given order; each block's columns, scaled to its typical magnitude, are
    projected off the span kept so far; the SVD of what remains gives its directions and
    their standard errors (1 / singular value, in typical magnitudes). A direction is kept when
    at least MIN_INDEPENDENT of its effect is its own and that error is below the block's
    `limit` (if it has one). B has orthonormal columns in scaled units: theta =
    theta0 + diag(scale) B z.
    """
    n_theta = J.shape[1]
    kept_span = np.zeros((J.shape[0], 0))
    basis: list[np.ndarray] = []
    fixed: dict[str, str] = {}
    kept_by_block: list[tuple[str, np.ndarray]] = []   # (label, orthonormal span of its kept effect)
    for block in blocks:
        own = J[:, block.index] * block.scale
        cols = own - kept_span @ (kept_span.T @ own) if kept_span.shape[1] else own
        _, s, Vt = np.linalg.svd(cols, full_matrices=False)
        std = 1.0 / np.maximum(s, 1e-300)
        independent = s / np.maximum(np.linalg.norm(own @ Vt.T, axis=0), 1e-300)
        keep = independent > MIN_INDEPENDENT
        if block.limit is not None:
            keep &= std < block.limit
        for v in Vt[keep]:
            column = np.zeros(n_theta)
            column[block.index] = v if len(v) > 1 else np.abs(v)   # a 1-D block keeps its sign
            basis.append(column)
        if np.any(~keep):
            # The figure that decided: too little of its own effect (an alias of what came
            # before), or a standard error above the limit (too small an effect on these poses).
            figures = [_why_held(block, independent[j], std[j], own @ Vt[j], kept_by_block)
                       for j in np.flatnonzero(~keep)]
            if len(block.index) == 1 or not np.any(keep):
                fixed[block.label] = f"{block.reason}: {figures[int(np.argmax(std[~keep]))]}"
            else:
                for v, figure in zip(Vt[~keep], figures):
                    fixed[f"{block.label} along {direction_label(v)}"] = f"{block.reason}: {figure}"
        if np.any(keep):
            # What this block adds is orthogonal to the span so far: append its orthonormal basis.
            kept_span = np.concatenate([kept_span, np.linalg.qr(cols @ Vt[keep].T)[0]], axis=1)
            kept_by_block.append((block.label, np.linalg.qr(own @ Vt[keep].T)[0]))
    B = np.stack(basis, axis=1) if basis else np.zeros((n_theta, 0))
    return B, fixed


# The end of the words for a direction held as an alias: `diagnose.split_identifiable` names
# the effect instead where one effect of the model is what it aliases.
BEFORE_IT = "(the rest is what the parameters before it do)"


# A held direction is named as what one block before it does where that block alone holds
# this much of its effect (the cosine of the angle between them: their canonical correlation).
ALIAS_CORRELATION = 0.99


def _alias_of(effect: np.ndarray, kept_by_block: Sequence[tuple[str, np.ndarray]]) -> tuple[str, float] | None:
    """(label, correlation) of the block before whose kept effect comes nearest `effect`, where
    it holds at least ALIAS_CORRELATION of it; None where the effect is spread over several."""
    size = float(np.linalg.norm(effect))
    if size == 0.0 or not kept_by_block:
        return None
    label, Q = max(kept_by_block, key=lambda item: float(np.linalg.norm(item[1].T @ effect)))
    correlation = float(np.linalg.norm(Q.T @ effect)) / size
    return (label, correlation) if correlation >= ALIAS_CORRELATION else None


def _why_held(block: Block, independent: float, std: float, effect: np.ndarray,
              kept_by_block: Sequence[tuple[str, np.ndarray]]) -> str:
    if not np.any(effect):
        return "it does not move these poses at all"
    alias = _alias_of(effect, kept_by_block) if independent <= MIN_INDEPENDENT else None
    if alias is not None:
        return (f"only {independent:.0%} of its effect on these poses is its own: it moves them as {alias[0]} does "
                f"(correlation {alias[1]:.4f})")
    if independent <= MIN_INDEPENDENT:
        return f"only {independent:.0%} of its effect on these poses is its own {BEFORE_IT}"
    return f"its standard error would be {std:.3g} x its typical size ({block.scale:g} {block.unit})"


__all__ = ["CLOSED_FORM", "RIGID_VARIANTS", "rigid_variants", "gross_outliers", "MIN_INDEPENDENT", "Spread", "describe_spread", "chordal_mean", "RigidRegistration", "rigid_registration", "Block",
           "determined_directions", "direction_label", "BEFORE_IT", "LIMIT_SCALES", "FORM_LIMIT_SCALES", "LEVER_LIMIT"]

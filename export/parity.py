"""Parity: the exported float32 graph in onnxruntime against the estimator's float64 predict.

Two pose sets are checked:

- `train`: the training measurements themselves.
- `random`: `n_random` poses with positions uniform in the axis-aligned box of the
  training positions, and orientations = a random training orientation composed with a
  random rotation of angle uniform in [0, RANDOM_ANGLE] rad (direction uniform on the
  sphere), the quaternion sign chosen at random (the sign of the input is free).

Why near the training orientations and not uniform on SO(3): a corrector is only used
where it was trained, and far from it the float64 function itself has legitimate
discontinuities that float32 cannot track (the rotation-vector and quaternion encodings
jump at 180 deg / w = 0, Shepperd's method switches branches, a network's output may fall
where Gram-Schmidt is ill-conditioned). There a 1-ulp input difference flips a branch and
the "error" measures the function's discontinuity, not the export. Within RANDOM_ANGLE of
the data (about half the 30 deg grid step of Exp III) the function is smooth, so the
difference is the graph's rounding error.

Reference: predict(x64) with x64 = the float32-rounded input, in float64, so that the
figure is the error added by the graph, not the unavoidable rounding of the input to the
float32 contract (~6e-8 relative). Errors: position = Euclidean distance (m), rotation =
geodesic angle between the quaternions (rad). The output must also be a unit quaternion
with qw >= 0.
"""
from __future__ import annotations

from enum import StrEnum
from pathlib import Path
from typing import Any

import numpy as np


class Parity(StrEnum):
    """What an export does with the parity check (`onnx_export.to_onnx`): refuse to save a
    model beyond tolerance, record the failure in the metadata, or not check (no training
    data needed)."""

    RAISE = "raise"
    WARN = "warn"
    SKIP = "skip"


RANDOM_ANGLE = 0.25  # rad
TOL_POS = 1e-5       # m
TOL_ROT = 1e-5       # rad
# Positions metres from the origin (a tracker's own frame) carry float32's rounding at that
# magnitude into every product: the tolerance is at least ULPS_POS float32 steps of the
# largest coordinate the graph sees (input or output).
ULPS_POS = 64
# How far the norm of an output quaternion may be off 1: the graph normalises every rotation
# it outputs, so what is left is float32 rounding.
UNIT_TOLERANCE = 1e-5


def position_tolerance(tol_pos: float, *poses: np.ndarray) -> float:
    """max(tol_pos, ULPS_POS float32 steps at the data's largest coordinate)."""
    largest = max(float(np.max(np.abs(np.asarray(p, float)[:, :3]))) for p in poses)
    return max(tol_pos, ULPS_POS * float(np.spacing(np.float32(largest))))


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product of (..., 4) quaternions (w, x, y, z)."""
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack([aw * bw - ax * bx - ay * by - az * bz,
                     aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw], axis=-1)


def quat_angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Geodesic angle (rad) between the rotations of (..., 4) quaternions, sign-free and
    accurate near 0 (atan2 of the vector and scalar parts of a^-1 b)."""
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    b = b / np.linalg.norm(b, axis=-1, keepdims=True)
    d = quat_multiply(a * np.array([1.0, -1.0, -1.0, -1.0]), b)
    return 2.0 * np.arctan2(np.linalg.norm(d[..., 1:], axis=-1), np.abs(d[..., 0]))


def random_poses(measured: np.ndarray, n: int, seed: int = 0, max_angle: float = RANDOM_ANGLE) -> np.ndarray:
    """(n, 7) poses around the training data (see the module docstring)."""
    rng = np.random.default_rng(seed)
    measured = np.asarray(measured, float)
    lo, hi = measured[:, :3].min(axis=0), measured[:, :3].max(axis=0)
    pos = lo + (hi - lo) * rng.random((n, 3))
    base = measured[rng.integers(0, len(measured), n), 3:7]
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    angle = max_angle * rng.random(n)
    delta = np.concatenate([np.cos(angle / 2)[:, None], np.sin(angle / 2)[:, None] * axis], axis=1)
    q = quat_multiply(base, delta)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q *= np.where(rng.random(n) < 0.5, -1.0, 1.0)[:, None]
    return np.concatenate([pos, q], axis=1)


def session(model: Any) -> Any:
    """An onnxruntime CPU session for a ModelProto, serialized bytes or a path."""
    import onnxruntime as ort

    if isinstance(model, (str, Path)):
        data: Any = str(model)
    elif isinstance(model, (bytes, bytearray)):
        data = bytes(model)
    else:
        data = model.SerializeToString()
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    opts.log_severity_level = 3
    return ort.InferenceSession(data, opts, providers=["CPUExecutionProvider"])


def run_onnx(model: Any, poses: np.ndarray, t: np.ndarray | None = None) -> np.ndarray:
    """Apply a model (ModelProto, bytes, path or an existing session) to (N, 7) poses; `t`
    (N,) s feeds a model with a time input (zeros when not given)."""
    sess = model if hasattr(model, "run") and hasattr(model, "get_inputs") else session(model)
    x = np.ascontiguousarray(np.asarray(poses, dtype=np.float32))
    feeds = {sess.get_inputs()[0].name: x}
    if len(sess.get_inputs()) > 1:
        feeds[sess.get_inputs()[1].name] = np.ascontiguousarray(
            np.zeros(len(x), np.float32) if t is None else np.asarray(t, dtype=np.float32))
    return sess.run(None, feeds)[0]


def compare(out32: np.ndarray, ref64: np.ndarray) -> dict[str, float]:
    """Max position (m) / rotation (rad) differences and the output quaternion's validity."""
    out = np.asarray(out32, float)
    dp = np.linalg.norm(out[:, :3] - ref64[:, :3], axis=1)
    dr = quat_angle(out[:, 3:7], ref64[:, 3:7])
    return {"n": int(len(out)), "max_pos_m": float(np.max(dp)), "max_rot_rad": float(np.max(dr)),
            "max_unit_norm_error": float(np.max(np.abs(np.linalg.norm(out[:, 3:7], axis=1) - 1.0))),
            "min_qw": float(np.min(out[:, 3])),
            "finite": bool(np.all(np.isfinite(out)))}


def broken_clause(sets: dict[str, dict[str, Any]]) -> str | None:
    """The first clause of the output contract the graph breaks on a pose set ({label:
    `compare`'s figures}), in words; None where it keeps them all."""
    for label, r in sets.items():
        if not r["finite"]:
            return f"an output that is not finite ({label} poses)"
        if r["min_qw"] < 0.0:
            return f"an output quaternion with qw = {r['min_qw']:.3g} < 0 ({label} poses; expected qw >= 0)"
        if r["max_unit_norm_error"] >= UNIT_TOLERANCE:
            return (f"an output quaternion whose norm is off 1 by {r['max_unit_norm_error']:.3g} ({label} poses; "
                    f"expected within {UNIT_TOLERANCE:g})")
    return None


def check_parity(estimator: Any, model: Any, measured: np.ndarray, *, n_random: int = 10_000, seed: int = 0,
                 tol_pos: float = TOL_POS, tol_rot: float = TOL_ROT, t: np.ndarray | None = None) -> dict[str, Any]:
    """Run the graph in onnxruntime on the training poses and `n_random` random poses
    (see the module docstring) and compare with `estimator.predict` in float64. The position
    tolerance grows with the data's magnitude (`position_tolerance`).

    Returns {"train": {...}, "random": {...}, "max_pos_m", "max_rot_rad", "passed",
    "tol_pos_m", "tol_rot_rad", "random_poses", "reference"} and, where the graph breaks the
    output contract, "broken_clause" (`broken_clause`).
    """
    sess = session(model)
    measured = np.asarray(measured, float)
    report: dict[str, Any] = {}
    sets = {"train": (measured, t)}
    if n_random > 0:
        # Times of a model with a time input: uniform over the training session's span.
        times = None if t is None else np.random.default_rng(seed + 1).uniform(np.min(t), np.max(t), n_random)
        sets["random"] = (random_poses(measured, n_random, seed), times)
    for label, (poses, times) in sets.items():
        x32 = poses.astype(np.float32)
        t32 = None if times is None else np.asarray(times, np.float32)
        args = () if t32 is None else (t32.astype(np.float64),)
        ref = np.asarray(estimator.predict(x32.astype(np.float64), *args), float)
        report[label] = compare(run_onnx(sess, x32, t32), ref)
        tol_pos = position_tolerance(tol_pos, poses, ref)
    max_pos = max(r["max_pos_m"] for r in report.values())
    max_rot = max(r["max_rot_rad"] for r in report.values())
    broken = broken_clause(report)
    if broken is not None:   # kept for a model written anyway (Parity.WARN): its metadata says why
        report["broken_clause"] = broken
    report.update({
        "max_pos_m": max_pos, "max_rot_rad": max_rot,
        "tol_pos_m": tol_pos, "tol_rot_rad": tol_rot,
        "passed": bool(max_pos <= tol_pos and max_rot <= tol_rot and broken is None),
        "random_poses": f"{n_random} poses, positions uniform in the training box, orientations "
                        f"within {RANDOM_ANGLE} rad of training orientations, seed {seed}",
        "reference": "estimator.predict in float64 on the float32-rounded inputs",
    })
    return report

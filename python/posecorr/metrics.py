"""Pose accuracy metrics of paper section 2.5.

rmse_pos (eq. 39, m), rmse_rot (eqs. 40-42, geodesic angle, rad), rmse_total (eq. 43,
w_pos = 1 / m, w_rot = 1), the improvement ratio raw / corrected, and the min / avg / max
summary of the paper's tables 2-4. Poses are (N, 7) arrays x, y, z, qw, qx, qy, qz.
"""
from __future__ import annotations

from typing import Iterable, Mapping

import numpy as np

from .rotations import geodesic_angle, quat_to_matrix

W_POS = 1.0  # 1/m
W_ROT = 1.0  # 1/rad
METRIC_KEYS = ("rmse_pos", "rmse_rot", "rmse_total")


def position_errors(p_ref: np.ndarray, p: np.ndarray) -> np.ndarray:
    """(N,) Euclidean distances in metres."""
    return np.linalg.norm(np.asarray(p_ref, float) - np.asarray(p, float), axis=-1)


def rotation_errors(R_ref: np.ndarray, R: np.ndarray) -> np.ndarray:
    """(N,) geodesic angles of R_ref R^T in rad (eqs. 40-41)."""
    return geodesic_angle(np.asarray(R_ref, float), np.asarray(R, float))


def rmse(errors: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(errors))))


def rmse_pos(p_ref: np.ndarray, p: np.ndarray) -> float:
    """Eq. 39, metres."""
    return rmse(position_errors(p_ref, p))


def rmse_rot(R_ref: np.ndarray, R: np.ndarray) -> float:
    """Eq. 42, radians."""
    return rmse(rotation_errors(R_ref, R))


def rmse_total(pos_errors: np.ndarray, rot_errors: np.ndarray | None,
               w_pos: float = W_POS, w_rot: float = W_ROT) -> float:
    """Eq. 43: RMS of w_pos |dt| + w_rot |dtheta| per pose; position only when rot_errors is None."""
    combined = w_pos * np.asarray(pos_errors, float)
    if rot_errors is not None:
        combined = combined + w_rot * np.asarray(rot_errors, float)
    return rmse(combined)


def pose_errors(reference: np.ndarray, estimate: np.ndarray,
                with_rotation: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """Per-pose position (m) and rotation (rad, or None) errors of (N, 7) poses."""
    reference, estimate = np.atleast_2d(reference), np.atleast_2d(estimate)
    dp = position_errors(reference[:, :3], estimate[:, :3])
    if not with_rotation:
        return dp, None
    return dp, rotation_errors(quat_to_matrix(reference[:, 3:7]), quat_to_matrix(estimate[:, 3:7]))


def pose_metrics(reference: np.ndarray, estimate: np.ndarray,
                 with_rotation: bool = True) -> dict[str, float | None]:
    """{"rmse_pos", "rmse_rot", "rmse_total"} of (N, 7) poses; rmse_rot is None for position-only data."""
    dp, dr = pose_errors(reference, estimate, with_rotation)
    return {"rmse_pos": rmse(dp), "rmse_rot": None if dr is None else rmse(dr),
            "rmse_total": rmse_total(dp, dr)}


def improvement(raw: Mapping[str, float | None], corrected: Mapping[str, float | None]) -> dict[str, float | None]:
    """raw / corrected for each metric: {"improvement_pos", "improvement_rot", "improvement_total"}."""
    out: dict[str, float | None] = {}
    for key in METRIC_KEYS:
        r, c = raw.get(key), corrected.get(key)
        name = "improvement_" + key.split("_", 1)[1]
        out[name] = None if r is None or c is None else (float("inf") if c == 0 else r / c)
    return out


def metric_block(raw: Mapping[str, float | None], corrected: Mapping[str, float | None]) -> dict[str, float | None]:
    """The corrected metrics with their improvements over raw, as in `fit --json`."""
    return {**{k: corrected.get(k) for k in METRIC_KEYS}, **improvement(raw, corrected)}


# The frames are unregistered when the raw rmse_pos is both this many times the best rigid
# fit's and above UNREGISTERED_MIN_M: the paper's registered experiments, whose raw error
# holds a station registration error of a few cm, stay 20-30x above the rigid fit; a tracker's
# own frame is metres away.
UNREGISTERED_FACTOR = 10.0
UNREGISTERED_MIN_M = 0.1
RULE = (f"raw rmse_pos exceeds both {UNREGISTERED_FACTOR:g}× the best rigid fit's on the same poses and "
        f"{UNREGISTERED_MIN_M * 1e3:g} mm (frames unregistered)")


def frames_unregistered(raw: Mapping[str, float | None], rigid: Mapping[str, float | None]) -> bool:
    """`RULE` on the metrics of the measurements and of the best rigid fit, on the same poses:
    where it holds, raw measures the frames' offset, not the tracker."""
    return bool(raw["rmse_pos"] > max(UNREGISTERED_FACTOR * rigid["rmse_pos"], UNREGISTERED_MIN_M))


def named_block(name: str, figures: Mapping[str, float | None]) -> dict[str, float | None | str]:
    """A scored model's figures with its name, as fit's JSON, the ledger and a model file's
    metadata keep the best rigid fit: {"name": "rigid-joint", "rmse_pos": ..., ...}."""
    return {"name": name, **figures}


def block_name(block: Mapping[str, object] | None) -> str | None:
    """The name of a `named_block`; files written before it was "name" called it "model"."""
    if not isinstance(block, Mapping):
        return None
    name = block.get("name", block.get("model"))
    return None if name is None else str(name)


def summarize(values: Iterable[float]) -> dict[str, float]:
    """min / avg / max over repeats, the layout of tables 2-4."""
    v = np.asarray(list(values), dtype=float)
    if v.size == 0:
        raise ValueError("summarize needs at least one value")
    return {"min": float(v.min()), "avg": float(v.mean()), "max": float(v.max())}

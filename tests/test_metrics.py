"""Metrics of paper section 2.5 against hand-computed cases."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from posecorr import metrics


def _pose(p, rotvec) -> np.ndarray:
    q = Rotation.from_rotvec(rotvec).as_quat(scalar_first=True)
    return np.concatenate([p, q])


def test_rmse_pos_by_hand() -> None:
    ref = np.zeros((2, 3))
    est = np.array([[0.003, 0.004, 0.0], [0.0, 0.0, 0.0]])   # errors 5 mm and 0
    assert metrics.rmse_pos(ref, est) == pytest.approx(math.sqrt((0.005**2 + 0) / 2), rel=1e-15)


def test_rmse_rot_and_total_by_hand() -> None:
    ref = np.stack([_pose([0, 0, 0], [0, 0, 0]), _pose([1, 2, 3], [0.1, 0.2, -0.3])])
    # Pose 1: 3 mm off and rotated 0.02 rad about z; pose 2: 4 mm off, rotated 0.01 rad about x.
    est = np.stack([
        _pose([0.003, 0, 0], [0, 0, 0.02]),
        np.concatenate([[1, 2, 3.004], (Rotation.from_rotvec([0.01, 0, 0])
                                        * Rotation.from_rotvec([0.1, 0.2, -0.3])).as_quat(scalar_first=True)]),
    ])
    m = metrics.pose_metrics(ref, est)
    assert m["rmse_pos"] == pytest.approx(math.sqrt((0.003**2 + 0.004**2) / 2), rel=1e-12)
    assert m["rmse_rot"] == pytest.approx(math.sqrt((0.02**2 + 0.01**2) / 2), rel=1e-9)
    # eq. 43 sums the weighted magnitudes per pose before squaring.
    assert m["rmse_total"] == pytest.approx(math.sqrt(((0.003 + 0.02) ** 2 + (0.004 + 0.01) ** 2) / 2), rel=1e-9)


def test_quaternion_sign_does_not_matter() -> None:
    a = _pose([0, 0, 0], [0.3, 0.1, 0.2])
    b = a.copy()
    b[3:] *= -1
    assert metrics.pose_metrics(a[None], b[None])["rmse_rot"] == pytest.approx(0.0, abs=1e-12)


def test_position_only_total_equals_position() -> None:
    ref = np.array([_pose([0, 0, 0], [0, 0, 0])])
    est = np.array([_pose([0.01, 0, 0], [0.5, 0, 0])])
    m = metrics.pose_metrics(ref, est, with_rotation=False)
    assert m["rmse_rot"] is None
    assert m["rmse_total"] == m["rmse_pos"] == pytest.approx(0.01)


def test_improvement_and_paper_table_example() -> None:
    # Table 4, Zhou tansig 16/2: raw total 0.0718, best 0.0042 -> 17.10.
    imp = metrics.improvement({"rmse_pos": 0.0222, "rmse_rot": 0.0508, "rmse_total": 0.0718},
                              {"rmse_pos": 0.0019, "rmse_rot": 0.0025, "rmse_total": 0.0042})
    assert imp["improvement_total"] == pytest.approx(17.10, abs=0.005)
    assert imp["improvement_pos"] == pytest.approx(11.68, abs=0.005)
    assert imp["improvement_rot"] == pytest.approx(20.32, abs=0.005)
    assert metrics.improvement({"rmse_pos": 1.0, "rmse_rot": None, "rmse_total": 1.0},
                               {"rmse_pos": 0.5, "rmse_rot": None, "rmse_total": 0.5})["improvement_rot"] is None


def test_summarize() -> None:
    assert metrics.summarize([3.0, 1.0, 2.0]) == {"min": 1.0, "avg": 2.0, "max": 3.0}
    with pytest.raises(ValueError):
        metrics.summarize([])

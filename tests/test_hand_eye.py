"""A robot carries the tracker (issue 23): the registration is the robot-world-hand-eye problem
T_i X = Y M_i, which posecorr's rigid stage solves in closed form before any iteration.

Truth twice over: the simulated frames (the station and mount effects the simulator applied),
and OpenCV's own solver (`cv2.calibrateRobotWorldHandEye`, Shah's method), written
independently of posecorr.
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

cv2 = pytest.importorskip("cv2")

from posecorr.simulate import simulate_session  # noqa: E402
from posecorr.train.identify import rigid_variants  # noqa: E402
from posecorr.train.physics import PhysicsModel, RigidModel  # noqa: E402

TRACKER_NOISE_LIMIT = (1e-3, 1e-3)      # m, rad: the "1 mm / 1 mrad at the noise of the tracker"
SESSIONS = [(seed, robot) for seed in range(3) for robot in ("ur5e", "ur10e")]


def _angle(w_a: np.ndarray, w_b: np.ndarray) -> float:
    return float((Rotation.from_rotvec(w_a).inv() * Rotation.from_rotvec(w_b)).magnitude())


def _opencv(table) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(R_X, t_X, R_Y, t_Y) from OpenCV: A X = Z B with A the reference pose (its 'world to
    camera'), B the tracker's reported pose ('base to gripper'), X the mount, Z = Y the frame
    from the tracker's reporting frame to the reference frame."""
    R_ref = Rotation.from_quat(table.ref_q[:, [1, 2, 3, 0]]).as_matrix()
    R_meas = Rotation.from_quat(table.meas_q[:, [1, 2, 3, 0]]).as_matrix()
    R_X, t_X, R_Y, t_Y = cv2.calibrateRobotWorldHandEye(
        list(R_ref), list(table.ref_p[:, :, None]), list(R_meas), list(table.meas_p[:, :, None]),
        method=cv2.CALIB_ROBOT_WORLD_HAND_EYE_SHAH)
    return R_X, t_X.ravel(), R_Y, t_Y.ravel()


@pytest.mark.parametrize("seed, robot", SESSIONS)
def test_hand_eye_recovers_registration_and_mount(seed: int, robot: str) -> None:
    session = simulate_session(seed, robot=robot)
    table, truth = session.table, session.effects
    assert session.spec.robot == robot and 30 <= table.n <= 60
    R_X, t_X, R_Y, t_Y = _opencv(table)
    for model in (RigidModel(variant="hand-eye"), PhysicsModel(("station", "mount"))):
        fitted = model.fit(table.measured, table.reference).params_
        station, mount = fitted["station"], fitted["mount"]
        # Against the simulated truth: mount (d, e) and station (w, v), within 1 mrad / 1 mm.
        assert _angle(mount[:3], truth["mount"][:3]) < TRACKER_NOISE_LIMIT[1]
        assert np.linalg.norm(mount[3:] - truth["mount"][3:]) < TRACKER_NOISE_LIMIT[0]
        assert _angle(station[:3], truth["station"][:3]) < TRACKER_NOISE_LIMIT[1]
        assert np.linalg.norm(station[3:] - truth["station"][3:]) < TRACKER_NOISE_LIMIT[0]
        # Against OpenCV: X is the mount (R_X = Exp(d), t_X = e), Y the inverse station rotation.
        assert _angle(mount[:3], Rotation.from_matrix(R_X).as_rotvec()) < 1e-4
        assert np.linalg.norm(mount[3:] - t_X) < 1e-4
        assert _angle(-station[:3], Rotation.from_matrix(R_Y).as_rotvec()) < 1e-4
        # and p_ref = R_Y p_meas + t_Y against measured = c + Exp(w)(p_ref - c) + v, c the mean
        # reference position: v = R_Y^T (c - t_Y) - c
        c = table.ref_p.mean(axis=0)
        assert np.linalg.norm(station[3:] - (R_Y.T @ (c - t_Y) - c)) < 1e-4


def test_the_closed_form_is_the_rigid_stage_itself() -> None:
    """The hand-eye variant is the closed form, no iteration: on noise-free robot poses it is
    exact, and a table whose orientations turn about one axis does not offer it."""
    session = simulate_session(7, robot="ur5e")
    table = session.table
    exact = session.context
    from posecorr.effects import apply_effects
    from posecorr.rotations import matrix_to_quat, quat_to_matrix

    R_ref = quat_to_matrix(table.ref_q)
    p, R = apply_effects(table.ref_p, R_ref, {"mount": session.effects["mount"]}, exact)
    p, R = apply_effects(p, R, {"station": session.effects["station"]}, exact)
    clean = np.concatenate([p, matrix_to_quat(R)], axis=1)
    fitted = RigidModel(variant="hand-eye").fit(clean, table.reference).params_
    np.testing.assert_allclose(fitted["mount"], session.effects["mount"], atol=1e-9)
    np.testing.assert_allclose(fitted["station"], session.effects["station"], atol=1e-9)
    assert "hand-eye" in rigid_variants(True, 3) and "hand-eye" not in rigid_variants(True, 1)
    assert "hand-eye" not in rigid_variants(False, 3)
    with pytest.raises(ValueError, match="needs reference orientations"):
        RigidModel(with_rotation=False, variant="hand-eye").fit(table.measured, table.reference)

"""Features against the simulator's own lattice: Exp III roll/pitch/yaw come back exactly."""
from __future__ import annotations

import numpy as np

from posecorr.analysis.features import pose_features
from posecorr.geometry import station_pose, upright_rotation, rot_x, rot_y, rot_z
from posecorr.rotations import matrix_to_quat


def test_roll_pitch_yaw_recovered() -> None:
    rng = np.random.default_rng(0)
    angles = rng.uniform(-0.5, 0.5, size=(50, 3))
    R = np.stack([upright_rotation() @ rot_z(y) @ rot_y(p) @ rot_x(r) for r, p, y in angles])
    poses = np.concatenate([np.tile([0.0, -0.6, 0.5], (50, 1)), matrix_to_quat(R)], axis=1)
    f = pose_features(poses)
    np.testing.assert_allclose(np.stack([f["roll"], f["pitch"], f["yaw"]], axis=1), angles, atol=1e-12)


def test_station_angles_and_range() -> None:
    R_S, t_S = station_pose()
    # A point 2 m straight ahead of the station (along its -z axis) has zero sweep angles.
    p = t_S + R_S @ np.array([0.0, 0.0, -2.0])
    pose = np.concatenate([p, matrix_to_quat(R_S)])[None]
    f = pose_features(pose, t=np.array([5.0]))
    assert abs(f["azimuth"][0]) < 1e-12 and abs(f["elevation"][0]) < 1e-12
    np.testing.assert_allclose(f["range"], 2.0)
    # With the station's orientation the tracker's z axis points back at the station:
    # the line of sight hits it head-on, incidence 0.
    np.testing.assert_allclose(f["incidence"], 0.0, atol=1e-7)
    assert f["t"][0] == 5.0


def test_roll_pitch_yaw_rebuild_the_rotation_at_gimbal_lock() -> None:
    """At pitch +-90 degrees roll and yaw came from atan2 of rounding errors: the three angles
    rebuilt another rotation (a matrix error of 2). scipy's as_euler("ZYX") is the truth,
    random rotations and locked ones alike."""
    import warnings

    from scipy.spatial.transform import Rotation

    from posecorr.analysis.features import roll_pitch_yaw

    rng = np.random.default_rng(0)
    locked = Rotation.from_euler("ZYX", np.stack([rng.uniform(-3, 3, 20), np.repeat([np.pi / 2, -np.pi / 2], 10),
                                                  rng.uniform(-3, 3, 20)], axis=1))
    rotations = Rotation.concatenate([Rotation.random(200, random_state=1), locked])
    got = roll_pitch_yaw(rotations.as_matrix())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)   # scipy's "gimbal lock detected"
        yaw, pitch, roll = rotations.as_euler("ZYX").T
    rebuilt = Rotation.from_euler("ZYX", np.stack([got["yaw"], got["pitch"], got["roll"]], axis=1))
    np.testing.assert_allclose(rebuilt.as_matrix(), rotations.as_matrix(), atol=1e-9)
    np.testing.assert_allclose(got["pitch"], pitch, atol=1e-9)
    free = np.abs(np.cos(pitch)) > 1e-6
    np.testing.assert_allclose(got["roll"][free], roll[free], atol=1e-9)
    np.testing.assert_allclose(np.cos(got["yaw"] - yaw), 1.0, atol=1e-9)


def test_unregistered_frames_have_no_station_and_angles_of_the_orientation_as_given() -> None:
    """Where the frames are unregistered the station's place in the reference frame is unknown:
    no range, azimuth, elevation or incidence, and roll, pitch, yaw are those of the reference
    orientation itself (scipy's as_euler("ZYX") as the truth), not relative to the paper's
    upright (which gave the identity a yaw of 85.5 degrees on the real session Exp1)."""
    from scipy.spatial.transform import Rotation

    from posecorr.analysis.features import STATION_FEATURES, pose_features

    rotations = Rotation.concatenate([Rotation.identity(), Rotation.random(30, random_state=4)])
    poses = np.hstack([np.random.default_rng(4).uniform(-2, 2, (31, 3)), rotations.as_quat(scalar_first=True)])
    registered, unregistered = pose_features(poses), pose_features(poses, registered=False)
    assert set(STATION_FEATURES) <= set(registered) and not set(STATION_FEATURES) & set(unregistered)
    yaw, pitch, roll = rotations.as_euler("ZYX").T
    np.testing.assert_allclose(unregistered["yaw"], yaw, atol=1e-9)
    np.testing.assert_allclose(unregistered["pitch"], pitch, atol=1e-9)
    np.testing.assert_allclose(unregistered["roll"], roll, atol=1e-9)
    assert unregistered["yaw"][0] == 0.0 and abs(registered["yaw"][0]) > 0.1
    for name in "xyz":
        np.testing.assert_array_equal(unregistered[name], registered[name])

"""Forward and inverse kinematics against closed forms and an independently structured URDF."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from posecorr.kinematics import UR_ARMS, KinematicsError, UrdfArm, inverse, load_arm, reference_poses

# The UR5e as the ROS description package lays it out: a `base_link` turned half a turn about z
# from the controller's `base`, joint frames with their own roll/pitch/yaw offsets, and a `tool0`
# reached through a `flange` frame. Joint origins (xyz, rpy) are UR's published UR5e kinematics in
# that package's convention; nothing here is derived from the DH table under test.
UR5E_DESCRIPTION = [
    ("base_link", "base_link_inertia", "fixed", (0, 0, 0), (0, 0, np.pi)),
    ("base_link_inertia", "shoulder_link", "revolute", (0, 0, 0.1625), (0, 0, 0)),
    ("shoulder_link", "upper_arm_link", "revolute", (0, 0, 0), (np.pi / 2, 0, 0)),
    ("upper_arm_link", "forearm_link", "revolute", (-0.425, 0, 0), (0, 0, 0)),
    ("forearm_link", "wrist_1_link", "revolute", (-0.3922, 0, 0.1333), (0, 0, 0)),
    ("wrist_1_link", "wrist_2_link", "revolute", (0, -0.0997, 0), (np.pi / 2, 0, 0)),
    ("wrist_2_link", "wrist_3_link", "revolute", (0, 0.0996, 0), (np.pi / 2, np.pi, np.pi)),
    ("wrist_3_link", "flange", "fixed", (0, 0, 0), (0, -np.pi / 2, -np.pi / 2)),
    ("flange", "tool0", "fixed", (0, 0, 0), (np.pi / 2, 0, np.pi / 2)),
    ("base_link", "base", "fixed", (0, 0, 0), (0, 0, np.pi)),
]


def write_urdf(path, chain=UR5E_DESCRIPTION) -> None:
    links = sorted({c for p, c, *_ in chain} | {p for p, *_ in chain})
    parts = ['<?xml version="1.0"?>', '<robot name="ur5e_test">']
    parts += [f'  <link name="{name}"/>' for name in links]
    for i, (parent, child, kind, xyz, rpy) in enumerate(chain):
        parts.append(f'  <joint name="{child}_joint" type="{kind}"><parent link="{parent}"/><child link="{child}"/>'
                     f'<origin xyz="{" ".join(map(repr, map(float, xyz)))}" rpy="{" ".join(map(repr, map(float, rpy)))}"/>'
                     + ('<axis xyz="0 0 1"/><limit lower="-6.3" upper="6.3" effort="1" velocity="1"/>'
                        if kind != "fixed" else "") + "</joint>")
    parts.append("</robot>")
    path.write_text("\n".join(parts))


def test_ur5e_zero_pose_is_the_published_stretched_arm() -> None:
    # At q = 0 a UR arm lies along -x: flange at (a2 + a3, -(d4 + d6), d1 - d5), tool z along -y.
    T = load_arm("ur5e").forward(np.zeros(6))[0]
    np.testing.assert_allclose(T[:3, 3], [-0.425 - 0.3922, -(0.1333 + 0.0996), 0.1625 - 0.0997], atol=1e-12)
    np.testing.assert_allclose(T[:3, 2], [0.0, -1.0, 0.0], atol=1e-12)


def test_dh_model_agrees_with_the_ros_description_urdf(tmp_path) -> None:
    path = tmp_path / "ur5e.urdf"
    write_urdf(path)
    urdf = UrdfArm(path, base_link="base_link", tip_link="tool0")
    assert urdf.joint_names == tuple(f"{c}_joint" for c in ("shoulder_link", "upper_arm_link", "forearm_link",
                                                            "wrist_1_link", "wrist_2_link", "wrist_3_link"))
    q = np.random.default_rng(0).uniform(-np.pi, np.pi, (50, 6))
    base_link_T_base = np.eye(4)
    base_link_T_base[:3, :3] = Rotation.from_euler("z", np.pi).as_matrix()
    np.testing.assert_allclose(urdf.forward(q), base_link_T_base @ load_arm("ur5e").forward(q), atol=1e-9)


def test_urdf_errors_name_the_file(tmp_path) -> None:
    path = tmp_path / "bad.urdf"
    path.write_text("<robot><link/></robot")
    with pytest.raises(KinematicsError, match="bad.urdf"):
        UrdfArm(path)
    write_urdf(path)
    with pytest.raises(KinematicsError, match="tip link 'nope'"):
        UrdfArm(path, base_link="base_link", tip_link="nope")


@pytest.mark.parametrize("name", sorted(UR_ARMS))
def test_inverse_reaches_forward_poses(name: str) -> None:
    arm = UR_ARMS[name]
    rng = np.random.default_rng(1)
    for _ in range(5):
        q_true = np.array([1.4, -1.2, 1.7, -2.0, 1.5, 0.3]) + rng.uniform(-0.3, 0.3, 6)
        target = arm.forward(q_true)[0]
        q = inverse(arm, target, q_true + rng.uniform(-0.1, 0.1, 6))
        np.testing.assert_allclose(arm.forward(q)[0], target, atol=1e-10)


def test_reference_pose_appends_the_paper_adapter() -> None:
    arm = load_arm("ur5e")
    q = np.array([[0.3, -1.0, 1.2, -1.7, 1.5, 0.2]])
    flange = arm.forward(q)[0]
    tracker = reference_poses(arm, q)[0]
    np.testing.assert_allclose(tracker[:3, 3], flange[:3, 3] + 0.042 * flange[:3, 2], atol=1e-12)
    np.testing.assert_allclose(tracker[:3, :3], flange[:3, :3], atol=1e-12)


def test_unknown_robot_is_refused() -> None:
    with pytest.raises(KinematicsError, match="unknown robot 'ur7'"):
        load_arm("ur7")

"""Per-pose features where residual structure can live (diagnosis and report).

All angles in rad, positions in m. Station quantities use the station's pose where the
session states it (`PoseTable.station_pose`), else the nominal one of eq. 23, and the
effects' own formulas (`effects.station_coords`, the `sweep` effect's angles):
s = R_S^T (p - t_S), the station looks along its -z axis; azimuth and elevation are the sweep
angles of the `sweep` effect; incidence is the angle between the tracker's z axis and the line
of sight back to the station. roll, pitch, yaw are the intrinsic Z-Y-X angles of the
orientation relative to `geometry.upright_rotation()` (Experiment III's convention
R = R_up Rz(yaw) Ry(pitch) Rx(roll)).

The nominal station and "upright" are places in the registered base frame. Where the frames are
unregistered (`metrics.frames_unregistered`: the reference is a laser tracker's frame, say)
and the session does not state its station, nobody knows where the station stands in the
reference frame: the station features are left out (`STATION_FEATURES`). There roll, pitch,
yaw are of the orientation as the table gives it.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from .._xp import namespace
from ..data import PoseTable
from ..effects import EffectContext, station_coords, sweep_angles
from ..geometry import upright_rotation
from ..rotations import normalize, quat_to_matrix

FEATURES = ("x", "y", "z", "range", "azimuth", "elevation", "incidence", "roll", "pitch", "yaw", "t")
STATION_FEATURES = ("range", "azimuth", "elevation", "incidence")
# What a page or a diagnosis says in their place.
UNPLACED_STATION = ("range, azimuth, elevation and incidence are left out: the frames are unregistered, so "
                    "where the station stands in the reference frame is unknown")


def pose_features(poses: np.ndarray, t: np.ndarray | None = None, registered: bool = True,
                  station: tuple[np.ndarray, np.ndarray] | None = None) -> dict[str, np.ndarray]:
    """{feature: (N,) values} of (N, 7) poses; "t" only when a time column is given; the
    station's features from `station` ((R_S, t_S) in the poses' frame) where given, else
    from the nominal station in `registered` frames; angles from upright only in those."""
    poses = np.atleast_2d(np.asarray(poses, float))
    p = poses[:, :3]
    R = quat_to_matrix(poses[:, 3:7])
    out = {"x": p[:, 0], "y": p[:, 1], "z": p[:, 2]}
    if registered or station is not None:
        ctx = EffectContext.default()
        if station is not None:
            ctx = replace(ctx, R_S=station[0], t_S=station[1])
        s = station_coords(p, ctx)
        # The sweep effect's own angles: a residual along azimuth is one that effect could bend.
        azimuth, elevation, distance = sweep_angles(namespace(s), s)
        u = normalize(p - ctx.t_S)
        cos_incidence = np.clip(-np.einsum("ni,ni->n", R[:, :, 2], u), -1.0, 1.0)
        out.update({"range": distance[:, 0], "azimuth": azimuth, "elevation": elevation,
                    "incidence": np.arccos(cos_incidence)})
    if registered:
        R = np.swapaxes(upright_rotation(), -1, -2) @ R
    out.update(roll_pitch_yaw(R))
    if t is not None:
        out["t"] = np.asarray(t, float)
    return out


def roll_pitch_yaw(R: np.ndarray) -> dict[str, np.ndarray]:
    """Angles (rad) with R = Rz(yaw) Ry(pitch) Rx(roll). At pitch +-90 degrees roll and yaw
    turn about one axis and only their difference is defined (the atan2s of two rounding
    errors otherwise, angles that rebuild another rotation): roll is taken as 0 there, the
    convention of scipy's as_euler."""
    cos_pitch = np.hypot(R[:, 0, 0], R[:, 1, 0])
    locked = cos_pitch < 1e-9
    return {"roll": np.where(locked, 0.0, np.arctan2(R[:, 2, 1], R[:, 2, 2])),
            "pitch": np.arctan2(-R[:, 2, 0], cos_pitch),
            "yaw": np.where(locked, np.arctan2(-R[:, 0, 1], R[:, 1, 1]), np.arctan2(R[:, 1, 0], R[:, 0, 0]))}


def table_features(table: PoseTable, registered: bool = True) -> dict[str, np.ndarray]:
    """Features of a table's reference poses (the robot's, free of tracker error)."""
    return pose_features(table.reference, table.time(), registered, stated_station(table))


def stated_station(table: PoseTable) -> tuple[np.ndarray, np.ndarray] | None:
    """(R_S, t_S) in the reference frame of the station the session states, None where it
    states none."""
    if table.station_pose is None:
        return None
    from ..train.identify import station_in_reference

    return station_in_reference(table.station_pose, table.measured, table.reference)

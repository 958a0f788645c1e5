"""A recording -> the paired-pose table (docs/design.md, "Data"), one row per accepted still segment.

Steps: read the joint and tracker streams (FORMATS), order the joints as the arm's model,
find the still segments, estimate the clock offset (or take the user's), gate and average the
tracker samples of every segment, map them into the base frame with the registration
(base_T_station, eq. 20) and pair them with the forward kinematics of the mean joint angles
times end_T_tracker (eqs. 19, 22). Rejected segments are kept in the result with their reason.
"""
from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from ..data import JOINTS, PoseTable, implausible_spread
from .. import geometry
from ..geometry import END_T_TRACKER, base_T_station, homogeneous
from ..jsonable import json_default
from ..kinematics import DEFAULT_ARM, Arm, load_arm, reference_poses
from ..registration import quaternion_order_note
from ..rotations import matrix_to_quat, quat_to_matrix
from .align import Alignment, check_overlap, estimate_offset
from .csvlog import CsvColumns, read_csv_log
from .rosformats import read_ros
from .segments import Segment, StillOptions, find_segments, measure
from .streams import IngestError, JointStream, PoseStream, keep_usable, median_period


@dataclass
class IngestOptions:
    robot: str = DEFAULT_ARM                # a UR model name or a URDF path
    base_link: str | None = None
    tip_link: str | None = None
    tool: np.ndarray = field(default_factory=lambda: END_T_TRACKER.copy())          # end_T_tracker
    registration: np.ndarray = field(default_factory=base_T_station)                # base_T_<tracker frame>
    joints_topic: str | None = None
    tracker_topic: str | None = None
    tracker_frame: str | None = None
    stamps: str = "header"                  # header stamps, or "receive" (the recorder's clock)
    joint_names: tuple[str, ...] | None = None
    csv: CsvColumns = field(default_factory=CsvColumns)
    still: StillOptions = field(default_factory=StillOptions)
    offset: float | None = None             # s, tracker clock - robot clock; None: estimate
    max_offset: float = 5.0
    session: str | None = None


@dataclass
class IngestResult:
    table: PoseTable
    segments: list[Segment]
    alignment: Alignment
    t0: float                                # robot clock of the first joint sample
    joints: JointStream
    tracker: PoseStream
    options: IngestOptions
    notes: list[str] = field(default_factory=list)      # what was read unusually or left out, and how

    @property
    def rejected(self) -> list[Segment]:
        return [s for s in self.segments if s.status != "ok"]

    def summary(self) -> dict:
        o = self.options
        return {
            "recording": [str(s) for s in dict.fromkeys((self.joints.source, self.tracker.source))],
            "rows": self.table.n, "segments_found": len(self.segments), "segments_rejected": len(self.rejected),
            "offset_s": self.alignment.offset, "offset_source": self.alignment.source,
            "offset_correlation": self.alignment.correlation,
            "joint_samples": len(self.joints.t), "tracker_samples": len(self.tracker.t),
            "joint_rate_hz": _rate(self.joints.t), "tracker_rate_hz": _rate(self.tracker.t),
            "robot": o.robot, "joint_names": list(self.joints.names), "notes": self.notes, "still": asdict(o.still),
            "segments": [s.describe(self.t0) for s in self.segments],
        }


def _rate(t: np.ndarray) -> float | None:
    """The publishing rate, from the median period (dropped samples do not lower it)."""
    period = median_period(t)
    return 1.0 / period if period > 0 else None


# Recording formats by how the path looks: (test, reader).
def _is_csv(paths: list[Path]) -> bool:
    return all(p.suffix.lower() == ".csv" for p in paths)


FORMATS: dict[str, Callable[[list[Path], IngestOptions], tuple[JointStream, PoseStream]]] = {
    "csv": lambda paths, o: read_csv_log(paths, o.csv),
    "ros": lambda paths, o: read_ros(paths[0], o.joints_topic, o.tracker_topic, o.tracker_frame, o.stamps),
}


def read_recording(paths: list[str | Path], options: IngestOptions) -> tuple[JointStream, PoseStream]:
    paths = [Path(p) for p in paths]
    if _is_csv(paths):
        return FORMATS["csv"](paths, options)
    if len(paths) != 1:
        raise IngestError(f"{', '.join(map(str, paths))}: give one bag or MCAP file (several files: CSV logs only)")
    return FORMATS["ros"](paths, options)


def order_joints(joints: JointStream, arm: Arm, wanted: tuple[str, ...] | None) -> tuple[list[int], list[str]]:
    """The stream's columns of the arm's joints, in the arm's order, and a note on how they were found.

    By name: the names given (--joint-names) or the model's, every one of them in the stream as
    it is or, all of them, after one common prefix (a UR driver's tf_prefix: ur_shoulder_pan_joint).
    By position only where the format fixes the order: a CSV log's columns (--joint-cols, in
    kinematic order by its layout) and messages that name no joints. A stream that names its
    joints otherwise is refused: read in message order it gives a wrong table without a sign
    (the UR driver publishes the elbow first).
    """
    names, found = wanted or arm.joint_names, joints.names
    if set(names) <= set(found):
        return [found.index(n) for n in names], []
    prefixes = _prefixes(names, found)
    if len(prefixes) == 1:
        prefix = prefixes[0]
        return [found.index(prefix + n) for n in names], [
            f"{joints.source}: the joint names carry the prefix {prefix!r} (a driver's tf_prefix): "
            f"matched to the robot's {', '.join(names)} after it"]
    columns = list(range(joints.q.shape[1]))
    if wanted is None and len(columns) == arm.n_joints:
        if joints.positional:
            return columns, []
        if not found:
            return columns, [f"{joints.source}: the messages name no joints: read in their order as the robot's "
                             f"{', '.join(names)}"]
    several = f" (they match after each of the prefixes {', '.join(map(repr, prefixes))})" if prefixes else ""
    raise IngestError(f"{joints.source}: joints {', '.join(found) or 'unnamed'} do not match the robot's "
                      f"{', '.join(names)}{several}; name them in kinematic order with --joint-names")


def _prefixes(names: tuple[str, ...], found: tuple[str, ...]) -> list[str]:
    """The prefixes p with p + name among `found` for every one of `names`."""
    candidates = {f[: len(f) - len(names[0])] for f in found if f.endswith(names[0])}
    return sorted(p for p in candidates if all(p + n in found for n in names))


# A UR's joints turn within +-2 pi (+-360 deg: the e-series and CB3 data sheets, ur_description's
# limits) and a URDF's continuous joint may be wound a turn further: radians stay within +-4 pi.
# A calibration recording in degrees goes beyond on some joint (any pose more than 12.6 deg
# from zero; a UR's home has the shoulder at -90), and read as radians gives a wrong table.
MAX_JOINT_RAD = 4 * np.pi


def check_units(joints: JointStream, columns: list[int], tracker: PoseStream) -> None:
    """IngestError on joint angles (of the arm's `columns`) that cannot be radians and tracker
    positions that cannot be metres. Refused, not warned: the still-speed threshold, the gate and
    the forward kinematics all take these units, so nothing after them would be right."""
    q = joints.q[:, columns]
    peak = np.abs(q).max(axis=0)
    j = int(np.argmax(peak))
    if peak[j] > MAX_JOINT_RAD:
        value = q[int(np.argmax(np.abs(q[:, j]))), j]
        name = joints.names[columns[j]] if joints.names else f"{j + 1}"
        raise IngestError(f"{joints.source}: joint {name} reads {value:.6g}, beyond ±4π = {MAX_JOINT_RAD:.4g} "
                          "(a revolute joint reads within ±2π rad): degrees? expected radians")
    spread = implausible_spread(tracker.p)
    if spread is not None:
        raise IngestError(f"{tracker.source}: the tracker positions lie a typical {spread:.4g} m from their "
                          "median, and a tracked cell spans a few metres: millimetres? expected metres")


def ingest(paths: list[str | Path], options: IngestOptions | None = None) -> IngestResult:
    """The paired-pose table of a recording (module docstring); IngestError on what cannot be used."""
    options = options or IngestOptions()
    arm = load_arm(options.robot, options.base_link, options.tip_link)
    joints, tracker = read_recording(paths, options)
    what = ", ".join(str(p) for p in paths)
    columns, notes = order_joints(joints, arm, options.joint_names)
    joints = keep_usable(joints, joints.q[:, columns])       # a gripper's NaN leaves the arm's joints alone
    tracker = keep_usable(tracker, np.hstack([tracker.p, tracker.q]))
    q = joints.q[:, columns]
    check_units(joints, columns, tracker)

    if options.offset is None:
        alignment = estimate_offset(joints.t, reference_poses(arm, q, options.tool), tracker.t, tracker.p,
                                    options.max_offset, what)
    else:
        check_overlap(joints.t, tracker.t - options.offset, 0.0, what, given=options.offset)
        alignment = Alignment(float(options.offset), None, "given")
    t_tracker = tracker.t - alignment.offset

    segments = find_segments(joints.t, q, options.still)
    if not segments:
        raise IngestError(f"{what}: no still segment (every joint slower than --still-speed {options.still.speed:g} "
                          f"rad/s for at least --min-still {options.still.min_duration:g} s)")
    for segment in segments:
        measure(segment, t_tracker, tracker.p, tracker.q, options.still)
    accepted = [s for s in segments if s.status == "ok"]
    if not accepted:
        reasons = "; ".join(f"segment {s.index}: {s.reason}" for s in segments[:3])
        which = "the one still segment is" if len(segments) == 1 else f"none of {len(segments)} still segments is"
        raise IngestError(f"{what}: {which} usable ({reasons}"
                          f"{'; ...' if len(segments) > 3 else ''})")
    for row, segment in enumerate(accepted):
        segment.row = row
    table = _table(accepted, arm, options, float(joints.t[0]), what)
    notes += _order_notes(accepted, table, tracker.source, options.csv if _is_csv([Path(p) for p in paths]) else None)
    return IngestResult(table, segments, alignment, float(joints.t[0]), joints, tracker, options,
                        joints.notes + tracker.notes + notes)


def _order_notes(segments: list[Segment], table: PoseTable, source: str, csv: CsvColumns | None) -> list[str]:
    """`registration.quaternion_order_note` on the tracker's quaternions as read (before the
    registration, whose product would not shift back) against the forward kinematics', with
    the columns a CSV log's were read from: a log written x, y, z, w read as w, x, y, z gives a
    table that fits badly and says nothing of why."""
    note = quaternion_order_note(np.stack([s.quat for s in segments]), table.ref_q,
                                 np.stack([s.p for s in segments]), table.ref_p)
    if note is None:
        return []
    columns = f"; ingest read the columns {', '.join(csv.pose[3:])} as w, x, y, z (--pose-cols)" if csv else ""
    return [f"{source}, tracker quaternions against the forward kinematics: {note}{columns}"]


def _table(segments: list[Segment], arm: Arm, options: IngestOptions, t0: float, what: str) -> PoseTable:
    q = np.stack([s.q for s in segments])
    ref = reference_poses(arm, q, options.tool)
    meas = options.registration @ homogeneous(quat_to_matrix(np.stack([s.quat for s in segments])),
                                              np.stack([s.p for s in segments]))
    extras: dict[str, np.ndarray] = {
        "id": np.array([f"seg{s.index:04d}" for s in segments], dtype=object),
        "t": np.array([0.5 * (s.window[0] + s.window[1]) - t0 for s in segments]),
    }
    if q.shape[1] == len(JOINTS):
        extras.update({name: q[:, i] for i, name in enumerate(JOINTS)})
    session = options.session or Path(what.split(",")[0]).stem
    extras["session"] = np.array([session] * len(segments), dtype=object)
    extras["jitter_mm"] = np.array([s.jitter_mm for s in segments])
    extras["n_samples"] = np.array([str(s.n_kept) for s in segments], dtype=object)
    return PoseTable(meas_p=meas[:, :3, 3].copy(), meas_q=matrix_to_quat(meas[:, :3, :3]),
                     ref_p=ref[:, :3, 3].copy(), ref_q=matrix_to_quat(ref[:, :3, :3]), extras=extras)


def parse_transform(text: str, kind: str) -> np.ndarray:
    """`geometry.parse_transform`, refused as an IngestError."""
    return geometry.parse_transform(text, kind, IngestError)


def segments_path(table_path: str | Path) -> Path:
    """The sidecar beside a table: TABLE.csv -> TABLE.csv.segments.json."""
    table_path = Path(table_path)
    return table_path.with_name(table_path.name + ".segments.json")


def write_segments(result: IngestResult, table_path: str | Path) -> Path:
    from ..safeio import write_text

    path = segments_path(table_path)
    write_text(path, json.dumps(result.summary(), indent=2, default=json_default) + "\n")
    return path

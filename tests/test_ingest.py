"""From a recording to the paired table: round trips through every format, segments, errors."""
from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from posecorr.data import read_table, write_table
from posecorr.ingest import IngestError, IngestOptions, JointStream, PoseStream, ingest
from posecorr.ingest.csvlog import CsvColumns, read_csv_log, write_csv_log
from posecorr.ingest.segments import StillOptions, find_segments, gate, quaternion_mean
from posecorr.recording import RecordingOptions, simulate_recording, write_recording
from posecorr.simulate import simulate

TARGETS = 5          # a 57 s recording: 28k joint states, 14k tracker poses per format
OFFSET = RecordingOptions().clock_offset


def posecorr(*args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONWARNINGS": "ignore"}
    return subprocess.run([sys.executable, "-m", "posecorr.cli", *args], capture_output=True, text=True,
                          env=env, timeout=600)


def one_line_error(out: subprocess.CompletedProcess, *fragments: str) -> str:
    assert out.returncode == 2, (out.returncode, out.stdout, out.stderr)
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("posecorr ingest: error: "), out.stderr
    assert "Traceback" not in out.stderr
    for fragment in fragments:
        assert fragment in lines[0], (fragment, lines[0])
    return lines[0]


@pytest.fixture(scope="module")
def experiment3():
    return simulate(3, seed=0)


@pytest.fixture(scope="module")
def recording(experiment3):
    return simulate_recording(experiment3, n_targets=TARGETS, seed=0)


# --- the round trip, as a user runs it ------------------------------------------------------

@pytest.mark.parametrize("name", ["rec.bag", "rec.mcap", "rec.csv"])
def test_simulated_recording_gives_back_the_simulated_table(tmp_path, name: str) -> None:
    sim = posecorr("simulate", "--experiment", "3", "--seed", "0", "--targets", str(TARGETS),
                   "--recording", str(tmp_path / name), "-o", str(tmp_path / "sim.csv"), "--json")
    assert sim.returncode == 0, sim.stderr
    assert json.loads(sim.stdout)["recording"]["clock_offset_s"] == OFFSET
    out = posecorr("ingest", str(tmp_path / name), "-o", str(tmp_path / "table.csv"), "--json")
    assert out.returncode == 0, out.stderr
    result = json.loads(out.stdout)
    expected, got = read_table(tmp_path / "sim.csv"), read_table(tmp_path / "table.csv")

    assert got.n == expected.n == TARGETS and result["segments_rejected"] == 0
    assert abs(result["offset_s"] - OFFSET) < 2e-3, result["offset_s"]
    # References: forward kinematics of the recorded joints against the commanded targets.
    np.testing.assert_allclose(got.ref_p, expected.ref_p, atol=1e-6)
    assert np.all(np.abs(np.sum(got.ref_q * expected.ref_q, axis=1)) > 1 - 1e-12)
    # Measurements: the mean of the gated samples, within the jitter of the table's poses.
    jitter_m = got.extras["jitter_mm"] * 1e-3
    assert np.all(np.linalg.norm(got.meas_p - expected.meas_p, axis=1) < jitter_m)
    assert np.all((0.15 < got.extras["jitter_mm"]) & (got.extras["jitter_mm"] < 0.4))
    angle = (Rotation.from_quat(got.meas_q[:, [1, 2, 3, 0]]).inv()
             * Rotation.from_quat(expected.meas_q[:, [1, 2, 3, 0]])).magnitude()
    assert np.all(angle < RecordingOptions().jitter_r)
    np.testing.assert_allclose(got.extras["t"], expected.extras["t"], atol=0.05)
    assert all(int(n) > 1000 for n in got.extras["n_samples"])
    assert set(got.extras["session"]) == {"rec"}

    sidecar = json.loads((tmp_path / "table.csv.segments.json").read_text())
    assert [s["status"] for s in sidecar["segments"]] == ["ok"] * TARGETS
    assert sidecar["offset_s"] == result["offset_s"]


def test_joint_angles_are_the_inverse_kinematics_of_the_targets(recording, tmp_path) -> None:
    path = write_recording(recording, tmp_path / "rec.csv")
    result = ingest([path])
    q = np.stack([result.table.extras[f"q{i}"] for i in range(1, 7)], axis=1)
    from posecorr.kinematics import load_arm, reference_poses

    T = reference_poses(load_arm("ur5e"), q)
    np.testing.assert_allclose(T[:, :3, 3], recording.table.ref_p, atol=1e-6)


def test_ros2_bag_directory_reads_like_the_ros1_bag(recording, tmp_path) -> None:
    ros1 = ingest([write_recording(recording, tmp_path / "rec.bag")])
    ros2 = ingest([write_recording(recording, tmp_path / "rec2")])
    # its database is named after the folder, as a ROS 2 recorder names it (not after the
    # hidden name it was written under)
    assert sorted(p.name for p in (tmp_path / "rec2").iterdir()) == ["metadata.yaml", "rec2.db3"]
    np.testing.assert_allclose(ros2.table.meas_p, ros1.table.meas_p, atol=1e-12)
    np.testing.assert_allclose(ros2.table.ref_p, ros1.table.ref_p, atol=1e-12)
    assert ros2.alignment.offset == pytest.approx(ros1.alignment.offset, abs=1e-6)


def _tf_bag(path: Path, recording, frames=("tracker", "controller")) -> None:
    """A ROS 2 bag whose tracker pose comes on /tf among other frames, the joints on /joint_states."""
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    Time, Header = T["builtin_interfaces/msg/Time"], T["std_msgs/msg/Header"]

    def header(t: float, frame: str):
        ns = int(round(t * 1e9))
        return Header(stamp=Time(sec=ns // 10**9, nanosec=ns % 10**9), frame_id=frame)

    with Writer(path, version=9) as writer:
        joints = writer.add_connection("/joint_states", "sensor_msgs/msg/JointState", typestore=ts)
        tf = writer.add_connection("/tf", "tf2_msgs/msg/TFMessage", typestore=ts)
        items = [(t, "j", q) for t, q in zip(recording.joints.t, recording.joints.q)]
        items += [(t, "p", (p, q)) for t, p, q in zip(recording.tracker.t, recording.tracker.p, recording.tracker.q)]
        for t, kind, value in sorted(items, key=lambda item: item[0]):
            ns = int(round(t * 1e9))
            if kind == "j":
                msg = T["sensor_msgs/msg/JointState"](header=header(t, ""), name=list(recording.joints.names),
                                                      position=np.asarray(value), velocity=np.zeros(0),
                                                      effort=np.zeros(0))
                writer.write(joints, ns, ts.serialize_cdr(msg, "sensor_msgs/msg/JointState"))
                continue
            p, q = value
            transforms = []
            for frame in frames:
                transform = T["geometry_msgs/msg/Transform"](
                    translation=T["geometry_msgs/msg/Vector3"](x=p[0], y=p[1], z=p[2]),
                    rotation=T["geometry_msgs/msg/Quaternion"](w=q[0], x=q[1], y=q[2], z=q[3]))
                transforms.append(T["geometry_msgs/msg/TransformStamped"](header=header(t, "world"),
                                                                          child_frame_id=frame, transform=transform))
            writer.write(tf, ns, ts.serialize_cdr(T["tf2_msgs/msg/TFMessage"](transforms=transforms),
                                                  "tf2_msgs/msg/TFMessage"))


def test_tracker_on_tf_needs_its_frame_named(recording, tmp_path) -> None:
    short = simulate_recording(simulate(3, seed=0), n_targets=3, seed=0)
    _tf_bag(tmp_path / "tf", short)
    with pytest.raises(IngestError, match="several frames .*controller, tracker.*--tracker-frame"):
        ingest([tmp_path / "tf"])
    result = ingest([tmp_path / "tf"], IngestOptions(tracker_frame="tracker"))
    assert result.table.n == 3
    np.testing.assert_allclose(result.table.meas_p, short.table.meas_p, atol=1e-4)


def test_two_csv_files_with_own_column_names(recording, tmp_path) -> None:
    with open(tmp_path / "joints.csv", "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["stamp", *recording.joints.names])
        writer.writerows([[repr(float(t)), *(repr(float(v)) for v in q)]
                          for t, q in zip(recording.joints.t, recording.joints.q)])
    with open(tmp_path / "tracker.csv", "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["stamp", "px", "py", "pz", "ow", "ox", "oy", "oz"])
        writer.writerows([[repr(float(t)), *(repr(float(v)) for v in np.concatenate([p, q]))]
                          for t, p, q in zip(recording.tracker.t, recording.tracker.p, recording.tracker.q)])
    out = posecorr("ingest", str(tmp_path / "joints.csv"), str(tmp_path / "tracker.csv"), "-o",
                   str(tmp_path / "table.csv"), "--time-col", "stamp", "--joint-cols", ",".join(recording.joints.names),
                   "--pose-cols", "px,py,pz,ow,ox,oy,oz", "--session", "cell-7")
    assert out.returncode == 0, out.stderr
    table = read_table(tmp_path / "table.csv")
    assert table.n == TARGETS and set(table.extras["session"]) == {"cell-7"}
    assert np.all(np.linalg.norm(table.meas_p - recording.table.meas_p, axis=1) < 1e-4)


# --- still segments, gating, averaging ---------------------------------------------------------

def test_quaternion_mean_is_the_eigenvector_mean_not_the_component_mean() -> None:
    rng = np.random.default_rng(3)
    centre = Rotation.from_rotvec([0.4, -1.1, 2.0])
    rotations = centre * Rotation.from_rotvec(0.05 * rng.standard_normal((400, 3)))
    q = rotations.as_quat()[:, [3, 0, 1, 2]]
    q[::2] *= -1                                   # the same rotations, half with the other sign
    mean = quaternion_mean(q)
    expected = rotations.mean().as_quat()[[3, 0, 1, 2]]   # scipy: Markley's method, independently
    assert abs(abs(mean @ expected) - 1) < 1e-12
    component = q.mean(axis=0)
    assert np.linalg.norm(component) < 0.2       # the naive mean collapses on mixed signs


def test_still_segments_and_settle_window() -> None:
    t = np.arange(0, 20, 0.002)
    q = np.zeros((len(t), 6))
    moving = (t > 5) & (t < 7)                     # still 0-5 s, moving 5-7 s, still 7-20 s
    q[moving, 0] = 0.3 * (t[moving] - 5)
    q[t >= 7, 0] = 0.6
    segments = find_segments(t, q, StillOptions(settle=0.5, min_duration=2.0))
    assert [(round(s.start, 1), round(s.end, 1)) for s in segments] == [(0.0, 5.0), (7.0, 20.0)]
    assert segments[0].window == pytest.approx((0.5, segments[0].end - 0.5), abs=0.03)
    np.testing.assert_allclose(segments[1].q, [0.6, 0, 0, 0, 0, 0], atol=1e-12)
    # A stop shorter than --min-still is no segment.
    assert len(find_segments(t, q, StillOptions(min_duration=6.0))) == 1


def test_gate_drops_a_burst_and_keeps_the_quiet_samples() -> None:
    rng = np.random.default_rng(4)
    t = np.arange(0, 4, 0.004)
    p = 1.5e-4 * rng.standard_normal((len(t), 3))
    burst = (t > 2.0) & (t < 2.3)
    p[burst] += 3e-3 * rng.standard_normal((int(burst.sum()), 3))
    keep = gate(t, p, 1e-3)
    assert not keep[burst].any()
    assert keep[np.abs(t - 2.15) > 0.3].all()


def test_bad_segments_are_listed_with_their_reason(recording, tmp_path) -> None:
    tracker = recording.tracker
    t_robot = tracker.t - OFFSET - recording.joints.t[0]
    p = tracker.p.copy()
    in_stop = lambda k: (t_robot > recording.stands[k, 0]) & (t_robot < recording.stands[k, 1])  # noqa: E731
    keep = ~in_stop(1) | (t_robot > recording.stands[1, 1] - 0.8)         # only 0.3 s left after settling
    noisy = in_stop(3)
    p[noisy] += 4e-4 * np.random.default_rng(5).standard_normal((int(noisy.sum()), 3))
    damaged = PoseStream(tracker.t[keep], p[keep], tracker.q[keep])
    write_csv_log(tmp_path / "rec.csv", recording.joints, damaged)
    out = posecorr("ingest", str(tmp_path / "rec.csv"), "-o", str(tmp_path / "table.csv"))
    assert out.returncode == 0, out.stderr
    assert "rejected segment 1" in out.stdout and "too few samples" in out.stdout
    assert "rejected segment 3" in out.stdout and "too much jitter" in out.stdout
    sidecar = json.loads((tmp_path / "table.csv.segments.json").read_text())
    status = {s["segment"]: (s["status"], s["reason"] or "") for s in sidecar["segments"]}
    assert status[1][0] == status[3][0] == "rejected"
    assert status[1][1].startswith("too few samples") and status[3][1].startswith("too much jitter")
    assert [s["row"] for s in sidecar["segments"]] == [0, None, 1, None, 2]
    assert read_table(tmp_path / "table.csv").n == TARGETS - 2


# --- what cannot be ingested: one line, exit 2 ---------------------------------------------

@pytest.fixture(scope="module")
def bag(recording, tmp_path_factory) -> Path:
    return write_recording(recording, tmp_path_factory.mktemp("bag") / "rec.bag")


def test_truncated_bag(bag, tmp_path) -> None:
    cut = tmp_path / "cut.bag"
    cut.write_bytes(bag.read_bytes()[: bag.stat().st_size // 2])
    one_line_error(posecorr("ingest", str(cut), "-o", str(tmp_path / "t.csv")), "cut.bag")


def test_malformed_bag_and_mcap(tmp_path) -> None:
    for name in ("junk.bag", "junk.mcap"):
        (tmp_path / name).write_bytes(b"#ROSBAG V2.0\n" + bytes(range(256)) * 8)
        one_line_error(posecorr("ingest", str(tmp_path / name), "-o", str(tmp_path / "t.csv")), name)


def test_truncated_mcap(recording, tmp_path) -> None:
    path = write_recording(recording, tmp_path / "rec.mcap")
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[: path.stat().st_size * 2 // 3])
    one_line_error(posecorr("ingest", str(cut), "-o", str(tmp_path / "t.csv")), "cut.mcap")


def test_missing_topic(bag, tmp_path) -> None:
    line = one_line_error(posecorr("ingest", str(bag), "-o", str(tmp_path / "t.csv"), "--tracker", "/vive/nope"),
                          "no topic /vive/nope", "/vive/tracker/pose")
    assert "/ur/joint_states" in line


def test_streams_that_do_not_overlap(recording, tmp_path) -> None:
    late = PoseStream(recording.tracker.t + 1000.0, recording.tracker.p, recording.tracker.q)
    write_csv_log(tmp_path / "late.csv", recording.joints, late)
    one_line_error(posecorr("ingest", str(tmp_path / "late.csv"), "-o", str(tmp_path / "t.csv")),
                   "late.csv", "do not overlap")


def test_a_joint_stream_too_short_for_the_offset_is_refused_with_its_length(tmp_path) -> None:
    """One joint row and one tracker row (the documented columns): the offset search read the
    second point of a speed grid that had none (IndexError, exit 1). Refused in one line with
    the stream's length, what the estimate takes and --offset; given it, the log is read on."""
    path = tmp_path / "short.csv"
    path.write_text("t,q1,q2,q3,q4,q5,q6,x,y,z,qw,qx,qy,qz\n"
                    "0,0,-1.5708,1.5708,0,1.5708,0,,,,,,,\n"
                    "0.001,,,,,,,0.1,0.2,0.3,1,0,0,0\n")
    table = str(tmp_path / "t.csv")
    one_line_error(posecorr("ingest", str(path), "-o", table),
                   "short.csv: the joint stream is too short to find the clock offset: it spans 0 s (1 joint state), "
                   "and the estimate takes at least 0.1 s of motion; give --offset, the tracker clock "
                   "minus the robot's")
    one_line_error(posecorr("ingest", str(path), "-o", table, "--offset", "0.001"), "short.csv: no still segment")
    # a second of joints beside a tracker stream of one pose: it said the speeds "correlate at
    # most 0.00 ... wrong topics", after numpy's warnings
    path.write_text("t,q1,q2,q3,q4,q5,q6,x,y,z,qw,qx,qy,qz\n"
                    "0,0,-1.5708,1.5708,0,1.5708,0,,,,,,,\n"
                    "0.5,,,,,,,0.1,0.2,0.3,1,0,0,0\n"
                    "1,0.2,-1.5708,1.5708,0,1.5708,0,,,,,,,\n")
    one_line_error(posecorr("ingest", str(path), "-o", table),
                   "short.csv: the tracker stream is too short to find the clock offset: it spans 0 s (1 tracker pose)")


def test_bad_csv_cell_names_row_and_column(recording, tmp_path) -> None:
    path = write_recording(recording, tmp_path / "rec.csv")
    lines = path.read_text().splitlines()
    cells = lines[5].split(",")
    cells[2] = "abc"
    lines[5] = ",".join(cells)
    path.write_text("\n".join(lines) + "\n")
    one_line_error(posecorr("ingest", str(path), "-o", str(tmp_path / "t.csv")), "row 6", "column q2", "'abc'")
    # blank lines above it are rows of the file too (it said row 6 here, after skipping them)
    lines[2:2] = ["", "," * lines[0].count(",")]
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(IngestError, match=r"row 8, column q2: expected a number, got 'abc'"):
        read_csv_log([path])
    # two logs joined with cat: the second's header is named as such, not as a bad number
    clean = write_recording(recording, tmp_path / "clean.csv").read_text().splitlines()
    joined = tmp_path / "joined.csv"
    joined.write_text("\n".join(clean[:8] + clean[:1] + clean[9:]) + "\n")
    with pytest.raises(IngestError, match=r"row 9, column (\w+): expected a number, got '\1', its column's name: a "
                                          r"header row again \(tables joined\? keep the first header only\)$"):
        read_csv_log([joined])


def test_a_paired_table_given_to_ingest_is_sent_to_fit(recording, tmp_path) -> None:
    """A table `posecorr fit` reads, given to ingest, was refused for a recording's column it
    lacks (`no time column 't'`; with t, as simulate and ingest write it, `no joint samples`),
    which did not say that the file needs no ingest."""
    bare = tmp_path / "bare.csv"
    write_table(replace(recording.table, extras={}), bare)
    one_line_error(posecorr("ingest", str(bare), "-o", str(tmp_path / "t.csv")),
                   "bare.csv: row 1: columns meas_x..ref_z: this file is already a paired pose table, not a "
                   "recording; give it to `posecorr fit` directly")
    joints = {f"q{i}": np.zeros(recording.table.n) for i in range(1, 7)}
    ingested = tmp_path / "ingested.csv"
    write_table(replace(recording.table, extras={**recording.table.extras, **joints}), ingested)
    with pytest.raises(IngestError, match=r"ingested\.csv: row 1: columns meas_x\.\.ref_z: this file is already a "
                                          r"paired pose table"):
        read_csv_log([ingested])


def test_stream_columns_named_otherwise_are_listed_with_the_option_that_reads_them(recording, tmp_path) -> None:
    """A log whose joint columns are j1..j6 said `no joint samples (columns t, q1, ..., q6)`:
    the columns found are named, and --joint-cols, which reads them (the tracker's: --pose-cols)."""
    lines = write_recording(recording, tmp_path / "rec.csv").read_text().splitlines()
    renamed = tmp_path / "j.csv"
    assert lines[0] == "t,q1,q2,q3,q4,q5,q6,x,y,z,qw,qx,qy,qz"
    renamed.write_text("\n".join(["t,j1,j2,j3,j4,j5,j6,x,y,z,qw,qx,qy,qz"] + lines[1:]) + "\n")
    one_line_error(posecorr("ingest", str(renamed), "-o", str(tmp_path / "t.csv")),
                   "j.csv: no joint columns q1, q2, q3, q4, q5, q6 in the header (found t, j1, j2, j3, j4, j5, j6, "
                   "x, y, z, qw, qx, qy, qz); name the joint-angle columns with --joint-cols, comma-separated in "
                   "kinematic order")
    joints, _ = read_csv_log([renamed], CsvColumns(joints=tuple(f"j{i}" for i in range(1, 7))))
    np.testing.assert_array_equal(joints.q, recording.joints.q)
    with pytest.raises(IngestError, match=r"rec\.csv: no tracker columns px, py, pz, ow, ox, oy, oz in the header "
                                          r"\(found t, q1, .*, qz\); name the tracker's position and quaternion "
                                          r"columns with --pose-cols, comma-separated in the order x, y, z, qw, qx, "
                                          r"qy, qz$"):
        read_csv_log([tmp_path / "rec.csv"], CsvColumns(pose=("px", "py", "pz", "ow", "ox", "oy", "oz")))


def test_an_offset_that_is_given_is_used(recording, tmp_path) -> None:
    path = write_recording(recording, tmp_path / "rec.csv")
    given = ingest([path], IngestOptions(offset=OFFSET))
    estimated = ingest([path])
    assert given.alignment.source == "given" and given.alignment.offset == OFFSET
    np.testing.assert_allclose(given.table.meas_p, estimated.table.meas_p, atol=2e-5)
    # an offset given that parts the streams is named as given (the words were --max-offset 0's)
    with pytest.raises(IngestError, match=r"\(with --offset 10000 s; the offset is the tracker clock minus the "
                                          r"robot's\)$"):
        ingest([path], IngestOptions(offset=10000.0))


def test_joint_stream_without_the_robot_joints_is_refused(recording) -> None:
    joints = JointStream(recording.joints.t, recording.joints.q[:, :5], ("a", "b", "c", "d", "e"))
    from posecorr.ingest.pipeline import order_joints
    from posecorr.kinematics import load_arm

    with pytest.raises(IngestError, match="--joint-names"):
        order_joints(joints, load_arm("ur5e"), None)


# --- joint names, NaN, repeated stamps, units: a bag's streams as drivers publish them --------

@pytest.fixture(scope="module")
def short(experiment3):
    """A 3-stop recording (35 s) for the tests that write a bag of their own."""
    return simulate_recording(experiment3, n_targets=3, seed=0)


def _bag(path: Path, recording, joints: JointStream | None = None, tracker: PoseStream | None = None) -> Path:
    """A ROS 1 bag (the suffix's format) of the recording with its streams replaced."""
    from dataclasses import replace

    return write_recording(replace(recording, joints=joints or recording.joints, tracker=tracker or recording.tracker),
                           path)


def _assert_is_the_truth(result, recording) -> None:
    """The table of the recording's targets: references to the micrometre, measurements within the jitter."""
    assert result.table.n == recording.table.n
    np.testing.assert_allclose(result.table.ref_p, recording.table.ref_p, atol=1e-6)
    assert np.all(np.linalg.norm(result.table.meas_p - recording.table.meas_p, axis=1)
                  < result.table.extras["jitter_mm"] * 1e-3)


def test_joint_names_with_a_prefix_in_the_driver_order(short, tmp_path) -> None:
    """The UR driver with a tf_prefix publishes ur_elbow_joint first: matched by name after the
    prefix (it was read in message order: references 355 mm off, exit 0)."""
    from posecorr.kinematics import UR_JOINT_NAMES

    order = [2, 1, 0, 3, 4, 5]
    names = tuple("ur_" + UR_JOINT_NAMES[i] for i in order)
    path = _bag(tmp_path / "prefix.bag", short, JointStream(short.joints.t, short.joints.q[:, order], names))
    result = ingest([path])
    _assert_is_the_truth(result, short)
    assert result.notes == [f"{path}:/ur/joint_states: the joint names carry the prefix 'ur_' (a driver's "
                            f"tf_prefix): matched to the robot's {', '.join(UR_JOINT_NAMES)} after it"]
    from posecorr.jsonable import json_default

    assert json.loads(json.dumps(result.summary(), default=json_default))["notes"] == result.notes


def test_joint_names_that_do_not_match_are_refused_not_read_in_message_order(short) -> None:
    from posecorr.ingest.pipeline import order_joints
    from posecorr.kinematics import UR_JOINT_NAMES, load_arm

    arm = load_arm("ur5e")
    names = ("j1", "j2", "j3", "j4", "j5", "j6")
    joints = JointStream(short.joints.t, short.joints.q, names, source="rec.bag:/joint_states")
    with pytest.raises(IngestError) as error:
        order_joints(joints, arm, None)
    assert str(error.value) == (f"rec.bag:/joint_states: joints {', '.join(names)} do not match the robot's "
                                f"{', '.join(UR_JOINT_NAMES)}; name them in kinematic order with --joint-names")
    # two arms on one topic: the model's names after either prefix, so neither is taken
    both = JointStream(short.joints.t, np.hstack([short.joints.q, short.joints.q]),
                       tuple(p + n for p in ("left_", "right_") for n in UR_JOINT_NAMES), source="two:/j")
    with pytest.raises(IngestError, match=r"after each of the prefixes 'left_', 'right_'\); name them"):
        order_joints(both, arm, None)
    assert order_joints(both, arm, tuple("right_" + n for n in UR_JOINT_NAMES)) == (list(range(6, 12)), [])
    # messages that name no joints: their order, said in a note; a CSV log's columns: theirs, by its layout
    unnamed = JointStream(short.joints.t, short.joints.q, (), source="rec.bag:/joint_states")
    assert order_joints(unnamed, arm, None) == (list(range(6)), [
        f"rec.bag:/joint_states: the messages name no joints: read in their order as the robot's "
        f"{', '.join(UR_JOINT_NAMES)}"])
    assert order_joints(JointStream(short.joints.t, short.joints.q, names, positional=True), arm, None) == \
        (list(range(6)), [])


def test_mcap_with_the_ros1_profile(recording, tmp_path) -> None:
    from mcap.writer import Writer
    from rosbags.typesys import Stores, get_typestore

    from posecorr.ingest.rosformats import _McapSource, _open_source, ros_messages

    ts = get_typestore(Stores.ROS1_NOETIC)
    path = tmp_path / "ros1.mcap"
    with open(path, "wb") as handle:
        writer = Writer(handle)
        writer.start(profile="ros1", library="test")
        channels: dict[str, int] = {}
        for topic, msgtype, ns, msg in ros_messages(ts, recording.joints, recording.tracker, True, "lighthouse"):
            if topic not in channels:
                text, _ = ts.generate_msgdef(msgtype, ros_version=1)
                schema = writer.register_schema(msgtype.replace("/msg/", "/"), "ros1msg", text.encode())
                channels[topic] = writer.register_channel(topic, "ros1", schema)
            writer.add_message(channels[topic], ns, ts.serialize_ros1(msg, msgtype), ns)
        writer.finish()
    assert isinstance(_open_source(path), _McapSource)     # rosbags reads the ROS 2 profile only
    from_mcap = ingest([path])
    from_bag = ingest([write_recording(recording, tmp_path / "rec.bag")])
    np.testing.assert_allclose(from_mcap.table.meas_p, from_bag.table.meas_p, atol=1e-12)
    np.testing.assert_allclose(from_mcap.table.ref_p, from_bag.table.ref_p, atol=1e-12)


def test_a_csv_log_with_comment_lines_reads_as_without_them(recording, tmp_path, capsys) -> None:
    """A logger's preamble and a note among the samples are no samples; the rows named in
    messages stay the file's lines."""
    path = write_recording(recording, tmp_path / "rec.csv")
    plain = read_csv_log([path])
    lines = path.read_text().splitlines()
    path.write_text("\n".join(["# logger v2", "# 250 Hz"] + lines[:4] + ["# operator bumped the table"]
                              + lines[4:]) + "\n")
    commented = read_csv_log([path])
    np.testing.assert_array_equal(plain[0].t, commented[0].t)
    np.testing.assert_array_equal(plain[0].q, commented[0].q)
    np.testing.assert_array_equal(plain[1].p, commented[1].p)
    np.testing.assert_array_equal(plain[1].q, commented[1].q)
    assert "row 7 starts with '#': read as comments, not data" in capsys.readouterr().err
    cells = lines[5].split(",")
    cells[2] = "abc"
    path.write_text("\n".join(["# logger v2"] + lines[:5] + [",".join(cells)] + lines[6:]) + "\n")
    with pytest.raises(IngestError, match=r"row 7, column q2: expected a number, got 'abc'"):
        read_csv_log([path])


def test_nan_samples_of_a_bag_are_left_out_and_counted(short, tmp_path) -> None:
    """A tracker's NaN on losing track, in a stop and in a move, and a joint state's, are left
    out with a note per topic (they ended in 'speeds correlate at most 0.00'); a gripper's
    joint that never reads leaves the arm's alone."""
    from posecorr.kinematics import UR_JOINT_NAMES

    t_robot = short.tracker.t - OFFSET - short.joints.t[0]
    stop = short.stands[1, 0]                                  # the second stop begins
    move = 0.5 * (short.stands[0, 1] + short.stands[1, 0])     # the middle of the move to it
    lost = np.flatnonzero(((t_robot > stop + 1.0) & (t_robot < stop + 1.1))
                          | ((t_robot > move) & (t_robot < move + 0.1)))
    p, q = short.tracker.p.copy(), short.tracker.q.copy()
    p[lost], q[lost[::2]] = np.nan, np.nan
    angles = np.hstack([short.joints.q, np.full((len(short.joints.t), 1), np.nan)])
    angles[1000, 2] = np.nan
    path = _bag(tmp_path / "nan.bag", short, JointStream(short.joints.t, angles, UR_JOINT_NAMES + ("gripper",)),
                PoseStream(short.tracker.t, p, q))
    result = ingest([path])
    _assert_is_the_truth(result, short)
    n_joints, n_tracker = len(short.joints.t), len(short.tracker.t)
    assert len(lost) > 20 and len(result.tracker.t) == n_tracker - len(lost)
    assert result.notes == [f"{path}:/ur/joint_states: left out 1 of {n_joints} samples with NaN or infinite values",
                            f"{path}:/vive/tracker/pose: left out {len(lost)} of {n_tracker} samples with NaN or "
                            "infinite values"]


def test_repeated_stamps_of_a_bag_keep_the_first_sample(short, tmp_path) -> None:
    """A joint state published twice and tracker poses stamped like the one before are left out,
    counted per topic (joints gave divide-by-zero warnings and 'a rigid registration needs at
    least 3 points, got 0'; tracker poses were counted twice); both streams strictly increase."""
    twice = np.sort(np.concatenate([np.arange(len(short.joints.t)), np.arange(0, len(short.joints.t), 50)]))
    t = short.tracker.t.copy()
    t[1::7] = t[0:-1:7]                    # every 7th pose a new one, stamped as the one before
    path = _bag(tmp_path / "dup.bag", short, JointStream(short.joints.t[twice], short.joints.q[twice],
                                                         short.joints.names),
                PoseStream(t, short.tracker.p, short.tracker.q))
    result = ingest([path])
    _assert_is_the_truth(result, short)
    first = np.ones(len(t), dtype=bool)
    first[1::7] = False
    np.testing.assert_array_equal(result.tracker.p, short.tracker.p[first])
    np.testing.assert_array_equal(result.joints.q, short.joints.q)
    assert np.all(np.diff(result.joints.t) > 0) and np.all(np.diff(result.tracker.t) > 0)
    assert result.notes == [
        f"{path}:/ur/joint_states: left out {len(twice) - len(short.joints.t)} samples that repeat the stamp of "
        "the one before (the first of each stamp kept)",
        f"{path}:/vive/tracker/pose: left out {int(np.sum(~first))} samples that repeat the stamp of the one before "
        "(the first of each stamp kept)"]


def test_joints_in_degrees_and_tracker_in_millimetres_are_refused(short, tmp_path) -> None:
    """Degrees gave a wrong table, exit 0; millimetres 'a rigid registration needs at least 3 points'."""
    write_csv_log(tmp_path / "deg.csv", JointStream(short.joints.t, np.degrees(short.joints.q), short.joints.names),
                  short.tracker)
    column = int(np.argmax(np.abs(short.joints.q).max(axis=0)))
    largest = np.degrees(short.joints.q[np.argmax(np.abs(short.joints.q[:, column])), column])
    assert abs(largest) > 4 * np.pi
    line = one_line_error(posecorr("ingest", str(tmp_path / "deg.csv"), "-o", str(tmp_path / "t.csv")))
    assert line == (f"posecorr ingest: error: {tmp_path / 'deg.csv'}: joint q{column + 1} reads {largest:.6g}, "
                    "beyond ±4π = 12.57 (a revolute joint reads within ±2π rad): degrees? expected radians")

    mm = short.tracker.p * 1e3
    spread = np.max(np.median(np.abs(mm - np.median(mm, axis=0)), axis=0))
    path = _bag(tmp_path / "mm.bag", short, tracker=PoseStream(short.tracker.t, mm, short.tracker.q))
    with pytest.raises(IngestError) as error:
        ingest([path])
    assert str(error.value) == (f"{path}:/vive/tracker/pose: the tracker positions lie a typical {spread:.4g} m "
                                "from their median, and a tracked cell spans a few metres: millimetres? "
                                "expected metres")


def test_a_quaternion_that_is_not_unit_is_named_by_csv_row_and_by_bag_stamp(short, tmp_path) -> None:
    """It named the sample's index after sorting ('tracker sample 3001'), not where to find it."""
    path = write_recording(short, tmp_path / "rec.csv")
    lines = path.read_text().splitlines()
    row = next(i for i, line in enumerate(lines) if i > 3000 and not line.endswith(","))   # a tracker row
    cells = lines[row].split(",")
    cells[-4:] = ["0.5", "0.5", "0.5", "0.6"]
    lines[row] = ",".join(cells)
    path.write_text("\n".join(["# logger v2"] + lines) + "\n")
    with pytest.raises(IngestError) as error:
        ingest([path])
    assert str(error.value) == (f"{path}: row {row + 2}, column qw..qz: quaternion norm 1.05357 is off 1 by more "
                                "than 0.001 (expected a unit quaternion w, x, y, z)")

    q = short.tracker.q.copy()
    q[[700, 900]] *= 1.01
    path = _bag(tmp_path / "q.bag", short, tracker=PoseStream(short.tracker.t, short.tracker.p, q))
    ns = int(round(short.tracker.t[700] * 1e9))
    stamp = ns // 10**9 + ns % 10**9 * 1e-9           # as the header's sec and nanosec read
    with pytest.raises(IngestError) as error:
        ingest([path])
    assert str(error.value) == (f"{path}: topic /vive/tracker/pose, the pose stamped {stamp:.6f} s (the first of 2): "
                                "quaternion norm 1.01 is off 1 by "
                                "more than 0.001 (expected a unit quaternion w, x, y, z)")


BOOT = 1234.5 - 1_700_000_000.0      # s: a tracker stamped on its boot clock, the robot on Unix time


def _boot_clock_bag(path: Path, recording, latency: float = 0.003) -> Path:
    """A ROS 2 bag whose tracker headers are on the tracker's boot clock (BOOT + its clock) and
    whose receive times are the recorder's (the robot's clock, `latency` after the sample)."""
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    from posecorr.ingest.rosformats import ros_messages

    ts = get_typestore(Stores.ROS2_HUMBLE)
    boot = PoseStream(recording.tracker.t + BOOT, recording.tracker.p, recording.tracker.q)
    to_recorder = int(round((latency - BOOT - OFFSET) * 1e9))
    with Writer(path, version=9) as writer:
        connections: dict[str, object] = {}
        for topic, msgtype, ns, msg in ros_messages(ts, recording.joints, boot, False, "lighthouse"):
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msgtype, typestore=ts)
            received = ns + (to_recorder if msgtype == "geometry_msgs/msg/PoseStamped" else 0)
            writer.write(connections[topic], received, ts.serialize_cdr(msg, msgtype))
    return path


def test_a_tracker_on_its_boot_clock(short, tmp_path) -> None:
    """The refusal points to --stamps receive, which works; --offset takes the ~1.7e9 s it needs
    (it took +-86400 s only, and the message pointed to it)."""
    path = _boot_clock_bag(tmp_path / "boot", short)
    with pytest.raises(IngestError) as error:
        ingest([path])
    j, t = short.joints.t, short.tracker.t + BOOT
    assert str(error.value) == (
        f"{path}: the streams do not overlap: joint states {j[0]:.3f}..{j[-1]:.3f} s, "
        f"tracker {t[0]:.3f}..{t[-1]:.3f} s (more than --max-offset 5 s apart; a bag stamped on two clocks "
        "(a tracker's boot time) reads on the recorder's with --stamps receive, else give --offset, the tracker "
        "clock minus the robot's)")
    received = ingest([path], IngestOptions(stamps="receive"))
    _assert_is_the_truth(received, short)
    assert abs(received.alignment.offset - 0.003) < 2e-3          # the latency, on the recorder's clock
    out = posecorr("ingest", str(path), "-o", str(tmp_path / "table.csv"), "--offset", repr(OFFSET + BOOT), "--json")
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout)["offset_s"] == OFFSET + BOOT
    table = read_table(tmp_path / "table.csv")
    np.testing.assert_allclose(table.ref_p, short.table.ref_p, atol=1e-6)
    assert np.all(np.linalg.norm(table.meas_p - short.table.meas_p, axis=1) < table.extras["jitter_mm"] * 1e-3)


def test_a_csv_log_read_in_chunks_reads_as_one(recording, tmp_path, monkeypatch) -> None:
    """A log is parsed CHUNK_ROWS records at a time: the streams do not depend on where the
    chunks end, and a bad cell far into the file is still named by its row."""
    import posecorr.ingest.csvlog as csvlog

    path = write_recording(recording, tmp_path / "rec.csv")
    whole = read_csv_log([path])
    monkeypatch.setattr(csvlog, "CHUNK_ROWS", 997)      # a prime: chunks end mid-way in both streams
    chunked = read_csv_log([path])
    for a, b in zip(whole, chunked):
        for name in ("t", "q", "p") if isinstance(a, PoseStream) else ("t", "q"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    np.testing.assert_array_equal(chunked[0].t, recording.joints.t)
    lines = path.read_text().splitlines()
    row = 5 * 997 + 3                                   # in the sixth chunk
    cells = lines[row - 1].split(",")
    cells[0] = "1e400"
    lines[row - 1] = ",".join(cells)
    lines[1:1] = ["# a comment line"]                   # a row of the file, not a sample
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(IngestError, match=rf"row {row + 1}, column t: expected a finite number"):
        read_csv_log([path])


def test_an_offset_beyond_the_search_is_named_not_aliased(experiment3, tmp_path) -> None:
    """Clocks 6.5 s apart, searched within 5 s: one stop early matched fairly well (a table with
    every pose paired to the wrong stop, correlation ~0.8); ingest names the offset that matches
    best beyond the range instead, and finds it when the range is raised as it says."""
    true = 6.5
    recording = simulate_recording(experiment3, n_targets=TARGETS, seed=0,
                                   options=RecordingOptions(clock_offset=true))
    path = tmp_path / "late.csv"
    write_csv_log(path, recording.joints, recording.tracker)
    with pytest.raises(IngestError, match=r"match best at a clock offset of \+6\.50 s \(correlation 0\.9\d\), beyond "
                                          r"--max-offset 5 s \(at most 0\.[5-8]\d within it\); raise --max-offset to 8"):
        ingest([path])
    found = ingest([path], IngestOptions(max_offset=8.0))
    assert found.alignment.offset == pytest.approx(true, abs=1e-3)
    assert found.table.n == TARGETS


# --- a CSV log in another time unit or layout, and what it leaves out ---------------------------

def _csv_rows(path: Path, column: str) -> list[int]:
    """The file rows (header row 1) whose `column` cell is filled."""
    with open(path, newline="") as handle:
        rows = list(csv.reader(handle))
    index = rows[0].index(column)
    return [number for number, cells in enumerate(rows[1:], start=2) if cells[index]]


def test_times_in_nanoseconds_are_refused_with_their_span(short, tmp_path) -> None:
    """Integer nanoseconds (a ROS stamp written out): the offset search asked numpy for a grid of
    92 TiB ('internal error: MemoryError'). Refused on reading, naming the rows and the span."""
    path = tmp_path / "ns.csv"
    write_csv_log(path, JointStream(short.joints.t * 1e9, short.joints.q, short.joints.names),
                  PoseStream(short.tracker.t * 1e9, short.tracker.p, short.tracker.q))
    rows = _csv_rows(path, "q1")
    span = float(np.ptp(short.joints.t * 1e9))
    line = one_line_error(posecorr("ingest", str(path), "-o", str(tmp_path / "t.csv")))
    assert line == (f"posecorr ingest: error: {path}: rows {rows[0]}..{rows[-1]}, column t: the joint stream spans "
                    f"{span:.6g} s ({span / 86_400:.3g} days), and a session lasts minutes to hours: nanoseconds "
                    "or milliseconds? posecorr reads seconds; convert the column to seconds")


def test_an_offset_grid_beyond_a_session_is_refused_not_allocated() -> None:
    """Joint stamps a stray one 30 000 years off the others (a bag's, which no column check
    sees): the grid of the offset search is refused with its size, not allocated."""
    from posecorr.ingest.align import estimate_offset

    t_robot = np.array([0.0, 1.0, 1e12])
    t_tracker = np.linspace(0.0, 1.0, 11)
    with pytest.raises(IngestError) as error:
        estimate_offset(t_robot, np.tile(np.eye(4), (3, 1, 1)), t_tracker, np.zeros((11, 3)), 5.0, "rec.bag")
    assert str(error.value) == ("rec.bag: the joint states span 1e+12 s (1.16e+07 days), 1e+14 steps of the 100 Hz "
                                "grid the clock offset is estimated on, more than a 2-day session's 1.73e+07; check "
                                "the stamps (one far off the others?), or give --offset")


def test_times_in_milliseconds_are_named_before_what_they_cause(short, tmp_path) -> None:
    """Milliseconds since the start span under two days: the log read as a robot that never
    moves ('give --offset'), with no word of the unit. A warning says so before the refusal."""
    path = tmp_path / "ms.csv"
    t0 = short.joints.t[0]
    write_csv_log(path, JointStream((short.joints.t - t0) * 1e3, short.joints.q, short.joints.names),
                  PoseStream((short.tracker.t - t0) * 1e3, short.tracker.p, short.tracker.q))
    joint, tracker = (float(np.median(np.diff(t))) * 1e3 for t in (short.joints.t, short.tracker.t))
    out = posecorr("ingest", str(path), "-o", str(tmp_path / "t.csv"))
    assert out.returncode == 2, out.stderr
    assert out.stderr.splitlines() == [
        f"posecorr: warning: {path}: column t: the joint samples are a median {joint:.3g} s apart ({1 / joint:.3g} Hz), "
        f"the tracker samples {tracker:.3g} s ({1 / tracker:.3g} Hz), where a robot cell records tens to thousands "
        "of samples a second: milliseconds? posecorr reads seconds",
        f"posecorr ingest: error: {path}: the robot does not move, so the clocks cannot be aligned on its motion; "
        "give --offset"]


def test_a_semicolon_separated_log_is_named_so(tmp_path) -> None:
    """It said only 'no time column' beside a header that plainly starts with t."""
    path = tmp_path / "semicolon.csv"
    path.write_text("t;q1;q2;q3;q4;q5;q6;x;y;z;qw;qx;qy;qz\n0;0;-1.5708;1.5708;0;1.5708;0;;;;;;;\n")
    with pytest.raises(IngestError) as error:
        read_csv_log([path])
    assert str(error.value) == (f"{path}: row 1: no time column 't' (header: t;q1;q2;q3;q4;q5;q6;x;y;z;qw;qx;qy;qz); "
                                "the header is one column holding ';': posecorr reads commas")


def test_tracker_quaternions_written_x_y_z_w_are_named(recording, tmp_path) -> None:
    """x, y, z, w under qw, qx, qy, qz (scipy's order) went into the table without a word; the
    forward kinematics' orientations say it, with the columns read and the option that maps
    them, and --pose-cols' help gives the order."""
    from posecorr.registration import quaternion_order_note

    path = tmp_path / "xyzw.csv"
    write_csv_log(path, recording.joints, PoseStream(recording.tracker.t, recording.tracker.p,
                                                     np.roll(recording.tracker.q, -1, axis=1)))
    result = ingest([path])
    ok = [s for s in result.segments if s.status == "ok"]
    note = quaternion_order_note(np.stack([s.quat for s in ok]), result.table.ref_q, np.stack([s.p for s in ok]),
                                 result.table.ref_p)
    assert note is not None and note.startswith("the quaternions look written in another order than their names")
    assert result.notes == [f"{path}, tracker quaternions against the forward kinematics: {note}; ingest read the "
                            "columns qw, qx, qy, qz as w, x, y, z (--pose-cols)"]
    assert ingest([write_recording(recording, tmp_path / "rec.csv")]).notes == []
    help_text = " ".join(posecorr("ingest", "--help").stdout.split())
    assert ("--pose-cols POSE_COLS CSV: tracker pose columns, the position x, y, z (m), then the unit quaternion in "
            "the order w, x, y, z (scalar first: for a log written x, y, z, w, name its w column first)") in help_text


def test_csv_rows_with_a_time_and_no_values_are_counted(short, tmp_path) -> None:
    """A logger's rows with the time alone were left out without a word (a bag's samples it
    cannot use are counted); a note names how many, and the first rows."""
    path = write_recording(short, tmp_path / "rec.csv")
    lines = path.read_text().splitlines()
    width = len(lines[0].split(","))
    tracker_rows = [i for i, line in enumerate(lines) if i and not line.endswith(",")]
    for bare in (tracker_rows[3000:3014:2], tracker_rows[3000:3001]):
        cut = list(lines)
        for i in bare:
            cut[i] = cut[i].split(",")[0] + "," * (width - 1)
        path.write_text("\n".join(cut) + "\n")
        result = ingest([path])
        assert len(result.tracker.t) == len(short.tracker.t) - len(bare)
        rows = [str(i + 1) for i in bare]
        assert result.notes == ([f"{path}: rows {', '.join(rows[:5])} and 2 more have a time but no joint or "
                                 "tracker values: 7 rows left out"] if len(bare) > 1 else
                                [f"{path}: row {rows[0]} has a time but no joint or tracker values: 1 row left out"])


def test_a_repeated_stamp_is_counted_in_the_singular() -> None:
    """'left out 1 samples that repeat the stamp'."""
    from posecorr.ingest.streams import keep_usable

    stream = PoseStream(np.array([0.0, 0.1, 0.1, 0.2]), np.zeros((4, 3)), np.tile([1.0, 0, 0, 0], (4, 1)),
                        source="rec.bag:/pose")
    assert keep_usable(stream, np.hstack([stream.p, stream.q])).notes == [
        "rec.bag:/pose: left out 1 sample that repeats the stamp of the one before (the first of each stamp kept)"]

"""ROS 1 bags, ROS 2 bags and MCAP files, read and written in pure Python (no ROS install).

Bags go through `rosbags` (ROS 1 `.bag`, ROS 2 bag directories and their `.db3` / `.mcap`
storage files); stand-alone `.mcap` files through the `mcap` package, whose reader accepts
both the ROS 1 and the ROS 2 profile, with `rosbags` decoding the messages from the schemas the
file carries. Message types are the ROS 2 names (`sensor_msgs/msg/JointState`).

Tracker poses are accepted from the message types in POSE_TYPES; a TF topic carries many
frames, so its transforms are filtered by their child frame.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np

from ..data import quaternion_faults
from .fastdecode import decoder
from .progress import progress_bar
from .streams import IngestError, JointStream, PoseStream

JOINT_TYPE = "sensor_msgs/msg/JointState"
TF_TYPE = "tf2_msgs/msg/TFMessage"


def _pose_of(pose: Any) -> tuple[Any, Any]:
    return (pose.position.x, pose.position.y, pose.position.z), pose.orientation


def _transform_of(transform: Any) -> tuple[Any, Any]:
    return (transform.translation.x, transform.translation.y, transform.translation.z), transform.rotation


# message type -> (header, position, quaternion) of one message
POSE_TYPES: dict[str, Callable[[Any], tuple[Any, Any, Any]]] = {
    "geometry_msgs/msg/PoseStamped": lambda m: (m.header, *_pose_of(m.pose)),
    "geometry_msgs/msg/PoseWithCovarianceStamped": lambda m: (m.header, *_pose_of(m.pose.pose)),
    "nav_msgs/msg/Odometry": lambda m: (m.header, *_pose_of(m.pose.pose)),
    "geometry_msgs/msg/TransformStamped": lambda m: (m.header, *_transform_of(m.transform)),
}

DEFAULT_JOINT_TOPICS = ("/joint_states", "/ur/joint_states")


@dataclass
class Topics:
    """The topics of a recording: {topic: message type}."""

    types: dict[str, str]

    def describe(self) -> str:
        return ", ".join(f"{t} ({m})" for t, m in sorted(self.types.items())) or "none"


# --- reading ---------------------------------------------------------------------------

class _BagSource:
    """Messages of a ROS 1 bag or ROS 2 bag through rosbags' AnyReader."""

    def __init__(self, path: Path) -> None:
        from rosbags.highlevel import AnyReader

        self.path = path
        self.reader = AnyReader([path])

    def __enter__(self) -> "_BagSource":
        self.reader.open()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.reader.close()

    def topics(self) -> Topics:
        return Topics({c.topic: c.msgtype for c in self.reader.connections})

    def count(self, topics: list[str]) -> int:
        return sum(c.msgcount for c in self.reader.connections if c.topic in topics)

    def messages(self, topics: list[str]) -> Iterator[tuple[str, int, bytes]]:
        connections = [c for c in self.reader.connections if c.topic in topics]
        for connection, stamp, raw in self.reader.messages(connections=connections):
            yield connection.topic, stamp, raw

    @property
    def encoding(self) -> str:
        return "cdr" if self.reader.is2 else "ros1"

    def deserialize(self, raw: bytes, msgtype: str, encoding: str) -> Any:
        return self.reader.deserialize(raw, msgtype)


class _McapSource:
    """Messages of a stand-alone MCAP file (ROS 1 or ROS 2 profile) through the mcap reader."""

    def __init__(self, path: Path) -> None:
        from rosbags.typesys import Stores, get_typestore

        self.path = path
        self.handle = open(path, "rb")
        self.typestore = get_typestore(Stores.EMPTY)

    def __enter__(self) -> "_McapSource":
        from mcap.reader import make_reader

        self.reader = make_reader(self.handle)
        summary = self.reader.get_summary()
        if summary is None:
            raise IngestError(f"{self.path}: MCAP file without a summary section (truncated?)")
        self.schemas, self.channels = summary.schemas, summary.channels
        self.counts = summary.statistics.channel_message_counts if summary.statistics else {}
        self._register_types()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.handle.close()

    def _register_types(self) -> None:
        from rosbags.typesys import get_types_from_idl, get_types_from_msg

        types: dict[str, Any] = {}
        for schema in self.schemas.values():
            text = schema.data.decode("utf-8")
            if schema.encoding in ("ros1msg", "ros2msg"):
                types.update(get_types_from_msg(text, _ros2_name(schema.name)))
            elif schema.encoding == "ros2idl":
                for part in text.split("=" * 80 + "\n"):
                    if part.strip():
                        types.update(get_types_from_idl(part.split("\n", 1)[1] if part.startswith("IDL: ") else part))
        self.typestore.register(types)

    def topics(self) -> Topics:
        return Topics({c.topic: _ros2_name(self.schemas[c.schema_id].name) for c in self.channels.values()
                       if c.schema_id in self.schemas})

    @property
    def encoding(self) -> str:
        encodings = {c.message_encoding for c in self.channels.values()}
        if len(encodings) != 1 or not encodings <= {"cdr", "ros1"}:
            raise IngestError(f"{self.path}: message encodings {', '.join(sorted(encodings))}, expected cdr or ros1")
        return encodings.pop()

    def count(self, topics: list[str]) -> int:
        return sum(self.counts.get(i, 0) for i, c in self.channels.items() if c.topic in topics)

    def messages(self, topics: list[str]) -> Iterator[tuple[str, int, bytes]]:
        for _, channel, message in self.reader.iter_messages(topics=topics):
            yield channel.topic, message.log_time, message.data

    def deserialize(self, raw: bytes, msgtype: str, encoding: str) -> Any:
        decode = self.typestore.deserialize_cdr if encoding == "cdr" else self.typestore.deserialize_ros1
        return decode(raw, msgtype)


def _ros2_name(name: str) -> str:
    """'sensor_msgs/JointState' (ROS 1) -> 'sensor_msgs/msg/JointState'."""
    parts = name.split("/")
    return f"{parts[0]}/msg/{parts[1]}" if len(parts) == 2 else name


def _open_source(path: Path) -> _BagSource | _McapSource:
    """rosbags for bags and ROS 2 MCAP (the faster reader), the mcap package for other MCAP profiles."""
    if path.suffix == ".mcap" and path.is_file():
        source = _BagSource(path)
        try:
            source.reader.open()
            source.reader.close()
        except Exception:  # noqa: BLE001 - not a ROS 2 MCAP: the mcap reader says what it is
            return _McapSource(path)
        return source
    return _BagSource(path)


def read_ros(path: str | Path, joint_topic: str | None = None, tracker_topic: str | None = None,
             tracker_frame: str | None = None, stamps: str = "header") -> tuple[JointStream, PoseStream]:
    """The joint and tracker streams of a bag or MCAP file; IngestError naming the file otherwise."""
    path = Path(path)
    if not path.exists():
        raise IngestError(f"{path}: no such file or directory")
    try:
        with _open_source(path) as source:
            topics = source.topics()
            joint_topic = _pick_joint_topic(path, topics, joint_topic)
            tracker_topic = _pick_tracker_topic(path, topics, tracker_topic)
            joints, tracker = _collect(path, source, topics, joint_topic, tracker_topic, tracker_frame, stamps)
        _check_tracker_quaternions(path, tracker_topic, tracker)
        return joints, tracker
    except IngestError:
        raise
    except Exception as exc:  # noqa: BLE001 - any failure inside a foreign file is the file's fault
        raise IngestError(f"{path}: not a readable recording ({type(exc).__name__}: "
                          f"{str(exc).splitlines()[0] if str(exc) else 'no detail'})") from None


def _check_tracker_quaternions(path: Path, topic: str, tracker: PoseStream) -> None:
    """IngestError naming the stamp of the first pose that is no unit quaternion (a message has
    no row; its stamp is what a bag viewer shows)."""
    bad, what = quaternion_faults(tracker.q)
    if bad.size:
        many = f" (the first of {bad.size})" if bad.size > 1 else ""
        raise IngestError(f"{path}: topic {topic}, the pose stamped {tracker.t[bad[0]]:.6f} s{many}: {what} "
                          "(expected a unit quaternion w, x, y, z)")


def _pick_joint_topic(path: Path, topics: Topics, wanted: str | None) -> str:
    if wanted is not None:
        if wanted not in topics.types:
            raise IngestError(f"{path}: no topic {wanted} (topics: {topics.describe()})")
        if topics.types[wanted] != JOINT_TYPE:
            raise IngestError(f"{path}: topic {wanted} is {topics.types[wanted]}, expected {JOINT_TYPE}")
        return wanted
    found = [t for t, m in topics.types.items() if m == JOINT_TYPE]
    if len(found) == 1:
        return found[0]
    preferred = [t for t in DEFAULT_JOINT_TOPICS if t in found]
    if preferred:
        return preferred[0]
    if not found:
        raise IngestError(f"{path}: no {JOINT_TYPE} topic (topics: {topics.describe()})")
    raise IngestError(f"{path}: several {JOINT_TYPE} topics ({', '.join(sorted(found))}); choose one with --joints")


def _pick_tracker_topic(path: Path, topics: Topics, wanted: str | None) -> str:
    accepted = set(POSE_TYPES) | {TF_TYPE}
    if wanted is not None:
        if wanted not in topics.types:
            raise IngestError(f"{path}: no topic {wanted} (topics: {topics.describe()})")
        if topics.types[wanted] not in accepted:
            raise IngestError(f"{path}: topic {wanted} is {topics.types[wanted]}, expected one of "
                              + ", ".join(sorted(accepted)))
        return wanted
    found = [t for t, m in topics.types.items() if m in POSE_TYPES]
    if len(found) == 1:
        return found[0]
    if not found:
        tf = [t for t, m in topics.types.items() if m == TF_TYPE and t != "/tf_static"]
        if len(tf) == 1:
            return tf[0]
        raise IngestError(f"{path}: no tracker pose topic (PoseStamped, PoseWithCovarianceStamped, Odometry, "
                          f"TransformStamped or TF; topics: {topics.describe()})")
    raise IngestError(f"{path}: several pose topics ({', '.join(sorted(found))}); choose one with --tracker")


def _generic_pose(extract: Callable[[Any], tuple[Any, Any, Any]], deserialize: Callable[[bytes], Any],
                  tracker_frame: str | None, child_frames: dict[str, int]) -> Callable[[bytes], list]:
    """A decoder of one pose message (or TF message) into [(header, (x, y, z), quaternion)]."""
    def decode(raw: bytes) -> list:
        msg = deserialize(raw)
        if extract is not None:
            return [extract(msg)]
        out = []
        for tf in msg.transforms:
            child_frames[tf.child_frame_id] = child_frames.get(tf.child_frame_id, 0) + 1
            if tracker_frame is None or tf.child_frame_id == tracker_frame:
                out.append((tf.header, *_transform_of(tf.transform)))
        return out
    return decode


def _reading(source: Any, topics: list[str], path: Path) -> Iterator[tuple[str, int, bytes]]:
    """The topics' messages, counted on a progress bar."""
    with progress_bar(source.count(topics), "msg", path) as done:
        for index, message in enumerate(source.messages(topics)):
            if index % 8192 == 0:
                done(index)
            yield message


def _collect(path: Path, source: Any, topics: Topics, joint_topic: str, tracker_topic: str,
             tracker_frame: str | None, stamps: str) -> tuple[JointStream, PoseStream]:
    encoding = source.encoding
    tracker_type = topics.types[tracker_topic]
    child_frames: dict[str, int] = {}
    generic_pose = _generic_pose(POSE_TYPES.get(tracker_type), lambda raw: source.deserialize(raw, tracker_type, encoding),
                                 tracker_frame, child_frames)
    fast_joints = fast_pose = None
    jt: list[float] = []
    jlog: list[int] = []
    jq: list[tuple[float, ...]] = []
    names: tuple[str, ...] | None = None
    pt: list[float] = []
    plog: list[int] = []
    pose: list[tuple[float, ...]] = []
    for topic, log_ns, raw in _reading(source, [joint_topic, tracker_topic], path):
        if topic == joint_topic:
            if fast_joints is None:
                fast_joints = decoder(JOINT_TYPE, encoding, raw) or _generic_joints(source, encoding)
            stamp, msg_names, position = fast_joints(raw)
            if names is None:
                names = msg_names
            elif msg_names != names and msg_names:
                raise IngestError(f"{path}: topic {joint_topic} changes its joint names at message {len(jt) + 1} "
                                  f"({', '.join(msg_names)} after {', '.join(names) or 'none'})")
            # Messages that name no joints (allowed by JointState) are read in their order
            # (pipeline.order_joints), so each must carry as many as the first.
            expected = len(names) if names else len(jq[0]) if jq else len(position)
            if len(position) != expected:
                raise IngestError(f"{path}: topic {joint_topic} message {len(jt) + 1} has {len(position)} positions "
                                  + (f"for {expected} joint names" if names else
                                     f"and no joint names, the first message {expected}"))
            jt.append(stamp)
            jlog.append(log_ns)
            jq.append(position)
            continue
        if fast_pose is None:
            fast_pose = decoder(tracker_type, encoding, raw) or False
        if fast_pose:
            stamp, _, values = fast_pose(raw)
            pt.append(stamp)
            plog.append(log_ns)
            pose.append(values)
            continue
        for header, position, o in generic_pose(raw):
            pt.append(header.stamp.sec + header.stamp.nanosec * 1e-9)
            plog.append(log_ns)
            pose.append((*position, o.w, o.x, o.y, o.z))
    if tracker_type == TF_TYPE:
        _check_tf_frame(path, tracker_topic, tracker_frame, child_frames)
    if not jt:
        raise IngestError(f"{path}: topic {joint_topic} has no messages")
    if not pt:
        raise IngestError(f"{path}: topic {tracker_topic} has no tracker poses")
    poses = np.asarray(pose, dtype=float)
    return (JointStream(_times(jt, jlog, stamps), np.asarray(jq, dtype=float), names or (),
                        source=f"{path}:{joint_topic}"),
            PoseStream(_times(pt, plog, stamps), poses[:, :3], poses[:, 3:7], source=f"{path}:{tracker_topic}"))


def _check_tf_frame(path: Path, topic: str, frame: str | None, child_frames: dict[str, int]) -> None:
    """IngestError unless the TF topic's tracker frame is the one named, or the only one."""
    if frame is None and len(child_frames) > 1:
        raise IngestError(f"{path}: TF topic {topic} carries several frames "
                          f"({', '.join(sorted(child_frames))}); choose the tracker's with --tracker-frame")
    if frame is not None and frame not in child_frames:
        raise IngestError(f"{path}: TF topic {topic} has no frame {frame} "
                          f"(frames: {', '.join(sorted(child_frames)) or 'none'})")


def _times(header_s: list[float], log_ns: list[int], stamps: str) -> np.ndarray:
    """Header stamps, or the recorder's receive times when asked or where a header stamp is unset."""
    header = np.asarray(header_s, dtype=float)
    received = np.asarray(log_ns, dtype=np.int64) * 1e-9
    return received if stamps == "receive" else np.where(header > 0, header, received)


def _generic_joints(source: Any, encoding: str) -> Callable[[bytes], tuple]:
    def decode(raw: bytes) -> tuple:
        msg = source.deserialize(raw, JOINT_TYPE, encoding)
        return (msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9, tuple(msg.name), tuple(msg.position))
    return decode


# --- writing (simulated recordings) ------------------------------------------------------

def ros_messages(typestore: Any, joints: JointStream, tracker: PoseStream, ros1: bool,
              frame: str) -> Iterator[tuple[str, str, int, Any]]:
    """(topic, type, stamp ns, message) of both streams, merged by time."""
    T = typestore.types
    Time = T["builtin_interfaces/msg/Time"]

    def header(t: float, frame_id: str) -> Any:
        ns = int(round(t * 1e9))
        stamp = Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
        return T["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id=frame_id) if ros1 else \
            T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id)

    names = list(joints.names)
    zeros = np.zeros(len(names))
    items = []
    for t, q in zip(joints.t, joints.q):
        items.append((t, JOINT_TOPIC, JOINT_TYPE, T[JOINT_TYPE](header=header(t, ""), name=names,
                                                               position=np.array(q), velocity=zeros, effort=zeros)))
    Pose, Point, Quat = (T["geometry_msgs/msg/Pose"], T["geometry_msgs/msg/Point"],
                         T["geometry_msgs/msg/Quaternion"])
    PoseStamped = T["geometry_msgs/msg/PoseStamped"]
    for t, p, q in zip(tracker.t, tracker.p, tracker.q):
        pose = Pose(position=Point(x=p[0], y=p[1], z=p[2]), orientation=Quat(w=q[0], x=q[1], y=q[2], z=q[3]))
        items.append((t, TRACKER_TOPIC, "geometry_msgs/msg/PoseStamped", PoseStamped(header=header(t, frame), pose=pose)))
    items.sort(key=lambda item: item[0])
    for t, topic, msgtype, msg in items:
        yield topic, msgtype, int(round(t * 1e9)), msg


JOINT_TOPIC = "/ur/joint_states"        # the paper's cell (section 2.2, figure 7)
TRACKER_TOPIC = "/vive/tracker/pose"


def write_ros1_bag(path: Path, joints: JointStream, tracker: PoseStream, frame: str) -> None:
    from rosbags.rosbag1 import Writer

    with Writer(path) as writer:
        _write_bag(writer, 1, joints, tracker, frame)


def write_ros2_bag(path: Path, joints: JointStream, tracker: PoseStream, frame: str) -> None:
    from rosbags.rosbag2 import Writer

    with Writer(path, version=9) as writer:
        _write_bag(writer, 2, joints, tracker, frame)


def _write_bag(writer: Any, ros_version: int, joints: JointStream, tracker: PoseStream, frame: str) -> None:
    """The messages into an open rosbags writer, one connection per topic."""
    from rosbags.typesys import Stores, get_typestore

    typestore = get_typestore(Stores.ROS1_NOETIC if ros_version == 1 else Stores.ROS2_HUMBLE)
    serialize = typestore.serialize_ros1 if ros_version == 1 else typestore.serialize_cdr
    connections: dict[str, Any] = {}
    for topic, msgtype, ns, msg in ros_messages(typestore, joints, tracker, ros_version == 1, frame):
        if topic not in connections:
            connections[topic] = writer.add_connection(topic, msgtype, typestore=typestore)
        writer.write(connections[topic], ns, serialize(msg, msgtype))


def write_mcap(path: Path, joints: JointStream, tracker: PoseStream, frame: str) -> None:
    from mcap.writer import Writer
    from rosbags.typesys import Stores, get_typestore

    typestore = get_typestore(Stores.ROS2_HUMBLE)
    with open(path, "wb") as handle:
        writer = Writer(handle)
        writer.start(profile="ros2", library="posecorr")
        channels: dict[str, int] = {}
        for topic, msgtype, ns, msg in ros_messages(typestore, joints, tracker, False, frame):
            if topic not in channels:
                text, _ = typestore.generate_msgdef(msgtype, ros_version=2)
                schema = writer.register_schema(msgtype, "ros2msg", text.encode("utf-8"))
                channels[topic] = writer.register_channel(topic, "cdr", schema)
            writer.add_message(channels[topic], ns, typestore.serialize_cdr(msg, msgtype), ns)
        writer.finish()

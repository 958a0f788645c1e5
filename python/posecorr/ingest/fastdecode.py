"""Direct decoders for the two messages a recording holds by the hundred thousand.

sensor_msgs/JointState and geometry_msgs/PoseStamped are read field by field with `struct`
from their ROS 1 or little-endian CDR bytes, some thirty times faster than building message
objects; any other type (or a big-endian CDR message) goes through rosbags' deserializer.
Each decoder returns (stamp_s, names, values): stamp_s 0 when the header is unset, names the
joint names (JointState) or None, values the positions, or x, y, z, qw, qx, qy, qz.
"""
from __future__ import annotations

import struct
from typing import Callable

_U32 = struct.Struct("<I").unpack_from
_STAMP1 = struct.Struct("<II").unpack_from   # ROS 1 time: sec, nsec (after the uint32 seq)
_STAMP2 = struct.Struct("<iI").unpack_from   # CDR builtin_interfaces/Time: int32 sec, uint32 nanosec
_POSE = struct.Struct("<7d").unpack_from


def _align(offset: int, size: int) -> int:
    # CDR aligns primitives to their size, counted from the end of the 4-byte encapsulation header.
    return offset + (-(offset - 4)) % size


def _ros1_header(raw: bytes) -> tuple[float, int]:
    sec, nsec = _STAMP1(raw, 4)
    return sec + nsec * 1e-9, 16 + _U32(raw, 12)[0]


def _cdr_header(raw: bytes) -> tuple[float, int]:
    sec, nsec = _STAMP2(raw, 4)
    return sec + nsec * 1e-9, 16 + _U32(raw, 12)[0]


def _pose_ros1(raw: bytes) -> tuple[float, None, tuple[float, ...]]:
    stamp, offset = _ros1_header(raw)
    x, y, z, qx, qy, qz, qw = _POSE(raw, offset)
    return stamp, None, (x, y, z, qw, qx, qy, qz)


def _pose_cdr(raw: bytes) -> tuple[float, None, tuple[float, ...]]:
    stamp, offset = _cdr_header(raw)
    x, y, z, qx, qy, qz, qw = _POSE(raw, _align(offset, 8))
    return stamp, None, (x, y, z, qw, qx, qy, qz)


def _joints_ros1(raw: bytes) -> tuple[float, tuple[str, ...], tuple[float, ...]]:
    stamp, offset = _ros1_header(raw)
    count = _U32(raw, offset)[0]
    offset += 4
    names = []
    for _ in range(count):
        n = _U32(raw, offset)[0]
        names.append(raw[offset + 4:offset + 4 + n].decode())
        offset += 4 + n
    n = _U32(raw, offset)[0]
    return stamp, tuple(names), struct.unpack_from(f"<{n}d", raw, offset + 4)


def _joints_cdr(raw: bytes) -> tuple[float, tuple[str, ...], tuple[float, ...]]:
    stamp, offset = _cdr_header(raw)
    offset = _align(offset, 4)
    count = _U32(raw, offset)[0]
    offset += 4
    names = []
    for _ in range(count):
        offset = _align(offset, 4)
        n = _U32(raw, offset)[0]                 # includes the terminating NUL
        names.append(raw[offset + 4:offset + 3 + n].decode())
        offset += 4 + n
    offset = _align(offset, 4)
    n = _U32(raw, offset)[0]
    return stamp, tuple(names), struct.unpack_from(f"<{n}d", raw, _align(offset + 4, 8))


Decoder = Callable[[bytes], tuple]
DECODERS: dict[tuple[str, str], Decoder] = {
    ("sensor_msgs/msg/JointState", "ros1"): _joints_ros1,
    ("sensor_msgs/msg/JointState", "cdr"): _joints_cdr,
    ("geometry_msgs/msg/PoseStamped", "ros1"): _pose_ros1,
    ("geometry_msgs/msg/PoseStamped", "cdr"): _pose_cdr,
}


def decoder(msgtype: str, encoding: str, sample: bytes) -> Decoder | None:
    """The direct decoder of a type and encoding, None when there is none (or CDR is big-endian)."""
    if encoding == "cdr" and sample[:2] != b"\x00\x01":
        return None
    return DECODERS.get((msgtype, encoding))

"""`posecorr ingest`."""
from __future__ import annotations

import argparse
from pathlib import Path

from . import options
from .common import CliError, TABLE, Verb, emit


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("recording", type=Path, nargs="+",
                   help="a ROS 1 .bag, a ROS 2 bag directory (or its .db3/.mcap), an .mcap file, or one or two CSV logs")
    p.add_argument("-o", "--output", type=options.file_name, required=True,
                   help="the table; its segment list goes beside it (OUT.segments.json)")
    p.add_argument("--robot", default="ur5e", help="ur3, ur5, ur10, ur3e, ur5e, ur10e, ur16e, or a .urdf file")
    p.add_argument("--base-link", help="URDF: the base link (default: the root)")
    p.add_argument("--tip-link", help="URDF: the flange link (default: tool0, else the only end link)")
    p.add_argument("--tool", default="paper",
                   help="end_T_tracker: paper (eq. 22: 42 mm along the flange z), none, or x,y,z[,qw,qx,qy,qz]")
    p.add_argument("--registration", default="paper",
                   help="base_T_(tracker frame): paper (eq. 23), none (poses already in the base frame), "
                        "or x,y,z,qw,qx,qy,qz")
    p.add_argument("--joints", help="joint-state topic (default: the only sensor_msgs/JointState one, "
                   "else /joint_states or /ur/joint_states)")
    p.add_argument("--tracker", help="tracker topic: PoseStamped, PoseWithCovarianceStamped, Odometry, "
                   "TransformStamped or TF (default: the only one)")
    p.add_argument("--tracker-frame", help="TF: the tracker's child frame (default: the only one)")
    p.add_argument("--joint-names", help="the robot's joints in the message, comma-separated, in kinematic order "
                   "(default: the model's names, as they are or after one common prefix such as a driver's "
                   "tf_prefix; messages that name no joints are read in their order)")
    p.add_argument("--stamps", choices=("header", "receive"), default="header",
                   help="header stamps (unset ones fall back to the receive time) or the recorder's receive times")
    p.add_argument("--time-col", default="t", help="CSV: time column (s)")
    p.add_argument("--joint-cols", default="q1,q2,q3,q4,q5,q6", help="CSV: joint-angle columns (rad)")
    p.add_argument("--pose-cols", default="x,y,z,qw,qx,qy,qz",
                   help="CSV: tracker pose columns, the position x, y, z (m), then the unit quaternion in the order "
                        "w, x, y, z (scalar first: for a log written x, y, z, w, name its w column first)")
    p.add_argument("--still-speed", type=options.real(0, 100, open_lo=True), default=0.01,
                   help="rad/s: still = every joint slower (default 0.01)")
    p.add_argument("--min-still", type=options.real(0, 86_400, open_lo=True), default=2.0,
                   help="s: shortest still segment (default 2)")
    p.add_argument("--settle", type=options.real(0, 86_400), default=0.5,
                   help="s dropped at both ends of a segment (default 0.5)")
    p.add_argument("--gate-mm", type=options.real(0, 1e4, open_lo=True), default=1.0,
                   help="mm: RMS gate on tracker samples over 0.1 s about the segment median (default 1)")
    p.add_argument("--max-jitter-mm", type=options.real(0, 1e4, open_lo=True), default=0.5,
                   help="mm: reject a segment whose kept samples scatter more (RMS, default 0.5)")
    p.add_argument("--min-samples", type=options.integer(1, 10_000_000), default=100,
                   help="reject a segment with fewer kept samples (default 100)")
    # Any finite offset: a tracker stamped on its boot clock is ~1.7e9 s behind a robot on Unix time.
    p.add_argument("--offset", type=options.real(),
                   help="s, tracker clock - robot clock (default: estimated); for a bag stamped on two clocks, "
                        "--stamps receive")
    p.add_argument("--max-offset", type=options.real(0, 3600, open_lo=True), default=5.0,
                   help="s: the offset search range (default 5)")
    p.add_argument("--session", help="the table's session column (default: the recording's name)")


def run(args: argparse.Namespace) -> None:
    from ..data import write_table
    from ..textui import counted
    from ..ingest import IngestOptions, ingest, write_segments
    from ..ingest.csvlog import CsvColumns
    from ..ingest.pipeline import parse_transform
    from ..ingest.segments import StillOptions

    def names(text: str, option: str = "") -> tuple[str, ...]:
        found = tuple(n.strip() for n in text.split(",") if n.strip())
        twice = sorted({n for n in found if found.count(n) > 1})
        if twice:
            raise CliError(f"{option}: {twice[0]!r} is named twice")
        return found

    options = IngestOptions(
        robot=args.robot, base_link=args.base_link, tip_link=args.tip_link,
        tool=parse_transform(args.tool, "tool"), registration=parse_transform(args.registration, "registration"),
        joints_topic=args.joints, tracker_topic=args.tracker, tracker_frame=args.tracker_frame, stamps=args.stamps,
        joint_names=names(args.joint_names, "--joint-names") if args.joint_names else None,
        csv=CsvColumns(args.time_col, names(args.joint_cols, "--joint-cols"), names(args.pose_cols, "--pose-cols")),
        still=StillOptions(args.still_speed, args.min_still, args.settle, args.gate_mm, args.max_jitter_mm,
                           args.min_samples),
        offset=args.offset, max_offset=args.max_offset, session=args.session)
    from ..ingest.pipeline import segments_path
    from ..safeio import check_output

    # The segment list goes beside the table: a path there that cannot take it fails now,
    # before the table is written.
    check_output(segments_path(args.output), args.recording)
    result = ingest(args.recording, options)
    write_table(result.table, args.output)
    sidecar = write_segments(result, args.output)
    summary = result.summary()
    payload = {"output": str(args.output), "segments_file": str(sidecar), **summary}

    def text() -> str:
        a = result.alignment
        how = (f"estimated, speed correlation {a.correlation:.3f}" if a.source == "estimated" else "given")
        rates = f"{summary['joint_samples']} joint states"
        if summary["joint_rate_hz"]:
            rates += f" ({summary['joint_rate_hz']:.0f} Hz)"
        rates += f", {summary['tracker_samples']} tracker poses"
        if summary["tracker_rate_hz"]:
            rates += f" ({summary['tracker_rate_hz']:.0f} Hz)"
        lines = [f"{', '.join(map(str, args.recording))}: {rates}"] + [f"note: {note}" for note in result.notes] + [
                 f"clock offset tracker - robot: {a.offset:+.4f} s ({how})",
                 f"{counted(len(result.segments), 'still segment')}: {counted(result.table.n, 'row')} -> {args.output}, "
                 f"{len(result.rejected)} rejected"]
        lines += [f"  rejected segment {s.index} (t {s.start - result.t0:.1f}..{s.end - result.t0:.1f} s): {s.reason}"
                  for s in result.rejected]
        jitter = result.table.extras["jitter_mm"]
        lines.append(f"jitter {jitter.min():.3f}..{jitter.max():.3f} mm; segments -> {sidecar}")
        return "\n".join(lines)

    emit(args, payload, text)


VERB = Verb(
    help="a recording (ROS 1/2 bag, MCAP, CSV log) -> the paired-pose table",
    rank=2,
    outputs={"output": TABLE},
    folder_inputs=("recording",),  # a ROS 2 bag is a folder
    add_arguments=add_arguments,
    run=run,
)
